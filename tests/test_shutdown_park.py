"""Shutdown park (issue 9, defect 7): the profile's ``shutdown`` section, ``Controller.park`` and the
control loop's end (``_shutdown`` from the front, a signal), with a fake actuator, in-process."""

from __future__ import annotations

import gc
import socket
import threading
import time

import msgspec
import numpy as np
import pytest

from crtk_bridge.core.actuator import CommandMode, DeviceStatus, Fault
from crtk_bridge.core.loop import ControlLoop
from crtk_bridge.core.snapshot import Layout, SnapshotBuffer
from crtk_bridge.core.state import OperatingState
from crtk_bridge.errors import ProfileError
from crtk_bridge.profile import Shutdown, parse_profile

from .conftest import so101_data, wait_until
from .test_controller import PROFILE, FakeActuator, make_rig

REST = np.array([PROFILE.shutdown.rest[j.name] for j in PROFILE.joints])
_enc = msgspec.msgpack.Encoder().encode
_dec = msgspec.msgpack.Decoder().decode


def with_shutdown(**kw):
    return msgspec.structs.replace(PROFILE, shutdown=msgspec.structs.replace(PROFILE.shutdown, **kw))


# ------------------------------------------------------------------ profile keys
def test_so101_and_koch_park_by_default_and_the_default_is_torque_off():
    from crtk_bridge.profile import load_profile

    for path in ("profiles/so101.yaml", "profiles/koch.yaml"):
        sd = load_profile(path).shutdown
        assert sd.action == "park" and 0 < sd.timeout_s <= 10
    data = so101_data()
    del data["shutdown"]
    assert parse_profile(data).shutdown == Shutdown(action="torque_off")


@pytest.mark.parametrize("section,needle", [
    ({"action": "park"}, "shutdown.rest: park needs a rest pose"),
    ({"action": "park", "rest": {**PROFILE.shutdown.rest, "elbow": 0.0}}, "shutdown.rest.elbow: unknown joint"),
    ({"action": "park", "rest": {**PROFILE.shutdown.rest, "gripper": 3.0}}, "shutdown.rest.gripper: 3.0 is outside"),
    ({"action": "park", "rest": PROFILE.shutdown.rest, "timeout_s": 30}, "shutdown.timeout_s: 30"),
    ({"action": "drop"}, "shutdown.action"),
])
def test_bad_shutdown_sections_are_refused_naming_the_key(section, needle):
    data = so101_data()
    data["shutdown"] = section
    with pytest.raises(ProfileError) as err:
        parse_profile(data, "so101.yaml")
    assert needle in str(err.value)


# ------------------------------------------------------------------ Controller.park
def test_park_moves_every_torqued_namespace_to_rest_with_busy_edges():
    c, act, clock, cycle, req = make_rig(FakeActuator(PROFILE))
    assert not c.park()  # DISABLED: nothing to park, nothing moves
    c.handle({"id": 1, "cmd": "enable"})
    c.handle({"id": 2, "cmd": "move_jp", "ns": "so101", "data": {"position": [1.0, 0.5, -0.5, 0.3, 1.0]}})
    cycle(40)  # mid-move: the park re-plans from the running trajectory
    c.outbox.clear()
    assert c.park()
    steps = []
    prev = act.pos.copy()
    for _ in range(1000):
        cycle()
        steps.append(np.abs(act.pos - prev).max())
        prev = act.pos.copy()
        if not c.in_motion():
            break
    np.testing.assert_allclose(act.pos, REST, atol=1e-6)
    assert c.at_rest_pose() and max(steps) <= 4.0 * c.dt + 1e-9  # within velocity_max
    busy = [m["data"]["is_busy"] for m in c.outbox if m.get("event") == "operating_state"]
    assert busy == [True, False]


def test_a_joint_the_rest_pose_does_not_name_stays_where_it_is():
    rest = dict(PROFILE.shutdown.rest)
    del rest["wrist_roll"]
    profile = with_shutdown(rest=rest)
    act = FakeActuator(profile)
    act.pos[4] = 0.7
    c, act, clock, cycle, req = make_rig(act, profile)
    c.handle({"id": 1, "cmd": "enable"})
    assert c.park()
    for _ in range(1000):
        cycle()
        if not c.in_motion():
            break
    assert act.pos[4] == pytest.approx(0.7) and act.pos[1] == pytest.approx(rest["shoulder_lift"])


def test_park_leaves_a_free_namespace_free():
    c, act, clock, cycle, req = make_rig(FakeActuator(PROFILE))  # its first cycle read
    c.handle({"id": 1, "cmd": "enable"})
    c.handle({"id": 2, "cmd": "free", "ns": "so101/gripper"})
    assert c.park()
    c.step()
    assert c.command.mode[5] == CommandMode.FREE and c.command.mode[0] == CommandMode.POSITION


