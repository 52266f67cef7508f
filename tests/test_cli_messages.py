"""What a new user meets at the command line: one-line errors (never a traceback), versions, help
that says what to type, JSON errors under --json, messages that neither repeat the robot nor print
309 digits."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from crtk_bridge import __version__
from crtk_bridge.cli import main as bridge_main
from crtk_bridge.client.cli import _fmt_event
from crtk_bridge.client.cli import main as ctl_main
from crtk_bridge.client.connection import Event
from crtk_bridge.daemon import AF_UNIX_PATH_MAX
from crtk_bridge.errors import fmt_number

from .conftest import ROOT, SO101, only_on


def run(module: str, *args: str, timeout: float = 60.0) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", module, *args], capture_output=True, text=True,
                          cwd=ROOT, timeout=timeout, stdin=subprocess.DEVNULL)


def one_line_error(proc: subprocess.CompletedProcess) -> str:
    """The process failed with exactly one line on stderr and no traceback; return the line."""
    assert proc.returncode != 0, proc
    assert "Traceback" not in proc.stderr, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    return lines[0]


def ctl(capsys, *args):
    code = ctl_main(list(args))
    out = capsys.readouterr()
    return code, out.out, out.err


# ---------------------------------------------------------------- versions and help

@pytest.mark.parametrize("module, prog", [("crtk_bridge.cli", "crtk-bridge"),
                                          ("crtk_bridge.client.cli", "crtk-ctl"),
                                          ("crtk_bridge.sim.cli", "crtk-sim")])
def test_every_tool_prints_its_version(module, prog):
    proc = run(module, "--version")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == f"{prog} {__version__}"


def test_bridge_help_lists_check(capsys):
    with pytest.raises(SystemExit) as info:
        bridge_main(["--help"])
    assert info.value.code == 0
    out = capsys.readouterr().out
    assert "crtk-bridge check --profile FILE" in out
    assert "check --profile FILE  validate a profile" in out


@pytest.mark.parametrize("cmd", ["move_jp", "move_jr", "servo_jp", "interpolate_jv", "fk"])
def test_joint_vector_help_says_how_many_values_in_which_order(cmd, capsys):
    assert ctl_main([cmd, "-h"]) == 0
    out = " ".join(capsys.readouterr().out.split())  # argparse wraps lines
    assert "one value per joint of the namespace" in out
    assert "in the order `crtk-ctl list` prints its joints" in out
    assert "shoulder_pan shoulder_lift elbow_flex wrist_flex wrist_roll" in out


# ---------------------------------------------------------------- crtk-ctl argument errors

@pytest.mark.parametrize("option, value", [("--timeout", "-1"), ("--timeout", "0"), ("--timeout", "inf"),
                                           ("--timeout", "nan"), ("--timeout", "soon")])
def test_bad_timeout_is_a_usage_error_not_a_traceback(option, value):
    # validated before any connection: no daemon is needed, and none is contacted
    proc = run("crtk_bridge.client.cli", "--socket", "/nonexistent/x.sock", option, value, "state")
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert proc.stderr.strip().splitlines()[-1].startswith(f"crtk-ctl: error: argument {option}: ")


def test_bad_rate_is_a_usage_error(capsys):
    code, _, err = ctl(capsys, "--socket", "/nonexistent/x.sock", "echo", "measured_js", "--rate", "-5")
    assert code == 2 and "argument --rate: must be a finite number > 0, got -5" in err


def test_unknown_query_is_one_line_listing_the_valid_ones():
    line = one_line_error(run("crtk_bridge.client.cli", "--socket", "/nonexistent/x.sock", "get", "measured_jz"))
    assert line.startswith("crtk-ctl get: error: argument TOPIC: invalid choice: 'measured_jz'")
    assert "'measured_js', 'setpoint_js', 'goal_js', 'measured_cp'" in line and "period_statistics" in line
    assert "<" not in line and "Topic." not in line  # no Python enum reprs


@pytest.mark.parametrize("value", ["nan", "inf", "-inf", "0", "-1", "soon"])
def test_bad_duration_is_refused_naming_the_option(value, capsys):
    # validated before any connection: nothing is sent (nan was accepted and sent once)
    code, _, err = ctl(capsys, "--socket", "/nonexistent/x.sock", "servo_jv", "0.1", "0", "0", "0", "0",
                       "--duration", value)
    assert code == 2 and err.count("\n") == 1
    assert err.startswith("crtk-ctl servo_jv: error: argument --duration: ")
    assert "needs --duration" not in err


@pytest.mark.parametrize("module, args, prog", [
    ("crtk_bridge.cli", ["check", "--bogus"], "crtk-bridge check"),
    ("crtk_bridge.cli", ["--bogus"], "crtk-bridge"),
    ("crtk_bridge.cli", ["setup-servos", "--prfile", "x.yaml"], "crtk-bridge setup-servos"),
    ("crtk_bridge.cli", ["init-profile", "--bogus"], "crtk-bridge init-profile"),
    ("crtk_bridge.client.cli", ["--bogus"], "crtk-ctl"),
    ("crtk_bridge.client.cli", ["calibrate", "--bogus"], "crtk-ctl calibrate"),
    ("crtk_bridge.client.cli", ["teleop", "--leader", "a", "--folower", "b"], "crtk-ctl teleop")])
def test_an_unknown_argument_is_named_before_a_missing_required_one(module, args, prog):
    proc = run(module, *args)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    last = proc.stderr.strip().splitlines()[-1]
    unknown = " ".join(a for a in args if a.startswith("--") and a not in ("--leader",))
    assert last.startswith(f"{prog}: error: unrecognized arguments: {unknown}"), proc.stderr
    assert "required" not in proc.stderr
    # with nothing unknown, the missing option is still named
    proc = run("crtk_bridge.cli", "check")
    assert "the following arguments are required: --profile" in proc.stderr


def test_json_usage_error_is_json(capsys):
    code, out, err = ctl(capsys, "--json", "--timeout", "-1", "state")
    assert code == 2 and out == ""
    obj = json.loads(err)
    assert obj["error"] == "usage" and "--timeout" in obj["message"]


def test_json_connection_error_is_json(short_tmp, capsys):
    code, out, err = ctl(capsys, "--json", "--socket", str(short_tmp / "none.sock"), "state")
    assert code == 2 and out == ""
    obj = json.loads(err)
    assert obj == {"error": "no_daemon", "message": obj["message"], "cmd": "state"}
    assert "none.sock" in obj["message"]


# ---------------------------------------------------------------- message formatting

def test_fmt_number_keeps_huge_values_short():
    assert fmt_number(1.5) == "1.5000"
    assert fmt_number(-0.25, sign=True) == "-0.2500"
    assert fmt_number(1e308) == "1e+308"
    assert fmt_number(-1.2345678e9, sign=True) == "-1.235e+09"
    assert fmt_number(float("inf")) == "inf"
    assert fmt_number(float("nan")) == "nan"


def test_event_line_names_the_robot_once():
    ev = Event("status", {"stamp": 12.5, "ns": "so101", "code": "state_changed", "message": "so101: DISABLED"})
    assert _fmt_event(ev) == "12.500  status  state_changed  so101: DISABLED"
    # a message that does not name its namespace gets it in front
    ev = Event("warning", {"stamp": 1.0, "ns": "so101/gripper", "code": "x", "message": "held"})
    assert _fmt_event(ev) == "1.000  warning x  so101/gripper: held"


def test_event_without_a_stamp_prints_when_it_was_received():
    ev = Event("error", {"stamp": 0.0, "ns": "so101", "code": "control_process_died",
                         "message": "so101: the control process stopped; daemon exiting"})
    assert _fmt_event(ev, received=1795710792.8914) == (
        "1795710792.891  error   control_process_died  so101: the control process stopped; daemon exiting")
    assert _fmt_event(ev._replace(data={**ev.data, "stamp": 12.5}), received=99.0).startswith("12.500  error")


# ---------------------------------------------------------------- against a daemon

@only_on("so101-feetech")
@pytest.mark.reuse_daemon  # ends DISABLED: one so101 daemon for both
def test_ctl_refusals_are_short_and_json_under_json(sim_daemon, capsys):
    sock = str(sim_daemon.socket_path)
    assert ctl(capsys, "--socket", sock, "enable")[0] == 0
    code, _, err = ctl(capsys, "--socket", sock, "move_jp", "1e308", "0", "0", "0", "0")
    assert code == 1 and len(err.strip().splitlines()) == 1
    assert "goal 1e+308 rad for joint 'shoulder_pan' is outside its limits [-1.9199, 1.9199]" in err
    assert len(err) < 300, err

    code, out, err = ctl(capsys, "--socket", sock, "--json", "servo_jp", "1e300", "0", "0", "0", "0")
    assert code == 1 and out == ""
    obj = json.loads(err)
    assert obj["error"] == "step_too_large" and obj["cmd"] == "servo_jp"
    assert "would jump 1e+300 rad" in obj["message"] and len(obj["message"]) < 200

    code, out, err = ctl(capsys, "--socket", sock, "--json", "--ns", "nowhere", "state")
    assert code == 1 and json.loads(err)["error"] == "unknown_namespace"
    assert ctl(capsys, "--socket", sock, "disable")[0] == 0


@only_on("so101-feetech")
@pytest.mark.reuse_daemon  # ends DISABLED: one so101 daemon for both
def test_second_daemon_on_a_served_socket_fails_at_once_in_one_line(sim_daemon):
    t0 = time.monotonic()
    proc = run("crtk_bridge.cli", "--profile", str(SO101), "--sim", "--socket", str(sim_daemon.socket_path))
    line = one_line_error(proc)
    assert line == (f"crtk-bridge: so101: another daemon is already serving {sim_daemon.socket_path} "
                    f"(stop it, or give another --socket)")
    # checked before the simulator and the control process: neither started
    assert "simulated" not in proc.stdout and proc.stdout == ""
    assert time.monotonic() - t0 < 20
    assert sim_daemon.proc.poll() is None and sim_daemon.socket_path.exists()  # the first one serves on


def test_socket_path_over_the_af_unix_limit_is_one_line(short_tmp):
    path = str(short_tmp / ("s" * AF_UNIX_PATH_MAX)) + ".sock"
    proc = run("crtk_bridge.cli", "--profile", str(SO101), "--sim", "--socket", path)
    line = one_line_error(proc)
    assert f"socket path {path} is {len(path)} bytes, longer than the AF_UNIX limit of 107" in line
    assert proc.stdout == ""  # nothing started


def test_socket_path_naming_a_regular_file_is_refused_and_kept(short_tmp):
    victim = short_tmp / "notes.txt"
    victim.write_text("keep me")
    proc = run("crtk_bridge.cli", "--profile", str(SO101), "--sim", "--socket", str(victim))
    assert f"{victim} exists and is not a socket" in one_line_error(proc)
    assert victim.read_text() == "keep me"


# ---------------------------------------------------------------- crtk-bridge check: kinematics

def _check_with(tmp_path, capsys, edit) -> tuple[int, str]:
    import yaml

    from .conftest import so101_data

    data = so101_data()
    edit(data)
    path = tmp_path / "arm.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    code = bridge_main(["check", "--profile", str(path)])
    captured = capsys.readouterr()
    return code, captured.err.strip() or captured.out.strip()


def test_check_names_the_tip_frame_key_when_the_urdf_lacks_it(tmp_path, capsys):
    code, err = _check_with(tmp_path, capsys,
                            lambda d: d["namespaces"][0]["kinematics"].update(tip_frame="gripper_tip"))
    assert code == 1 and len(err.splitlines()) == 1
    assert f"{tmp_path / 'arm.yaml'}: namespaces[0] (so101).kinematics.tip_frame: 'gripper_tip' is not a " \
           "link of " in err
    assert "(its links: base_link, " in err and "gripper_frame_link" in err


def test_check_names_the_base_frame_key(tmp_path, capsys):
    code, err = _check_with(tmp_path, capsys,
                            lambda d: d["namespaces"][0]["kinematics"].update(base_frame="world"))
    assert code == 1 and "namespaces[0] (so101).kinematics.base_frame: 'world' is not a link of " in err


def test_check_names_a_joint_missing_from_the_urdf(tmp_path, capsys):
    def rename(d):
        d["joints"][0]["name"] = "shoulder_yaw"
        d["namespaces"][0]["joints"][0] = "shoulder_yaw"
        d["shutdown"]["rest"]["shoulder_yaw"] = d["shutdown"]["rest"].pop("shoulder_pan")  # renamed everywhere

    code, err = _check_with(tmp_path, capsys, rename)
    assert code == 1 and len(err.splitlines()) == 1
    assert "namespaces[0] (so101).joints: 'shoulder_yaw' not a joint of " in err
    assert "(its joints: shoulder_pan, shoulder_lift" in err


def test_check_names_a_joint_unit_the_urdf_contradicts(tmp_path, capsys):
    """A profile's ``unit`` is its URDF's joint kind: rad for a revolute joint, m for a prismatic one."""
    code, err = _check_with(tmp_path, capsys, lambda d: d["joints"][2].update(unit="m"))
    assert code == 1 and len(err.splitlines()) == 1
    assert "joints[2] (elbow_flex).unit: 'm', but " in err and "makes elbow_flex a revolute joint: set unit: rad" in err
    urdf = (ROOT / "profiles" / "urdf" / "so101.urdf").read_text()
    assert urdf.count('<joint name="elbow_flex" type="revolute">') == 1
    (tmp_path / "slide.urdf").write_text(urdf.replace('<joint name="elbow_flex" type="revolute">',
                                                      '<joint name="elbow_flex" type="prismatic">'))
    code, err = _check_with(tmp_path, capsys, lambda d: d["namespaces"][0]["kinematics"].update(urdf="slide.urdf"))
    assert code == 1 and "makes elbow_flex a prismatic joint: set unit: m" in err
    code, err = _check_with(tmp_path, capsys, lambda d: (d["namespaces"][0]["kinematics"].update(urdf="slide.urdf"),
                                                         d["joints"][2].update(unit="m")))
    assert code == 0, err


def test_check_names_a_base_frame_moved_by_a_joint(tmp_path, capsys):
    code, err = _check_with(tmp_path, capsys,
                            lambda d: d["namespaces"][0]["kinematics"].update(base_frame="upper_arm_link"))
    assert code == 1 and "namespaces[0] (so101).kinematics: " in err and "must be fixed to the URDF root" in err


def test_check_reports_the_kinematics_it_validated(capsys):
    assert bridge_main(["check", "--profile", str(SO101)]) == 0
    assert "kinematics so101: base_link -> gripper_frame_link" in capsys.readouterr().out


def test_daemon_refuses_a_bad_tip_frame_before_starting_anything(tmp_path, short_tmp):
    import yaml

    from .conftest import so101_data

    data = so101_data()
    data["namespaces"][0]["kinematics"]["tip_frame"] = "gripper_tip"
    path = tmp_path / "arm.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    proc = run("crtk_bridge.cli", "--profile", str(path), "--sim", "--socket", str(short_tmp / "a.sock"))
    assert "namespaces[0] (so101).kinematics.tip_frame" in one_line_error(proc)
    assert proc.stdout == ""  # neither the simulator nor the control process started


@pytest.mark.parametrize("profile", sorted((ROOT / "profiles").glob("*.yaml")), ids=lambda p: p.name)
def test_every_shipped_profile_passes_check_with_its_kinematics(profile, capsys):
    assert bridge_main(["check", "--profile", str(profile)]) == 0, capsys.readouterr().err
    out = capsys.readouterr().out
    if "kinematics:" in profile.read_text():
        assert "; kinematics " in out


def test_a_failed_sim_start_leaves_no_folder_it_created(short_tmp, monkeypatch):
    """A simulator that does not start: the daemon stops, removing the socket folders it created
    and its --sim work folder (with what the simulator left in it); a folder that was there stays."""
    import tempfile

    from crtk_bridge import daemon
    from crtk_bridge.errors import CrtkBridgeError

    tmp = short_tmp / "tmp"
    tmp.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(tmp))  # where mkdtemp puts the --sim work folder

    def failing(self, profile_path, device, workdir, **kwargs):
        (Path(workdir) / "sim.sock").write_text("")  # what a simulator that died leaves behind
        raise CrtkBridgeError("--sim: the simulator exited with status 1")

    monkeypatch.setattr(daemon.SimulatorProcess, "__init__", failing)
    for parent, kept in ((short_tmp / "run" / "crtk-bridge", None), (short_tmp / "there", short_tmp / "there")):
        if kept is not None:
            kept.mkdir()
        with pytest.raises(CrtkBridgeError, match="exited with status 1"):
            daemon.run(str(SO101), sim=True, socket_path=str(parent / "so101.sock"))
        assert os.listdir(tmp) == []
        assert not (short_tmp / "run").exists()
        assert kept is None or kept.is_dir()
