"""Leader -> follower teleoperation (crtk_bridge/client/teleop.py, ``crtk-ctl teleop``): two simulated
SO-101 daemons, the leader DISABLED (torque off) and moved by the simulator's hand, the follower
ENABLED. Proves: teleop never enables the follower; it sends nothing until the operator aligned
the leader (the follower does not move toward a far leader); then the follower tracks the
leader; a leader that goes away ends teleop with an error naming it and the follower holds."""

from __future__ import annotations

import re
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

import numpy as np
import pytest
import yaml

from crtk_bridge.client import connect
from crtk_bridge.client.teleop import ALIGNING, DISABLED, ENABLED, Pair, Teleop, TeleopError, pair_namespaces
from crtk_bridge.profile import load_profile, resolve_profile_arg, shipped_profiles_dir
from crtk_bridge.sim.control import control_request

from .conftest import ROOT, SO101, DaemonProcess, _counts_per_rad, profile_data, wait_until


@pytest.fixture(scope="module")
def rig():
    d = Path(tempfile.mkdtemp(prefix="crtk-"))
    data = profile_data(SO101)
    data["name"] = "so101_leader"
    leader_profile = d / "leader.yaml"
    leader_profile.write_text(yaml.safe_dump(data))
    follower = DaemonProcess(["--profile", str(SO101), "--sim"], d / "f.sock", d / "f.log")
    try:
        leader = DaemonProcess(["--profile", str(leader_profile), "--sim"], d / "l.sock", d / "l.log")
    except BaseException:
        follower.stop()
        raise
    yield leader, follower, load_profile(leader_profile)
    leader.stop()
    follower.stop()
    shutil.rmtree(d, ignore_errors=True)


def hand_move(leader: DaemonProcess, profile, joint: str, delta_rad: float) -> None:
    """Turn the leader's ``joint`` by ``delta_rad`` by hand (its servo is torque off)."""
    j = next(j for j in profile.joints if j.name == joint)
    sid = j.backend["id"]
    ctl = leader.sim_control_path()
    now = control_request(ctl, {"cmd": "read", "id": sid, "register": "Present_Position"})["value"]
    target = int(round(now + delta_rad * _counts_per_rad(j)))
    reply = control_request(ctl, {"cmd": "hand", "id": sid, "position": target, "speed": 3000})
    assert reply["ok"], reply


class Recorder:
    def __init__(self):
        self.lines: list[tuple[str, str]] = []
        self.lock = threading.Lock()

    def __call__(self, state: str, message: str) -> None:
        with self.lock:
            self.lines.append((state, message))

    def saw(self, state: str, text: str = "") -> bool:
        with self.lock:
            return any(s == state and text in m for s, m in self.lines)


def start(teleop: Teleop) -> tuple[threading.Thread, list]:
    errors: list = []

    def run():
        try:
            teleop.run()
        except BaseException as exc:  # noqa: BLE001 - reported to the test
            errors.append(exc)

    t = threading.Thread(target=run, daemon=True)
    t.start()
    return t, errors


def test_teleop_refuses_a_disabled_follower_and_never_enables_it(rig):
    leader, follower, _ = rig
    with connect(socket=str(leader.socket_path)) as lead, connect(socket=str(follower.socket_path)) as fol:
        assert fol.device().operating_state() == "DISABLED"
        with pytest.raises(TeleopError, match=r"follower 'so101' is DISABLED: teleop never enables a robot"):
            Teleop(lead, fol).run()
        assert fol.device().operating_state() == "DISABLED"


def test_crtk_ctl_teleop_refuses_a_rate_above_the_followers_loop_rate(rig, capsys):
    from crtk_bridge.client.cli import main

    leader, follower, _ = rig
    assert main(["teleop", "--leader", str(leader.socket_path), "--follower", str(follower.socket_path),
                 "--rate", "1000"]) == 1
    assert capsys.readouterr().err.strip().splitlines() == [
        "crtk-ctl: --rate (rate_hz): must be from 10 to 200 Hz (the loop rate of the follower 'so101'), got 1000"]