# ------------------------------------------------------------------ the loop's end
class LoopRig:
    """A ControlLoop on a fake actuator in a thread, talking over a real SEQPACKET pair."""

    def __init__(self, profile):
        self.act = FakeActuator(profile)
        self.front, back = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        self.snap = SnapshotBuffer(Layout(len(profile.joints), len(profile.namespaces)), create=True)
        self.loop = ControlLoop(profile, self.act, back, self.snap, realtime=False)
        self.msgs: list[dict] = []
        self.status = None
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()
        self.front.settimeout(0.05)
        self.rid = 0
        self.torque_log: list[tuple[bool, np.ndarray]] = []  # (torque, position) at every write
        orig = self.act._write

        def write(cmd):
            out = orig(cmd)
            self.torque_log.append((self.act.torque, self.act.pos.copy()))
            return out

        self.act._write = write

    def _run(self):
        self.status = self.loop.run(None)

    def pump(self) -> None:
        while True:
            try:
                data = self.front.recv(1 << 17)
            except (socket.timeout, BlockingIOError):
                return
            if not data:
                return
            self.msgs.append(_dec(data))

    def request(self, cmd, ns=None, **data) -> dict:
        self.rid += 1
        rid = self.rid
        self.front.send(_enc({"id": rid, "cmd": cmd, "ns": ns, "data": data}))

        def reply():
            self.pump()
            return next((m for m in self.msgs if m.get("id") == rid), None)

        return wait_until(reply, 5, what=f"reply to {cmd}")

    def events(self, code=None) -> list[dict]:
        self.pump()
        return [m["data"] for m in self.msgs if m.get("event") in ("status", "warning", "error")
                and (code is None or m["data"]["code"] == code)]

    def end(self, timeout=10) -> None:
        self.thread.join(timeout)
        assert not self.thread.is_alive()
        self.pump()

    def close(self) -> None:
        self.loop.running = False
        self.loop.abort_park = True
        self.thread.join(5)
        self.front.close()
        self.snap.close(unlink=True)
        gc.unfreeze()  # the loop froze the GC for its cycle; this is the test process


@pytest.fixture
def loop_rig():
    rigs = []

    def make(profile=PROFILE):
        r = LoopRig(profile)
        rigs.append(r)
        wait_until(lambda: r.loop.controller.feedback.stamp > 0, 5, what="loop running")
        return r

    yield make
    for r in rigs:
        r.close()


def enable_and_move(r: LoopRig, goal=(1.0, 0.5, -0.5, 0.3, 1.0)) -> None:
    assert r.request("enable")["ok"]
    assert r.request("move_jp", "so101", position=list(goal))["ok"]
    wait_until(lambda: np.abs(r.act.pos[:5] - goal).max() < 1e-6, 5, what="move done")


def test_shutdown_request_parks_then_torque_off(loop_rig):
    r = loop_rig()
    enable_and_move(r)
    r.front.send(_enc({"cmd": "_shutdown"}))
    # meanwhile: other commands are refused, a client leaving does not stop the park
    reply = r.request("move_jp", "so101", position=[0.0] * 5)
    assert reply["error"]["code"] == "invalid_state" and "parking" in reply["error"]["message"]
    r.front.send(_enc({"id": None, "cmd": "_client_lost"}))
    r.end()
    assert r.status == 0
    np.testing.assert_allclose(r.act.pos, REST, atol=1e-6)
    assert not r.act.torque
    # torque stayed on until the rest pose was reached
    assert all(t for t, _ in r.torque_log)
    np.testing.assert_allclose(r.torque_log[-1][1], REST, atol=1e-6)
    codes = [e["code"] for e in r.events() if e["code"].startswith("shutdown")]
    assert codes == ["shutdown_park", "shutdown_parked"]


def test_park_that_runs_out_of_time_switches_torque_off_where_it_is(loop_rig):
    r = loop_rig(with_shutdown(timeout_s=0.1))
    enable_and_move(r)
    r.loop.request_stop()  # as SIGTERM does
    r.end()
    assert not r.act.torque
    assert np.abs(r.act.pos - REST).max() > 0.5  # stopped short: torque off at the time limit
    assert [e["code"] for e in r.events() if e["code"].startswith("shutdown")] == ["shutdown_park",
                                                                                 "shutdown_park_timeout"]


def test_a_second_signal_or_a_stop_cuts_the_park_short(loop_rig):
    r = loop_rig()
    enable_and_move(r)
    r.loop.request_stop()
    wait_until(lambda: r.events("shutdown_park"), 5, what="park started")
    r.loop.request_stop()  # a second SIGTERM / Ctrl-C
    r.end()
    assert not r.act.torque and np.abs(r.act.pos - REST).max() > 0.3
    assert "second signal" in r.events("shutdown_park_aborted")[0]["message"]

    r = loop_rig()
    enable_and_move(r)
    r.front.send(_enc({"cmd": "_shutdown"}))
    wait_until(lambda: r.events("shutdown_park"), 5, what="park started")
    assert r.request("disable")["ok"]  # a stop is never refused, not even while parking
    r.end()
    assert not r.act.torque and r.loop.controller.state is OperatingState.DISABLED
    assert "DISABLED" in r.events("shutdown_park_aborted")[0]["message"]


