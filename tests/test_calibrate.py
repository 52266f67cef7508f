"""``crtk-ctl calibrate`` end to end (issue 12): the real daemon on the simulated SO-101, the tool
driven through a scripted stdin, the joints moved by hand through the simulator's control socket
(``hand``: a torque-off servo turned at a bounded speed). The calibration written into a copy of
profiles/so101.yaml (comments kept) has offsets and ranges within a few ticks of the sweep, and
the restarted daemon reports angles from it. Refused while ENABLED."""

from __future__ import annotations

import math
import subprocess
import sys
import threading

import pytest

from crtk_bridge.client import CommandError, connect
from crtk_bridge.profile import load_profile
from crtk_bridge.sim.control import control_request

from .conftest import KOCH, ROOT, SO101, SO101_URDF, DaemonProcess, wait_until

TICKS = 4096
#: the simulated arm's travel per joint (Present_Position ticks), swept by hand
SWEEP = {"shoulder_pan": (650, 3450), "shoulder_lift": (800, 3300), "elbow_flex": (900, 3200),
         "wrist_flex": (950, 3150), "wrist_roll": (10, 4090), "gripper": (1900, 3300)}
IDS = {"shoulder_pan": 1, "shoulder_lift": 2, "elbow_flex": 3, "wrist_flex": 4, "wrist_roll": 5, "gripper": 6}
HAND_SPEED = 5000.0  # ticks/s
TOLERANCE = 3  # ticks


#: a comment line of each robot's profile, to show the written profile kept its comments
COMMENT = {SO101: "# SIGTERM / Ctrl-C with the arm ENABLED", KOCH: "# Re-measure calibration (offset, direction"}
SOURCE: dict = {}  # copied profile -> the profile it is a copy of
BOTH = pytest.mark.parametrize("profile", [SO101, KOCH], ids=["so101-feetech", "koch-dynamixel"], indirect=True)


@pytest.fixture
def profile(request, short_tmp):
    """A robot's profile (profiles/so101.yaml unless parametrized) copied with its comments, its
    URDF path made absolute."""
    src = getattr(request, "param", SO101)
    path = short_tmp / "arm.yaml"
    path.write_text(SO101.read_text().replace("urdf: urdf/so101.urdf", f"urdf: {SO101_URDF}") if src == SO101
                    else src.read_text())
    SOURCE[path] = src
    return path


def arm_ns(profile) -> tuple[str, str]:
    """(arm namespace, gripper namespace) of the copied profile."""
    p = load_profile(profile)
    return p.namespaces[0].name, p.namespaces[1].name


@pytest.fixture
def daemon(short_tmp, profile):
    d = DaemonProcess(["--profile", str(profile), "--sim"], short_tmp / "arm.sock", short_tmp / "daemon.log")
    yield d
    d.stop()


class Tool:
    """``crtk-ctl calibrate`` as a subprocess with a scripted stdin and its output collected."""

    def __init__(self, socket: str, *args: str):
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "crtk_bridge.client.cli", "calibrate", "--socket", socket, *args],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, cwd=ROOT, text=True)
        self.lines: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self):
        for line in self.proc.stdout:
            self.lines.append(line.rstrip("\n"))

    def output(self) -> str:
        return "\n".join(self.lines)

    def expect(self, text: str, timeout: float = 10.0) -> None:
        wait_until(lambda: any(text in line for line in self.lines) or self.proc.poll() is not None, timeout,
                   what=f"{text!r} from crtk-ctl calibrate")
        assert any(text in line for line in self.lines), self.output()

    def enter(self) -> None:
        self.proc.stdin.write("\n")
        self.proc.stdin.flush()

    def finish(self, timeout: float = 15.0) -> int:
        try:
            self.proc.stdin.close()
        except BrokenPipeError:
            pass
        code = self.proc.wait(timeout)
        self._reader.join(2.0)
        return code

    def kill(self):
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


def hand_all(sim: str, targets: dict[str, int]) -> None:
    """Turn every named joint by hand to its target (at once), then wait until all got there."""
    for name, pos in targets.items():
        reply = control_request(sim, {"cmd": "hand", "id": IDS[name], "position": pos, "speed": HAND_SPEED})
        assert reply["ok"], reply

    def there():
        return all(control_request(sim, {"cmd": "read", "id": IDS[n], "register": "Present_Position"})["value"] == p
                   for n, p in targets.items())

    wait_until(there, 5, what=f"joints moved by hand to {targets}")