def test_teleop_waits_for_alignment_then_the_follower_tracks_the_leader(rig):
    leader, follower, profile = rig
    with connect(socket=str(leader.socket_path)) as lead, connect(socket=str(follower.socket_path)) as fol:
        arm = fol.device("so101")
        assert arm.enable(10)
        rec = Recorder()
        # 0.3 rad: beyond the tolerance, yet within safety.servo_step_max (0.35), so only teleop's
        # own alignment check keeps the follower from jumping there
        hand_move(leader, profile, "elbow_flex", 0.3)
        wait_until(lambda: abs(lead.device("so101").measured_jp()[0][2] - arm.measured_jp()[0][2]) > 0.28, 5,
                   what="the leader's elbow 0.3 rad away from the follower's")
        before = arm.measured_jp()[0]
        t = Teleop(lead, fol, rate_hz=50, tolerance=0.1, on_state=rec)
        thread, errors = start(t)
        try:
            wait_until(lambda: rec.saw(ALIGNING, "'elbow_flex'"), 5, what="ALIGNING naming elbow_flex")
            # nothing was sent: the follower did not move toward the far leader
            assert t.state == ALIGNING
            assert np.allclose(arm.measured_jp()[0], before, atol=0.02)
            hand_move(leader, profile, "elbow_flex", -0.3)  # the operator brings the leader back
            wait_until(lambda: t.state == ENABLED, 5, what="teleop ENABLED once aligned")
            hand_move(leader, profile, "wrist_flex", 0.3)
            hand_move(leader, profile, "shoulder_pan", -0.25)
            lead_arm = lead.device("so101")

            def tracking() -> bool:
                err = np.abs(arm.measured_jp()[0] - lead_arm.measured_jp()[0])
                return err.max() < 0.03 and abs(arm.measured_jp()[0][3] - before[3]) > 0.25

            wait_until(tracking, 8, what="the follower at the leader's pose (wrist_flex +0.3, shoulder_pan -0.25)")
            # the gripper pair follows too
            hand_move(leader, profile, "gripper", 0.3)
            wait_until(lambda: abs(fol.device("so101/gripper").measured_jp()[0][0]
                                   - lead.device("so101/gripper").measured_jp()[0][0]) < 0.03
                       and abs(fol.device("so101/gripper").measured_jp()[0][0]) > 0.2, 8,
                       what="the follower's gripper at the leader's")
        finally:
            t.stop()
            thread.join(5)
        assert not errors, errors
        assert t.state == DISABLED and arm.operating_state() == "ENABLED"  # ending never disables


def test_a_paused_follower_is_waited_for_and_can_be_resumed_by_the_operator(rig):
    """A follower PAUSED under teleop (a stop from another session): teleop goes back to
    ALIGNING and stays there -- it never claims to follow a PAUSED robot -- and gives up control
    so the operator can resume it from another session (crtk-ctl resume); then it takes control
    again and follows once aligned."""
    leader, follower, _ = rig
    with connect(socket=str(leader.socket_path)) as lead, connect(socket=str(follower.socket_path)) as fol:
        arm = fol.device("so101")
        if arm.operating_state() != "ENABLED":  # the test before leaves it so; alone, enable it
            assert arm.enable(10)
        rec = Recorder()
        t = Teleop(lead, fol, rate_hz=50, tolerance=0.1, on_state=rec)
        steps = [0]
        step = t._step

        def counted() -> None:
            steps[0] += 1
            step()

        t._step = counted
        thread, errors = start(t)
        try:
            wait_until(lambda: t.state == ENABLED, 5, what="teleop ENABLED")
            with connect(socket=str(follower.socket_path)) as op:
                assert op.device("so101").pause()  # a stop from any session
            wait_until(lambda: rec.saw(ALIGNING, "PAUSED"), 5, what="ALIGNING: the follower PAUSED")
            with rec.lock:
                seen = len(rec.lines)
            at = steps[0]
            wait_until(lambda: steps[0] >= at + 10, 5, what="ten teleop ticks while PAUSED")
            with rec.lock:
                during = [s for s, _ in rec.lines[seen:]]
            assert ENABLED not in during, rec.lines[seen:]  # nothing sent, no 'following' while PAUSED
            assert t.state == ALIGNING
            with connect(socket=str(follower.socket_path)) as op:  # the operator resumes it
                assert op.device("so101").resume(5)
            wait_until(lambda: t.state == ENABLED, 5, what="teleop following again after resume")
        finally:
            t.stop()
            thread.join(5)
        assert not errors, errors
        assert arm.operating_state() == "ENABLED"


