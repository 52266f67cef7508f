"""End to end, the CRTK spec's own namespace example on real kinds of devices: a UR5e over RTDE
with a Robotiq 2F-85 on its tool flange (profiles/ur5e_robotiq.yaml, issue 20), ``--sim`` putting
the gripper's simulator behind the UR simulator's tool port 54321. The gripper's Modbus RTU bus
(~5 ms for one read and one write) is served at its own rate: the arm keeps its 500 Hz cycle
(no overrun; at most a stray one on a loaded host) while the gripper moves, the two namespaces move independently under one operating
state, and pause / resume resumes where the arm's own stop left it."""

from __future__ import annotations

import time

import numpy as np
import pytest

from crtk_bridge.client import connect
from crtk_bridge.sim.control import control_request

from .conftest import ROOT, DaemonProcess, wait_until
from .test_e2e_multibus import Buses

UR_ROBOTIQ = ROOT / "profiles" / "ur5e_robotiq.yaml"
QUICK = {"cmd": "timings", "power_on_s": 0.1, "brake_release_s": 0.1, "unlock_delay_s": 0.3}


def ctl(sims: Buses, bus: str, request: dict) -> dict:
    reply = control_request(sims.sims[bus], request)
    assert reply.get("ok"), (request, reply)
    return reply


def test_a_ur_arm_with_a_robotiq_gripper_on_its_tool_flange(short_tmp):
    d = DaemonProcess(["--profile", str(UR_ROBOTIQ), "--sim"], short_tmp / "urr.sock", short_tmp / "daemon.log")
    try:
        sims = Buses(d, {"arm", "hand"})
        assert "bus 'hand' behind bus 'arm''s port 54321 (socket://127." in d.output()
        ctl(sims, "arm", QUICK)
        ctl(sims, "hand", {"cmd": "activation", "seconds": 0.3})
        ur = lambda: ctl(sims, "arm", {"cmd": "state"})  # noqa: E731
        gripper = lambda: ctl(sims, "hand", {"cmd": "dump"})  # noqa: E731
        assert ur()["tool_clients"] == 1  # the gripper's link is the arm's tool port
        robot = connect(socket=str(d.socket_path))
        try:
            info = robot.list()
            assert info["backend"] == "ur+robotiq"
            assert [ns["name"] for ns in info["namespaces"]] == ["ur5e", "ur5e/gripper"]
            assert [ns["units"] for ns in info["namespaces"]] == [["rad"] * 6, ["m"]]  # the finger opening: m
            arm, hand = robot.device("ur5e"), robot.device("ur5e/gripper")
            assert arm.enable(20.0) and hand.operating_state() == "ENABLED"  # one state: the gripper activated too
            assert gripper()["gGTO"] == 1 and ur()["robot_mode"] == "RUNNING"
            q0 = np.array(ur()["q"])
            # both namespaces move at once, each to its own goal: the gripper closes to 3 cm
            # while the arm turns its base; over it the loop runs at the arm's 500 Hz with no
            # overrun (a cycle that waited for the gripper's bus would overrun every time)
            before = robot.connection.request("period_statistics")
            requests = gripper()["requests"]
            goal = q0 + np.array([0.3, 0, 0, 0, 0, 0])
            arm.move_jp(list(goal))
            hand.move_jp([0.03])
            wait_until(lambda: abs(hand.measured_js()[0][0] - 0.03) < 0.002, 10, what="the gripper at 3 cm")
            wait_until(lambda: not arm.is_busy() and not hand.is_busy()
                       and np.allclose(ur()["q"], goal, atol=5e-4), 15, what="both moves done")
            after = robot.connection.request("period_statistics")
            assert after["period_s"] == pytest.approx(0.002)
            assert after["cycles"] - before["cycles"] > 100  # (the window's cycles: ~500 a second)
            # a cycle that waited for the gripper's bus (~5 ms of wire) would overrun every time;
            # none did in any run here, but a loaded CI host may stall one cycle of hundreds
            overruns = after["overruns"] - before["overruns"]
            assert overruns <= 0.01 * (after["cycles"] - before["cycles"]), (before, after)
            assert gripper()["requests"] > requests + 10  # its bus was busy all along, at its own rate
            # the arm moves alone: the gripper holds where it is
            held = hand.measured_js()[0][0]
            arm.move_jp(list(q0))
            wait_until(lambda: not arm.is_busy() and np.allclose(ur()["q"], q0, atol=5e-4), 15, what="the arm back")
            assert hand.measured_js()[0][0] == pytest.approx(held, abs=0.002)
            # the gripper moves alone: the arm holds
            hand.move_jp([0.06])
            wait_until(lambda: abs(hand.measured_js()[0][0] - 0.06) < 0.002, 10, what="the gripper at 6 cm")
            np.testing.assert_allclose(ur()["q"], q0, atol=5e-4)
            # pause / resume: a long arm move stopped on its way by the controller's own safeguard
            # stop; on resume the arm holds where it stopped, not where core's ramp would be
            goal = q0 + np.array([0.8, 0, 0, 0, 0, 0])
            arm.move_jp(list(goal))
            wait_until(lambda: abs(ur()["q"][0] - q0[0]) > 0.2, 5, what="the move under way")
            ctl(sims, "arm", {"cmd": "stop", "kind": "safeguard"})
            wait_until(lambda: arm.operating_state() == "PAUSED", 3, what="PAUSED")
            assert hand.operating_state() == "PAUSED"  # one robot, one state
            ctl(sims, "arm", {"cmd": "release", "kind": "safeguard"})
            time.sleep(0.2)
            stopped = np.array(ur()["q"])
            assert abs(stopped[0] - goal[0]) > 0.05  # stopped short of the goal
            assert arm.resume(5.0) and arm.operating_state() == "ENABLED"
            time.sleep(0.3)
            np.testing.assert_allclose(ur()["q"], stopped, atol=2e-3)
            # and the gripper still follows after the resume
            hand.move_jp([0.02])
            wait_until(lambda: abs(hand.measured_js()[0][0] - 0.02) < 0.002, 10, what="the gripper at 2 cm")
            # the tool flange's link lost (the gripper's RS-485 through the arm's port 54321): the
            # robot FAULTs naming the bus and the port, the arm included; enable recovers
            mark = robot.connection.event_count
            ctl(sims, "arm", {"cmd": "link_loss", "duration_s": 0.5, "ports": ["tool"]})
            ev = robot.wait_for_event("port_lost", 5, kind="error", since=mark)
            assert ev is not None, list(robot.connection.events_since(mark))
            assert ev.data["message"].startswith("ur5e_robotiq: bus 'hand': ") and ":54321" in ev.data["message"], ev.data
            wait_until(arm.is_fault, 2, what="FAULT state")
            wait_until(lambda: not arm.is_busy(), 10, what="the fault's DISABLE")
            assert ur()["robot_mode"] == "POWER_OFF"
            wait_until(lambda: ur()["tool_clients"] == 1, 10, what="the gripper's link back")
            assert arm.enable(20.0) and hand.operating_state() == "ENABLED"
            # DISABLE ends once both buses are off: the arm powered off, the gripper's go bit off
            assert arm.disable(10.0)
            assert ur()["robot_mode"] == "POWER_OFF" and gripper()["gGTO"] == 0
        finally:
            robot.close()
    except BaseException:
        d.print_tail()
        raise
    finally:
        d.stop()
