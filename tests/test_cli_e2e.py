"""`crtk-bridge check` and `crtk-ctl` against a real daemon on each simulated robot."""

from __future__ import annotations

import json

import pytest
import yaml

from crtk_bridge.cli import main as bridge_main
from crtk_bridge.client.cli import main as ctl_main

from .conftest import so101_data

pytestmark = pytest.mark.requires()  # every simulated robot


def test_check_accepts_a_valid_profile(sim_robot, capsys):
    assert bridge_main(["check", "--profile", str(sim_robot.profile)]) == 0
    assert sim_robot.arm in capsys.readouterr().out


def test_check_rejects_an_invalid_profile_naming_key(tmp_path, capsys):
    data = so101_data()
    data["joints"][1]["limits"]["velocity_max"] = "fast"
    data["backend"]["baudrate"] = 123
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(data))
    assert bridge_main(["check", "--profile", str(bad)]) == 1
    err = capsys.readouterr().err
    assert str(bad) in err and "joints[1] (shoulder_lift).limits.velocity_max" in err


def test_check_rejects_unknown_backend_key(tmp_path, capsys):
    data = so101_data()
    data["backend"]["speed"] = 3
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(data))
    assert bridge_main(["check", "--profile", str(bad)]) == 1
    err = capsys.readouterr().err
    assert str(bad) in err and "speed" in err


def ctl(capsys, *args):
    code = ctl_main(list(args))
    out = capsys.readouterr()
    return code, out.out, out.err


def test_crtk_ctl_drives_the_daemon(sim_daemon, capsys):
    bot = sim_daemon.robot
    goal = [f"{x:g}" for x in bot.goals["small"]]
    sock = str(sim_daemon.socket_path)
    code, out, _ = ctl(capsys, "--socket", sock, "--json", "state")
    assert code == 0 and json.loads(out)["state"] == "DISABLED"

    code, _, err = ctl(capsys, "--socket", sock, "move_jp", *goal)
    assert code == 1 and len(err.strip().splitlines()) == 1 and "DISABLED" in err

    code, out, _ = ctl(capsys, "--socket", sock, "list")
    assert code == 0 and bot.arm in out and "move_jp" in out
    if bot.gripper is not None:
        assert bot.gripper in out

    assert ctl(capsys, "--socket", sock, "enable")[0] == 0
    assert ctl(capsys, "--socket", sock, "home")[0] == 0
    assert ctl(capsys, "--socket", sock, "move_jp", *goal, "--wait")[0] == 0
    code, out, _ = ctl(capsys, "--socket", sock, "--json", "get", "measured_js")
    js = json.loads(out)
    assert code == 0 and js["stamp"] > 0 and js["name"] == list(bot.joint_names)
    assert js["position"] == pytest.approx(list(bot.goals["small"]), abs=0.02)

    code, out, _ = ctl(capsys, "--socket", sock, "--json", "echo", "measured_js", "--rate", "50", "--count", "5")
    frames = [json.loads(line) for line in out.splitlines() if line.strip()]
    assert code == 0 and len(frames) == 5

    if bot.gripper is not None:
        code, out, _ = ctl(capsys, "--socket", sock, "--ns", bot.gripper, "move_jp", "0.4", "--wait")
        assert code == 0
    assert ctl(capsys, "--socket", sock, "disable")[0] == 0
    code, out, _ = ctl(capsys, "--socket", sock, "--json", "state")
    assert json.loads(out)["state"] == "DISABLED"


def test_crtk_ctl_without_daemon_exits_2_naming_socket(short_tmp, capsys):
    code, _, err = ctl(capsys, "--socket", str(short_tmp / "none.sock"), "state")
    assert code == 2 and "none.sock" in err