def test_crtk_ctl_teleop_follows_and_a_lost_leader_ends_it_with_the_follower_holding(rig):
    leader, follower, profile = rig
    with connect(socket=str(follower.socket_path)) as fol:
        arm = fol.device("so101")
        assert arm.operating_state() == "ENABLED"  # left so by the test before
        proc = subprocess.Popen(
            [sys.executable, "-m", "crtk_bridge.client.cli", "teleop", "--leader", str(leader.socket_path),
             "--follower", str(follower.socket_path), "--align", "move", "--rate", "40"],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, cwd=ROOT, text=True)
        try:
            lines: list[str] = []

            def read() -> None:
                for line in proc.stdout:
                    lines.append(line)

            reader = threading.Thread(target=read, daemon=True)
            reader.start()
            wait_until(lambda: any("teleop ENABLED" in x for x in lines), 15, what="crtk-ctl teleop ENABLED")
            leader.stop()
            assert proc.wait(10) == 1
            reader.join(5)
            out = "".join(lines)
            assert "leader 'so101_leader' went away" in out, out
        finally:
            if proc.poll() is None:
                proc.kill()
        held = arm.measured_jp()[0]
        assert arm.operating_state() == "ENABLED"
        wait_until(lambda: np.allclose(arm.measured_jp()[0], held, atol=0.01), 3, what="the follower holding")


class _Ns:
    def __init__(self, name: str, joints: list[str]):
        self.name, self.joint_names = name, joints

    def supports(self, cmd: str) -> bool:
        return True


class _Bot:
    def __init__(self, name: str, namespaces: dict[str, list[str]]):
        self.name, self.namespaces = name, list(namespaces)
        self._ns = {ns: _Ns(ns, joints) for ns, joints in namespaces.items()}

    def device(self, name: str) -> _Ns:
        return self._ns[name]


def test_joints_paired_by_position_must_not_be_named_joints_of_the_other_order():
    """Joint i follows joint i: a leader listing the follower's joints in another order would
    drive each joint with another joint's angle. Refused, naming both; joints named alike in
    the same order, or not sharing names at all (another kind of arm), pair."""
    arm = ["shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll"]
    swapped = ["shoulder_pan", "shoulder_lift", "wrist_flex", "elbow_flex", "wrist_roll"]
    follower = _Bot("so101", {"so101": arm})
    with pytest.raises(TeleopError, match=r"so101_leader -> so101: leader joint 2 is 'wrist_flex', "
                                          r"follower joint 2 is 'elbow_flex'.*'wrist_flex' is follower joint 3"):
        pair_namespaces(_Bot("so101_leader", {"so101_leader": swapped}), follower)
    assert len(pair_namespaces(_Bot("so101_leader", {"so101_leader": list(arm)}), follower)) == 1
    assert len(pair_namespaces(_Bot("other", {"other": ["j1", "j2", "j3", "j4", "j5"]}), follower)) == 1


def test_a_non_finite_leader_position_is_never_followed_nor_counted_aligned():
    """A leader reading NaN / inf (a broken sensor, a bad calibration) is no position: teleop treats
    it as invalid data (the follower holds in ALIGNING) instead of counting it aligned (NaN > the
    tolerance is false) and streaming it."""

    class Leader(_Ns):
        def measured_jp(self):
            return np.array([0.0, np.nan, 0.0, np.inf, 0.0]), 1.0

    t = Teleop.__new__(Teleop)
    t.leader = _Bot("so101_leader", {})
    arm = ["shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll"]
    pair = Pair(Leader("so101_leader", arm), _Ns("so101", arm))
    assert t._leader_position(pair) is None


class _Daemon(_Bot):
    """A robot as Teleop's constructor sees it: its socket path and loop rate (``list``)."""

    def __init__(self, name: str, rate_hz: float):
        super().__init__(name, {name: ["j1", "j2"]})
        self.info = {"rate_hz": rate_hz}
        self.connection = type("Conn", (), {"path": f"/tmp/{name}.sock"})()


@pytest.mark.parametrize("rate, why", [
    (0.0, "got 0"), (-5.0, "got -5"), (9.5, "got 9.5"), (float("nan"), "got nan"), (float("inf"), "got inf"),
    (200.5, "got 200.5"),
])
def test_a_rate_out_of_range_is_refused_naming_the_option_and_the_range(rate, why):
    with pytest.raises(TeleopError) as refused:
        Teleop(_Daemon("lead", 1000.0), _Daemon("follow", 200.0), rate_hz=rate)
    assert str(refused.value) == (f"--rate (rate_hz): must be from 10 to 200 Hz (the loop rate of the follower "
                                  f"'follow'), {why}")


