"""Hot replug (issue 12): the USB adapter pulled out mid-motion and plugged back in, on the real
daemon over each simulated robot. The simulator's control socket closes the pty (the daemon's fd
reads EIO, the link the profile names goes away), then brings it back under a NEW device name
behind the same link, as udev re-points a /dev/serial/by-id link at a new ttyACM number. The
servos lose power meanwhile (torque off when they come back, as real servos do)."""

from __future__ import annotations

import os
import re

import numpy as np
import pytest

from crtk_bridge.client import CommandError, connect
from crtk_bridge.sim.control import control_request

from .conftest import wait_until


def sim_req(sim: str, **req) -> dict:
    reply = control_request(sim, req)
    assert reply.get("ok"), reply
    return reply


def sim_link(daemon) -> str:
    """The pty link the daemon's profile names (--sim prints it)."""
    return re.search(r"simulated \S+ bus on (\S+)", daemon.output()).group(1)


def test_unplug_mid_motion_faults_naming_the_port_and_replug_reenables(sim_daemon):
    r = sim_daemon.robot
    sim = sim_daemon.sim_control_path()
    robot = connect(socket=str(sim_daemon.socket_path))
    try:
        arm = robot.device(r.arm)
        port = sim_link(sim_daemon)
        old_pty = sim_req(sim, cmd="dump")["pty"]
        assert arm.enable(5.0)
        mark = robot.connection.event_count
        arm.move_jp(r.goals["wide"])
        wait_until(lambda: np.abs(arm.measured_jp()[0]).max() > 0.1, 5, what="the arm moving")

        sim_req(sim, cmd="usb_unplug", power_off=True)
        ev = robot.wait_for_event("port_lost", 3.0, kind="error", since=mark)
        assert ev is not None, robot.connection.events_since(mark)
        assert f"serial port {port} is gone" in ev.data["message"], ev.data
        assert not os.path.lexists(port), "the unplugged adapter's link is gone"
        wait_until(arm.is_fault, 2, what="FAULT after the unplug")
        with pytest.raises(CommandError, match=f"serial port {re.escape(port)} is gone"):
            arm.enable(2.0)  # refused while the port is gone, naming it

        mark = robot.connection.event_count
        back = sim_req(sim, cmd="usb_plug")
        assert back["pty"] != old_pty and os.readlink(port) == back["pty"], (old_pty, back)
        ev = robot.wait_for_event("fault_cleared", 5.0, kind="status", since=mark)
        assert ev is not None, robot.connection.events_since(mark)
        assert port in ev.data["message"] and "torque off" in ev.data["message"], ev.data
        assert arm.is_fault(), "the robot never leaves FAULT by itself"

        assert arm.enable(5.0), "enable after the replug"
        torque = {sid: s["torque_enable"] for sid, s in sim_req(sim, cmd="dump")["servos"].items()}
        assert all(v == 1 for v in torque.values()), torque
        arm.move_jp(r.goals["small"]).wait(timeout=10.0)
        assert np.allclose(arm.measured_jp()[0], r.goals["small"], atol=0.05)

        # unplugged while DISABLED: a warning naming the port, the state stays, the bus comes back
        assert arm.disable(5.0)
        mark = robot.connection.event_count
        sim_req(sim, cmd="usb_unplug")
        ev = robot.wait_for_event("device_fault", 3.0, kind="warning", since=mark)
        assert ev is not None and f"serial port {port} is gone" in ev.data["message"], robot.connection.events_since(mark)
        sim_req(sim, cmd="usb_plug")
        assert robot.wait_for_event("fault_cleared", 5.0, kind="status", since=mark) is not None
        assert arm.is_disabled()
    finally:
        robot.close()
