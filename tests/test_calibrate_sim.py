"""The simulators' hand (issue 12): the control socket's ``hand`` moves a torque-off servo as a hand
turning its horn would, at a bounded speed (so a reader sees it travel, as a calibration sweep
needs), and refuses a servo whose torque is on (it holds its position)."""

from __future__ import annotations

import time

import pytest

from crtk_bridge.sim.control import control_request
from crtk_bridge.sim.dynamixel import DynamixelSimulator
from crtk_bridge.sim.feetech import FeetechSimulator

from .conftest import wait_until

SIMS = {
    "feetech": lambda ctl: FeetechSimulator(servo_ids=[1, 2], control=ctl),
    "dynamixel": lambda ctl: DynamixelSimulator(servos=[1, 2], control=ctl),
}


@pytest.mark.parametrize("vendor", list(SIMS))
def test_hand_moves_a_torque_off_servo_at_its_speed_and_not_a_torqued_one(short_tmp, vendor):
    ctl = str(short_tmp / "sim.sock")
    sim = SIMS[vendor](ctl)
    sim.start()
    try:
        def present(sid: int) -> int:
            return control_request(ctl, {"cmd": "read", "id": sid, "register": "Present_Position"})["value"]

        # a homing offset on the servo: the hand's target is what the servo reports
        assert control_request(ctl, {"cmd": "write", "id": 1, "register": "Homing_Offset", "value": 100})["ok"]
        start = present(1)
        t0 = time.monotonic()
        assert control_request(ctl, {"cmd": "hand", "id": 1, "position": start + 800, "speed": 2000})["ok"]
        mid = present(1)
        assert start <= mid < start + 800, "the hand travels at its speed, it does not teleport"
        wait_until(lambda: present(1) == start + 800, 3, what="the hand reaching its target")
        assert time.monotonic() - t0 >= 0.8 * 800 / 2000
        # ...and lets go there (Present_Position rounds to the target up to half a tick before the
        # hand's last step lands on it: the next update, however late a loaded host makes it)
        wait_until(lambda: control_request(ctl, {"cmd": "dump"})["by_hand"] == [], 2, what="the hand letting go")

        assert control_request(ctl, {"cmd": "write", "id": 2, "register": "Torque_Enable", "value": 1})["ok"]
        reply = control_request(ctl, {"cmd": "hand", "id": 2, "position": 100})
        assert not reply["ok"] and "torque is on" in reply["error"], reply
        reply = control_request(ctl, {"cmd": "hand", "id": 1, "position": 10, "speed": 0})
        assert not reply["ok"] and "speed" in reply["error"], reply
    finally:
        sim.stop()


def test_usb_replug_gives_a_new_pty_behind_the_same_link(short_tmp):
    import os

    link = short_tmp / "tty"
    sim = FeetechSimulator(servo_ids=[1], link=link)
    sim.start()
    try:
        old = os.readlink(link)
        sim.usb_unplug()
        assert not os.path.lexists(link) and not sim.plugged
        sim.usb_plug()
        assert sim.plugged and os.readlink(link) == sim.pty_path != old
    finally:
        sim.stop()


def test_range_bar_shows_the_range_seen_the_middle_pose_and_where_the_joint_is():
    import math

    from crtk_bridge.client.calibrate import bar, bar_lines

    b = bar(-math.pi / 2, math.pi / 4, math.pi / 4, width=9)  # one turn over 9 cells, middle at 4
    assert b == "[..==|#...]"  # seen -90..+45 deg (cells 2..5), the joint at +45
    assert bar(0.0, 0.0, 0.0, width=9) == "[....#....]"  # not moved: the joint sits at the middle
    (line,) = bar_lines({"elbow_flex": [-math.pi / 2, math.pi / 4, 0.0]})
    assert line.startswith("  elbow_flex [") and line.endswith(" -90.0 ..   +45.0 deg")