def test_the_rate_is_capped_by_the_slower_daemon_and_defaults_within_it():
    with pytest.raises(TeleopError, match=r"^--rate \(rate_hz\): must be from 10 to 100 Hz \(the loop rate of the "
                                          r"leader 'lead'\), got 150$"):
        Teleop(_Daemon("lead", 100.0), _Daemon("follow", 200.0), rate_hz=150)
    assert Teleop(_Daemon("lead", 100.0), _Daemon("follow", 200.0), rate_hz=100).period == pytest.approx(0.01)
    assert Teleop(_Daemon("lead", 1000.0), _Daemon("follow", 200.0)).period == pytest.approx(1 / 50)
    assert Teleop(_Daemon("lead", 1000.0), _Daemon("follow", 30.0)).period == pytest.approx(1 / 30)  # not refused


@pytest.mark.parametrize("tolerance", [0.0, -0.1, 0.009, 0.31, float("nan"), float("inf"), float("-inf")])
def test_a_tolerance_out_of_range_is_refused_naming_the_option_and_the_range(tolerance):
    with pytest.raises(TeleopError) as refused:
        Teleop(_Daemon("lead", 200.0), _Daemon("follow", 200.0), tolerance=tolerance)
    assert str(refused.value) == f"--tolerance (tolerance): must be from 0.01 to 0.3 rad, got {tolerance:g}"
    assert Teleop(_Daemon("lead", 200.0), _Daemon("follow", 200.0), tolerance=0.3).tolerance == 0.3


@pytest.mark.parametrize("option, value, allowed", [
    ("--rate", "nan", "must be from 10 to the daemons' loop rate (Hz), got nan"),
    ("--rate", "5", "must be from 10 to the daemons' loop rate (Hz), got 5"),
    ("--rate", "inf", "must be from 10 to the daemons' loop rate (Hz), got inf"),
    ("--tolerance", "0.5", "must be from 0.01 to 0.3 rad, got 0.5"),
    ("--tolerance", "0", "must be from 0.01 to 0.3 rad, got 0"),
    ("--tolerance", "nan", "must be from 0.01 to 0.3 rad, got nan"),
    ("--tolerance", "x", "expected a number, got 'x'"),
])
def test_crtk_ctl_teleop_refuses_out_of_range_options_before_connecting(capsys, option, value, allowed):
    from crtk_bridge.client.cli import main

    assert main(["teleop", "--leader", "/nonexistent/l.sock", "--follower", "/nonexistent/f.sock",
                 option, value]) == 2
    assert capsys.readouterr().err.strip().splitlines()[-1] == f"crtk-ctl teleop: error: argument {option}: {allowed}"


@pytest.mark.parametrize("option, kwargs, shown", [
    ("--rate (rate_hz)", {"rate_hz": "x"}, "'x'"), ("--rate (rate_hz)", {"rate_hz": True}, "True"),
    ("--tolerance (tolerance)", {"tolerance": None}, "None"), ("--tolerance (tolerance)", {"tolerance": "0.1"}, "'0.1'"),
])
def test_an_ill_typed_rate_or_tolerance_is_a_teleop_error_naming_the_option(option, kwargs, shown):
    with pytest.raises(TeleopError) as refused:
        Teleop(_Daemon("lead", 200.0), _Daemon("follow", 200.0), **kwargs)
    assert str(refused.value) == f"{option}: expected a number, got {shown}"
    assert Teleop(_Daemon("lead", 200.0), _Daemon("follow", 200.0), rate_hz=np.int64(20)).period == pytest.approx(0.05)


def _fenced_sh(doc: Path, first_line: str) -> list[str]:
    """The lines of the ```sh block of ``doc`` that starts with ``first_line``."""
    blocks = re.findall(r"```sh\n(.*?)```", doc.read_text(), re.S)
    block = next(b for b in blocks if b.startswith(first_line))
    return [ln for ln in block.splitlines() if ln.strip()]


