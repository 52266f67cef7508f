"""A backend with its own cartesian control (``native_cartesian``, as a UR's servoL / speedL /
moveL will be): cartesian commands reach it as cartesian setpoints through the controller, with
no IK, and it supplies measured_cp itself. Driven cycle by cycle with a fake backend."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from crtk_bridge.core.actuator import FRAME_BODY, Capabilities, CartesianMode, CommandMode
from crtk_bridge.core.state import OperatingState
from crtk_bridge.server.cartesian import CartesianSpace

from .test_controller import PROFILE, FakeActuator, make_rig

ARM = "so101"
ARM_IDX = np.array([PROFILE.joint_index(j) for j in PROFILE.namespace(ARM).joints])
GRIP_IDX = np.array([PROFILE.joint_index(j) for j in PROFILE.namespace("so101/gripper").joints])
MOVE_CYCLES = 20  # the fake controller's moveL takes this many cycles


class FakeNativeArm(FakeActuator):
    """A controller that servos its tool in cartesian space and reports its TCP pose."""

    CAPS = Capabilities(position=True, measures_velocity=True, native_cartesian=True)

    def __init__(self, profile):
        super().__init__(profile)
        self.tcp_p = np.array([0.3, 0.0, 0.2])
        self.tcp_q = np.array([0.0, 1.0, 0.0, 0.0])
        self.done_seq = 0
        self.moving = 0  # cycles left of the running moveL
        self.writes: list[tuple[int, np.ndarray, dict]] = []  # (cartesian mode, joint modes, row 0)

    def _read(self, fb):
        super()._read(fb)
        cart = fb.cartesian
        cart.position[0] = self.tcp_p
        cart.orientation[0] = self.tcp_q
        cart.done_seq[0] = self.done_seq
        cart.stamp = 2.0
        return None

    def _write(self, cmd):
        super()._write(cmd)
        c = cmd.cartesian
        mode = CartesianMode(int(c.mode[0]))
        self.writes.append((mode, cmd.mode.copy(), {
            "position": c.position[0].copy(), "orientation": c.orientation[0].copy(), "linear": c.linear[0].copy(),
            "angular": c.angular[0].copy(), "frame": int(c.frame[0]), "seq": int(c.seq[0])}))
        if mode is CartesianMode.POSE:
            self.tcp_p[:], self.tcp_q[:] = c.position[0], c.orientation[0]
        elif mode is CartesianMode.TWIST:
            self.tcp_p += c.linear[0] * 0.005
        elif mode is CartesianMode.MOVE and self.done_seq < c.seq[0]:
            self.moving = self.moving or MOVE_CYCLES
            self.moving -= 1
            if self.moving == 0:
                self.tcp_p[:], self.tcp_q[:] = c.position[0], c.orientation[0]
                self.done_seq = int(c.seq[0])
        return None


@pytest.fixture
def native():
    c, act, clock, cycle, req = rig = make_rig(FakeNativeArm(PROFILE))
    assert req("enable")["ok"]
    cycle(2)
    return rig


POSE = {"position": [0.25, 0.05, 0.15], "orientation": [0.0, 0.0, 0.0, 1.2]}  # normalised on the way
# a servo step from the fake's TCP ([0.3, 0, 0.2], [0, 1, 0, 0]) within safety.cartesian_step_max
NEAR = {"position": [0.31, 0.0, 0.19], "orientation": [0.0, 1.2, 0.0, 0.0]}


def test_the_backend_declares_its_rows_and_supplies_measured_cp(native):
    c, act, clock, cycle, req = native
    assert act.cartesian_namespaces() == [ARM] and list(c.native_cartesian) == [ARM]
    assert c.feedback.cartesian.stamp == 2.0
    assert c.feedback.cartesian.position[0] == pytest.approx(act.tcp_p)  # copied in on every read


def test_servo_cp_reaches_the_backend_as_a_pose_not_joint_goals(native):
    c, act, clock, cycle, req = native
    assert req("servo_cp", ARM, **NEAR)["ok"]
    cycle()
    mode, joints, row = act.writes[-1]
    assert mode is CartesianMode.POSE
    assert row["position"] == pytest.approx(NEAR["position"]) and row["orientation"] == pytest.approx([0, 1, 0, 0])
    assert np.all(joints[ARM_IDX] == CommandMode.NONE)  # the arm's joints are the backend's now
    assert np.all(joints[GRIP_IDX] == CommandMode.POSITION)  # the gripper is not
    cycle()
    assert c.feedback.cartesian.position[0] == pytest.approx(NEAR["position"])  # measured_cp follows
    assert not c.is_busy


def test_servo_cv_reaches_the_backend_as_a_twist_in_its_frame(native):
    c, act, clock, cycle, req = native
    p0 = act.tcp_p.copy()
    for _ in range(10):
        assert req("servo_cv", ARM, linear=[0.0, 0.02, 0.0], angular=[0.0, 0.0, 0.1], frame="body")["ok"]
        cycle()
    mode, joints, row = act.writes[-1]
    assert mode is CartesianMode.TWIST and row["frame"] == FRAME_BODY
    assert row["linear"] == pytest.approx([0, 0.02, 0]) and row["angular"] == pytest.approx([0, 0, 0.1])
    assert act.tcp_p - p0 == pytest.approx([0, 0.02 * 10 * 0.005, 0])
    assert not c.twist_motions[ARM].active  # no Jacobian mapping in core for a native namespace


def test_move_cp_is_busy_until_the_backend_reports_it_done(native):
    c, act, clock, cycle, req = native
    c.outbox.clear()
    r = req("move_cp", ARM, **POSE)
    assert r["ok"] and r["data"]["busy_seq"] == 1
    states = [m["data"] for m in c.outbox if m.get("event") == "operating_state"]
    assert states[-1]["is_busy"] and c.outbox.index(r) > c.outbox.index({"event": "operating_state", "data": states[-1]})
    c.outbox.clear()
    cycle(MOVE_CYCLES - 1)
    assert c.is_busy and act.writes[-1][0] is CartesianMode.MOVE and act.writes[-1][2]["seq"] == 1
    cycle(3)
    assert not c.is_busy
    edges = [m["data"]["is_busy"] for m in c.outbox if m.get("event") == "operating_state"]
    assert edges == [False]
    assert act.tcp_p == pytest.approx(POSE["position"])
    mode, joints, _ = act.writes[-1]
    assert mode is CartesianMode.NONE and np.all(joints[ARM_IDX] == CommandMode.POSITION)  # holding


def test_servo_stream_watchdog_hands_the_joints_back(native):
    c, act, clock, cycle, req = native
    assert req("servo_cp", ARM, **NEAR)["ok"]
    c.outbox.clear()
    cycle(int(PROFILE.safety.servo_timeout_s / c.dt) + 3)
    warnings = [m["data"] for m in c.outbox if m.get("event") == "warning"]
    assert [w["code"] for w in warnings] == ["servo_timeout"] and ARM in warnings[0]["message"]
    mode, joints, _ = act.writes[-1]
    assert mode is CartesianMode.NONE and np.all(joints[ARM_IDX] == CommandMode.POSITION)
    m = c.namespaces[ARM]
    assert m.setpoint_p == pytest.approx(act.pos[ARM_IDX])  # held where the backend left the arm


def test_what_was_commanded_is_the_setpoint_and_the_goal(native):
    c, act, clock, cycle, req = native
    nc, m = c.native_cartesian[ARM], c.namespaces[ARM]
    assert req("move_jp", ARM, position=list(act.pos[ARM_IDX]))["ok"]
    cycle(2)
    assert m.goal_stamp > 0
    assert req("servo_cp", ARM, **NEAR)["ok"]
    assert nc.setpoint_stamp > 0 and nc.position == pytest.approx(NEAR["position"])
    assert nc.goal_stamp == 0.0 and m.goal_stamp == 0.0  # the move_jp's goal is not the arm's any more
    cycle(int(PROFILE.safety.servo_timeout_s / c.dt) + 3)  # the stream's watchdog: held there
    assert not nc.active and nc.setpoint_stamp > 0
    assert req("move_cp", ARM, **POSE)["ok"]
    assert nc.setpoint_stamp == 0.0  # the backend's own trajectory runs: its setpoints are its own
    assert nc.goal_stamp > 0 and nc.goal_position == pytest.approx(POSE["position"])
    cycle(MOVE_CYCLES + 2)
    assert not c.is_busy and nc.setpoint_stamp > 0 and nc.position == pytest.approx(POSE["position"])
    assert nc.goal_stamp > 0  # the goal stays after the move
    assert req("servo_cv", ARM, linear=[0.01, 0, 0], angular=[0, 0, 0], frame="body")["ok"]
    assert nc.twist_stamp > 0 and nc.setpoint_stamp == 0.0 and nc.goal_stamp == 0.0
    assert req("hold", ARM)["ok"]
    cycle()
    assert nc.twist_stamp == nc.setpoint_stamp == nc.goal_stamp == 0.0  # hold: nothing commanded remains


@pytest.mark.parametrize("how", ["joint command", "hold", "pause", "fault", "client lost"])
def test_anything_else_ends_the_cartesian_setpoint(native, how):
    c, act, clock, cycle, req = native
    assert req("servo_cv", ARM, linear=[0.01, 0, 0], angular=[0, 0, 0])["ok"]
    cycle()
    assert act.writes[-1][0] is CartesianMode.TWIST
    n = len(act.writes)
    if how == "joint command":
        assert req("servo_jp", ARM, position=list(act.pos[ARM_IDX]))["ok"]
    elif how == "hold":
        assert req("hold", ARM)["ok"]
    elif how == "pause":
        assert req("pause")["ok"]
    elif how == "fault":
        from crtk_bridge.core.actuator import Fault
        c.on_read(act.new_feedback(), Fault("bus_timeout", "so101: no reply", transient=False))
    else:
        req("_client_lost")
    cycle(2)
    assert not c.native_cartesian[ARM].active
    if c.state is OperatingState.FAULT:
        assert len(act.writes) == n or act.writes[-1][0] is CartesianMode.NONE  # nothing more goes out
    else:
        assert act.writes[-1][0] is CartesianMode.NONE


def test_a_move_runs_on_when_the_client_leaves(native):
    c, act, clock, cycle, req = native
    assert req("move_cp", ARM, **POSE)["ok"]
    cycle(2)
    req("_client_lost")
    cycle(MOVE_CYCLES + 2)
    assert act.done_seq == 1 and act.tcp_p == pytest.approx(POSE["position"])


def test_refusals(native):
    c, act, clock, cycle, req = native
    r = req("servo_cp", ARM, position=[0, 0, float("inf")], orientation=[0, 0, 0, 1])
    assert not r["ok"] and r["error"]["code"] == "bad_request" and "position" in r["error"]["message"]
    r = req("move_cp", ARM, position=[0, 0, 0.1], orientation=[0, 0, 0, 0])
    assert not r["ok"] and r["error"]["code"] == "bad_request" and "quaternion" in r["error"]["message"]
    assert not c.native_cartesian[ARM].active and not c.is_busy
    assert req("pause")["ok"]
    r = req("servo_cp", ARM, **NEAR)
    assert not r["ok"] and r["error"]["code"] == "invalid_state"


@pytest.mark.parametrize("cmd", ["servo_cp", "interpolate_cp"])
def test_pose_steps_beyond_the_safety_bounds_are_refused(native, cmd):
    c, act, clock, cycle, req = native
    sf = PROFILE.safety
    nc = c.native_cartesian[ARM]
    # from the measured pose: a translation just over cartesian_step_max
    far = {"position": [0.3, 0.0, 0.2 + sf.cartesian_step_max * 1.1], "orientation": [0, 1, 0, 0]}
    r = req(cmd, ARM, **far)
    assert not r["ok"] and r["error"]["code"] == "step_too_large", r
    assert "safety.cartesian_step_max" in r["error"]["message"] and "measured pose" in r["error"]["message"]
    assert not nc.active
    # a rotation just over cartesian_rotation_step_max about z, in place
    half = (sf.cartesian_rotation_step_max * 1.1) / 2
    turned = [float(np.sin(half)), float(np.cos(half)), 0.0, 0.0]  # dot with [0, 1, 0, 0] = cos(half)
    r = req(cmd, ARM, position=[0.3, 0.0, 0.2], orientation=turned)
    assert not r["ok"] and r["error"]["code"] == "step_too_large"
    assert "safety.cartesian_rotation_step_max" in r["error"]["message"]
    assert not nc.active
    cycle()
    assert act.writes[-1][0] is CartesianMode.NONE  # nothing reached the backend
    # a stream is bounded step by step from its previous pose, not from where the arm lags
    assert req(cmd, ARM, **NEAR)["ok"]
    nxt = dict(NEAR, position=[0.31 + sf.cartesian_step_max * 0.9, 0.0, 0.19])
    assert req(cmd, ARM, **nxt)["ok"]
    act.tcp_p[:] = [0.3, 0.0, 0.2]  # the arm lags far behind: the base is still the previous pose
    cycle()
    third = dict(NEAR, position=[0.31 + sf.cartesian_step_max * 1.8, 0.0, 0.19])  # 1.8 bounds from the arm
    assert req(cmd, ARM, **third)["ok"]  # 0.9 bound from the previous pose
    r = req(cmd, ARM, **NEAR)  # back by 1.8 bounds in one step
    assert not r["ok"] and r["error"]["code"] == "step_too_large" and "previous pose" in r["error"]["message"]
    assert nc.position == pytest.approx(third["position"])  # unchanged
    # move_cp is planned by the backend: not bounded by a step
    assert req("move_cp", ARM, **POSE)["ok"]


@pytest.mark.parametrize("cmd", ["servo_cv", "interpolate_cv"])
def test_twists_beyond_the_safety_bounds_are_refused(native, cmd):
    c, act, clock, cycle, req = native
    sf = PROFILE.safety
    nc = c.native_cartesian[ARM]
    v = sf.cartesian_velocity_max
    assert req(cmd, ARM, linear=[0.6 * v, 0.0, 0.7 * v], angular=[0, 0, 0])["ok"]  # |v| = 0.92 bound
    cycle()
    r = req(cmd, ARM, linear=[0.8 * v, 0.0, 0.7 * v], angular=[0, 0, 0])  # each within, |v| = 1.06 bound
    assert not r["ok"] and r["error"]["code"] == "out_of_limits"
    assert "safety.cartesian_velocity_max" in r["error"]["message"] and "m/s" in r["error"]["message"]
    w = sf.cartesian_angular_velocity_max
    r = req(cmd, ARM, linear=[0, 0, 0], angular=[0.0, 0.8 * w, 0.7 * w])
    assert not r["ok"] and r["error"]["code"] == "out_of_limits"
    assert "safety.cartesian_angular_velocity_max" in r["error"]["message"]
    cycle()
    assert act.writes[-1][2]["linear"] == pytest.approx([0.6 * v, 0.0, 0.7 * v])  # the previous twist stays


# ------------------------------------------------------------------ the front's routing
def _state(native_p, native_q, stamp=5.0, **commanded):
    z = np.zeros(5)
    return {"measured_stamp": 4.0, "measured_p": z, "measured_v": z, "measured_f": z, "measures_velocity": True,
            "measures_effort": False, "setpoint_stamp": 0.0, "setpoint_p": z, "setpoint_v": z, "setpoint_f": z,
            "setpoint_has_p": False, "setpoint_has_v": False, "setpoint_has_f": False, "goal_stamp": 0.0,
            "goal_p": z, "goal_v": z, "goal_f": z, "goal_has_p": False, "goal_has_v": False, "goal_has_f": False,
            "native_stamp": stamp, "native_p": np.array(native_p), "native_q": np.array(native_q),
            "native_sp_stamp": 0.0, "native_sp_p": np.zeros(3), "native_sp_q": np.array([0.0, 0, 0, 1]),
            "native_tw_stamp": 0.0, "native_tw": np.zeros(6), "native_tw_body": False,
            "native_goal_stamp": 0.0, "native_goal_p": np.zeros(3), "native_goal_q": np.array([0.0, 0, 0, 1]),
            **{k: np.array(v) if isinstance(v, list) else v for k, v in commanded.items()}}


def test_the_front_routes_cartesian_commands_to_a_native_backend_without_ik():
    ns = PROFILE.namespace(ARM)
    joint_cmds = ["servo_jp", "servo_jr", "servo_jv", "interpolate_jp", "interpolate_jv", "move_jp", "move_jr"]
    cs = CartesianSpace(PROFILE, ARM, ns.kinematics, joint_cmds, False, native=True)
    try:
        def no_ik(*args, **kwargs):
            raise AssertionError("IK ran for a native cartesian backend")

        cs.kin.ik = cs._ik_kin.ik = no_ik
        st = _state([0.3, 0.0, 0.2], [0.0, 1.0, 0.0, 0.0])
        run = asyncio.run
        assert run(cs.translate("move_cp", POSE, st, "spatial", False)) == (
            "move_cp", {"position": POSE["position"], "orientation": [0.0, 0.0, 0.0, 1.0]})
        cmd, data = run(cs.translate("servo_cr", {"position": [0.0, 0.0, 0.01], "orientation": [0, 0, 0, 1]},
                                     st, "spatial", False))
        assert cmd == "servo_cp" and data["position"] == pytest.approx([0.3, 0.0, 0.21])
        assert data["orientation"] == pytest.approx([0.0, 1.0, 0.0, 0.0])
        assert run(cs.translate("servo_cv", {"linear": [0, 0, 1], "angular": [0, 0, 0]}, st, "body", False)) == (
            "servo_cv", {"linear": [0.0, 0.0, 1.0], "angular": [0.0, 0.0, 0.0], "frame": "body"})
        # measured_cp is the backend's own pose with its own stamp, not FK of the joints
        mcp = cs.query("measured_cp", st, "spatial")
        assert mcp["stamp"] == 5.0 and mcp["position"] == pytest.approx([0.3, 0.0, 0.2])
        assert cs.query("measured_cp", _state([0, 0, 0], [0, 0, 0, 1], stamp=0.0), "spatial")["stamp"] == 0.0
        # setpoint_cp / goal_cp / setpoint_cv: what the backend was commanded, not FK of the joints
        st = _state([0.3, 0.0, 0.2], [0.0, 1.0, 0.0, 0.0], native_sp_stamp=6.0, native_sp_p=[0.31, 0.0, 0.19],
                    native_sp_q=[0.0, 2.0, 0.0, 0.0], native_goal_stamp=7.0, native_goal_p=[0.25, 0.05, 0.15],
                    native_tw_stamp=8.0, native_tw=[0.0, 0.02, 0.0, 0.0, 0.0, 0.1], native_tw_body=False)
        sp = cs.query("setpoint_cp", st, "spatial")
        assert sp["stamp"] == 6.0 and sp["position"] == pytest.approx([0.31, 0.0, 0.19])
        assert sp["orientation"] == pytest.approx([0.0, 1.0, 0.0, 0.0])
        g = cs.query("goal_cp", st, "spatial")
        assert g["stamp"] == 7.0 and g["position"] == pytest.approx([0.25, 0.05, 0.15])
        tw = cs.query("setpoint_cv", st, "spatial")
        assert tw["stamp"] == 8.0 and tw["linear"] == pytest.approx([0.0, 0.02, 0.0])
        body = cs.query("setpoint_cv", st, "body")  # the tip is turned pi about y: y stays, z flips
        assert body["linear"] == pytest.approx([0.0, 0.02, 0.0], abs=1e-12)
        assert body["angular"] == pytest.approx([0.0, 0.0, -0.1], abs=1e-12)
        assert cs.query("setpoint_cp", _state([0.3, 0.0, 0.2], [0.0, 1.0, 0.0, 0.0]), "spatial")["stamp"] == 0.0
    finally:
        cs.close()