def test_the_fronts_second_signal_cuts_the_park_short(loop_rig):
    """A second signal sent by pid reaches the front process alone: it says ``_torque_off``."""
    r = loop_rig()
    enable_and_move(r)
    r.front.send(_enc({"id": None, "cmd": "_shutdown"}))
    wait_until(lambda: r.events("shutdown_park"), 5, what="park started")
    r.front.send(_enc({"id": None, "cmd": "_torque_off"}))
    r.end()
    assert not r.act.torque and np.abs(r.act.pos - REST).max() > 0.3
    assert "second signal" in r.events("shutdown_park_aborted")[0]["message"]


def test_one_ctrl_c_to_the_group_parks_whichever_process_hears_it_first(loop_rig):
    """A terminal's Ctrl-C reaches both processes: the front's ``_shutdown`` read before the
    control process's own SIGINT is still one signal, and the park runs to its end."""
    r = loop_rig()
    enable_and_move(r)
    r.front.send(_enc({"id": None, "cmd": "_shutdown"}))
    wait_until(lambda: r.events("shutdown_park"), 5, what="park started")
    r.loop.request_stop()  # the same Ctrl-C, as the control process's SIGINT
    r.end()
    assert not r.act.torque
    np.testing.assert_allclose(r.act.pos, REST, atol=1e-6)
    assert r.events("shutdown_parked") and not r.events("shutdown_park_aborted")


def test_shutdown_while_disabled_or_with_torque_off_moves_nothing(loop_rig):
    r = loop_rig()
    r.front.send(_enc({"cmd": "_shutdown"}))
    r.end()
    assert r.torque_log == [] and not r.act.torque
    assert not [e for e in r.events() if e["code"].startswith("shutdown")]

    r = loop_rig(with_shutdown(action="torque_off"))
    enable_and_move(r)
    at = r.act.pos.copy()
    r.front.send(_enc({"cmd": "_shutdown"}))
    r.end()
    assert not r.act.torque
    np.testing.assert_allclose(r.act.pos, at)
    assert [e["code"] for e in r.events() if e["code"].startswith("shutdown")] == ["shutdown_torque_off"]


def test_a_torque_off_that_fails_at_shutdown_is_said_never_published_as_disabled(loop_rig):
    """The loop's last torque off fails (a joint does not confirm): clients hear an error naming
    the joint and the robot's last state is FAULT, never DISABLED (the failure was swallowed and
    DISABLED published: session 7's review)."""
    from crtk_bridge.errors import BackendError

    r = loop_rig(with_shutdown(action="torque_off"))
    enable_and_move(r)

    def no_confirmation():
        raise BackendError("so101: joint 'gripper' (id 6) did not confirm Torque_Enable = 0")
        yield  # pragma: no cover

    r.act._disable_steps = no_confirmation
    r.front.send(_enc({"cmd": "_shutdown"}))
    r.end()
    (failed,) = r.events("torque_off_unconfirmed")
    assert "shutdown" in failed["message"] and "'gripper'" in failed["message"], failed
    states = [m["data"]["state"] for m in r.msgs if m.get("event") == "operating_state"]
    assert states[-1] == "FAULT" and r.loop.controller.state is OperatingState.FAULT
    assert r.loop.controller.torque_unconfirmed


def test_a_torque_off_that_close_could_not_confirm_is_said_never_published_as_disabled(loop_rig):
    """The loop's torque off succeeded, but the backend's close() could not confirm it on a bus (a
    composite's own-rate bus whose worker was stuck in a call on it keeps the bus: no second thread
    runs its torque off) and reported a FAULT ``torque_off_unconfirmed``: clients hear it as an
    error naming the bus, and the robot's last state is FAULT, not DISABLED."""
    r = loop_rig(with_shutdown(action="torque_off"))
    enable_and_move(r)
    act, close = r.act, r.act._close_hook

    def stuck_bus_close():
        close()
        act.report_status(DeviceStatus.FAULT, Fault(
            "torque_off_unconfirmed", "so101: close: torque off not confirmed on bus 'gripper': its worker was "
            "still inside a call on the bus after 1 s", transient=False))

    act._close_hook = stuck_bus_close
    r.front.send(_enc({"cmd": "_shutdown"}))
    r.end()
    (failed,) = r.events("torque_off_unconfirmed")
    assert "shutdown" in failed["message"] and "bus 'gripper'" in failed["message"], failed
    states = [m["data"]["state"] for m in r.msgs if m.get("event") == "operating_state"]
    assert states[-1] == "FAULT" and r.loop.controller.state is OperatingState.FAULT


def test_no_park_while_a_lifecycle_transition_is_under_way():
    from .test_transitions import SlowActuator, make_slow_rig

    c, act, clock, cycle, send, replies = make_slow_rig(SlowActuator(PROFILE, enable_cycles=1))
    c.handle({"id": 1, "cmd": "enable"})
    cycle(5)
    assert c.state is OperatingState.ENABLED
    c.handle({"id": 2, "cmd": "pause"})  # three cycles long: the state stays ENABLED meanwhile
    assert c.state is OperatingState.ENABLED and c.is_busy
    assert not c.park()  # the shutdown aborts the transition and switches torque off instead
    cycle(5)
    assert c.state is OperatingState.PAUSED and c.park()  # once it ended, a PAUSED arm parks