@BOTH
def test_scripted_sweep_writes_offsets_and_ranges_and_the_restarted_daemon_uses_them(short_tmp, profile, daemon):
    sim = daemon.sim_control_path()
    tool = Tool(str(daemon.socket_path), "--profile", str(profile))
    try:
        tool.expect("1/3")
        tool.enter()  # the simulated arm rests at the middle of its turn
        tool.expect("2/3")
        hand_all(sim, {n: lo for n, (lo, hi) in SWEEP.items()})
        hand_all(sim, {n: hi for n, (lo, hi) in SWEEP.items()})
        hand_all(sim, {n: (lo + hi) // 2 for n, (lo, hi) in SWEEP.items() if n != "gripper"})
        tool.enter()
        tool.expect("3/3")
        hand_all(sim, {"gripper": SWEEP["gripper"][0]})  # closed
        tool.enter()
        assert tool.finish() == 0, tool.output()
    finally:
        tool.kill()
    out = tool.output()
    assert "[" in out and "|" in out and "deg" in out, out  # the range bars were shown
    assert f"Wrote {profile}" in out, out

    text = profile.read_text()
    assert COMMENT[SOURCE[profile]] in text  # comments kept
    cal = {j.name: j.backend["calibration"] for j in load_profile(profile).joints}
    for name, (lo, hi) in SWEEP.items():
        c = cal[name]
        if name == "wrist_roll":  # swept over the whole turn: continuous, zero at the middle pose
            assert c["range"] == [0, TICKS - 1] and abs(c["offset"] - 2048) <= TOLERANCE, c
            continue
        assert abs(c["range"][0] - lo) <= TOLERANCE and abs(c["range"][1] - hi) <= TOLERANCE, (name, c)
        want = lo if name == "gripper" else (lo + hi) // 2  # gripper: zero at its closed end
        assert abs(c["offset"] - want) <= TOLERANCE and c["direction"] == 1, (name, c)
        assert c["homing_offset"] == 0, c  # read from the servo: the ticks were measured with it

    # the daemon uses it after a restart: a hand position reads as the calibration says
    daemon.stop()
    again = DaemonProcess(["--profile", str(profile), "--sim"], short_tmp / "arm2.sock", short_tmp / "d2.log")
    try:
        sim = again.sim_control_path()
        hand_all(sim, {"shoulder_pan": 3000, "gripper": 2500})
        robot = connect(socket=str(again.socket_path))
        try:
            def angle(ns: str, k: int) -> float:
                return robot.device(ns).measured_jp()[0][k]

            arm, grip = arm_ns(profile)
            want = (3000 - cal["shoulder_pan"]["offset"]) * 2 * math.pi / TICKS
            wait_until(lambda: abs(angle(arm, 0) - want) < 1.5 * 2 * math.pi / TICKS, 3, what="shoulder_pan angle")
            want = (2500 - cal["gripper"]["offset"]) * 2 * math.pi / TICKS
            wait_until(lambda: abs(angle(grip, 0) - want) < 1.5 * 2 * math.pi / TICKS, 3, what="gripper")
        finally:
            robot.close()
    finally:
        again.stop()


def test_calibrate_is_refused_while_enabled(profile, daemon):
    robot = connect(socket=str(daemon.socket_path))
    try:
        assert robot.device("so101").enable(5.0)
        with pytest.raises(CommandError, match="calibrate needs the robot DISABLED \\(it is ENABLED\\)") as err:
            robot.calibrate("begin")
        assert err.value.code == "invalid_state"
        before = profile.read_text()
        tool = Tool(str(daemon.socket_path), "--profile", str(profile))
        try:
            code = tool.finish()
        finally:
            tool.kill()
        assert code == 1 and "DISABLED" in tool.output() and "ENABLED" in tool.output(), tool.output()
        assert "1/3" not in tool.output()  # refused before asking anything
        assert profile.read_text() == before
        assert robot.device("so101").is_enabled()  # nothing changed
    finally:
        robot.close()