@pytest.mark.parametrize("pair", ["so101", "koch"])
def test_docs_teleop_example_runs_verbatim_from_the_installed_package_with_the_shipped_leaders(installed, pair):
    """docs/teleop.md's example, each line run as written (the Koch pair with its names swapped in)
    from a folder outside the clone on a non-editable install: both daemons on --sim, the follower
    enabled, teleop started; turning the leader simulator's joints by hand moves the follower."""
    lines = _fenced_sh(ROOT / "docs" / "teleop.md", "crtk-bridge --profile profiles/so101_leader.yaml")
    assert len(lines) == 4
    if pair == "koch":
        lines = [ln.replace("so101", "koch") for ln in lines]
    cwd = installed.cwd(f"teleop-{pair}")
    runtime = installed.runtime / "crtk-bridge"
    procs: list[subprocess.Popen] = []
    logs: list[Path] = []
    try:
        for k, line in enumerate(lines):
            command = shlex.split(line, comments=True)
            if command[-1] == "&":  # a daemon in the background: wait for its socket
                logs.append(cwd / f"daemon{k}.log")
                procs.append(installed.popen(command[:-1], cwd, logs[-1]))
                robot = load_profile(resolve_profile_arg(command[2])).name
                wait_until(lambda: (runtime / f"{robot}.sock").exists() or procs[-1].poll() is not None, 60,
                           what=f"{robot}'s daemon socket")
                assert procs[-1].poll() is None, logs[-1].read_text()
            elif command[1] == "teleop":  # runs until Ctrl-C
                logs.append(cwd / "teleop.log")
                procs.append(installed.popen(command, cwd, logs[-1]))
            else:
                done = installed.run(command, cwd)
                assert done.returncode == 0, done.stdout + done.stderr
        teleop, leader_log = procs[-1], logs[0]
        wait_until(lambda: "teleop ENABLED" in logs[-1].read_text() or teleop.poll() is not None, 20,
                   what="crtk-ctl teleop ENABLED")
        assert teleop.poll() is None, logs[-1].read_text()
        leader_profile = load_profile(shipped_profiles_dir() / f"{pair}_leader.yaml")
        sim = next(ln.rsplit(" ", 1)[-1].rstrip(")") for ln in leader_log.read_text().splitlines()
                   if "simulator control socket" in ln)
        joint = next(j for j in leader_profile.joints if j.name == "wrist_flex")
        now = control_request(sim, {"cmd": "read", "id": joint.backend["id"], "register": "Present_Position"})["value"]
        target = int(round(now + 0.3 * _counts_per_rad(joint)))
        assert control_request(sim, {"cmd": "hand", "id": joint.backend["id"], "position": target, "speed": 3000})["ok"]
        with connect(socket=str(runtime / f"{pair}.sock")) as fol:
            arm = fol.device(pair)
            wait_until(lambda: abs(arm.measured_jp()[0][3] - 0.3) < 0.03, 10,
                       what=f"the follower {pair}'s wrist_flex at the leader's +0.3 rad")
        teleop.send_signal(signal.SIGINT)
        assert teleop.wait(10) == 130, logs[-1].read_text()
    finally:
        for proc in reversed(procs):
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT if proc is procs[-1] else signal.SIGTERM)
                try:
                    proc.wait(20)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()


def test_koch_leader_trigger_commands_of_its_profile_torque_the_gripper_only_in_current_based_position(short_tmp):
    """profiles/koch_leader.yaml's comments give the commands that make its gripper a spring-loaded
    trigger (LeRobot's koch_leader): run as written, the arm's servos end torque off (moved by hand)
    and the gripper's torqued in current-based position mode (5), at the commanded rest."""
    path = shipped_profiles_dir() / "koch_leader.yaml"
    commands = [shlex.split(ln.lstrip("# "), comments=True) for ln in path.read_text().splitlines()
                if ln.startswith("#   crtk-ctl --robot koch_leader")]
    assert len(commands) == 3
    d = DaemonProcess(["--profile", str(path), "--sim"], short_tmp / "kl.sock", short_tmp / "kl.log")
    try:
        for command in commands:
            assert command[:3] == ["crtk-ctl", "--robot", "koch_leader"]
            done = subprocess.run([sys.executable, "-m", "crtk_bridge.client.cli", "--socket", str(d.socket_path),
                                   *command[3:]], capture_output=True, text=True, cwd=ROOT, timeout=30)
            assert done.returncode == 0, done.stdout + done.stderr
        sim = d.sim_control_path()

        def reg(sid: int, name: str) -> int:
            return control_request(sim, {"cmd": "read", "id": sid, "register": name})["value"]

        assert [reg(i, "Torque_Enable") for i in range(1, 7)] == [0, 0, 0, 0, 0, 1]
        assert reg(6, "Operating_Mode") == 5 and reg(1, "Operating_Mode") == 4
        with connect(socket=str(d.socket_path)) as leader:
            assert leader.device("koch_leader").operating_state() == "ENABLED"
            assert abs(leader.device("koch_leader/gripper").measured_jp()[0][0] - 0.6) < 0.02
    finally:
        d.stop()
