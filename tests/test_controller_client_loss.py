"""Client loss policy (docs/protocol.md, Client loss), driven on the controller directly: a command
with an end (move, home, interpolate_jp/jr goal) completes after its sender leaves; a command
without one (servo streams, velocity and effort setpoints and goals) stops and holds."""

from __future__ import annotations

import numpy as np

from crtk_bridge.core.motion import Mode

from .test_controller import rig  # noqa: F401 - the fixture


def _lost(c):
    c.outbox.clear()
    c.handle({"id": None, "cmd": "_client_lost"})
    return [m["data"]["code"] for m in c.outbox if m.get("event") == "warning"]


def test_a_move_completes_after_its_sender_left(rig):  # noqa: F811
    c, act, clock, cycle, req = rig
    assert req("enable")["ok"]
    goal = [0.3, 0.2, -0.2, 0.1, 0.0]
    assert req("move_jp", "so101", position=goal)["ok"]
    cycle(5)
    assert _lost(c) == []  # nothing was stopped: no control_released
    assert c.namespaces["so101"].mode is Mode.MOVE and c.is_busy
    cycle(3000)
    assert not c.is_busy
    np.testing.assert_allclose(act.pos[:5], goal, atol=1e-6)


def test_home_completes_after_its_sender_left(rig):  # noqa: F811
    c, act, clock, cycle, req = rig
    assert req("enable")["ok"]
    assert req("move_jp", "so101", position=[0.3, 0.2, -0.2, 0.1, 0.0])["ok"]
    cycle(3000)
    assert req("home")["ok"]
    cycle(5)
    _lost(c)
    assert c.homing
    cycle(3000)
    assert not c.is_busy and c.is_homed
    np.testing.assert_allclose(act.pos[:5], c.namespaces["so101"].home, atol=1e-6)


def test_an_interpolate_goal_is_reached_after_its_sender_left(rig):  # noqa: F811
    c, act, clock, cycle, req = rig
    assert req("enable")["ok"]
    goal = [0.05, 0.0, 0.0, 0.0, 0.0]
    assert req("interpolate_jp", "so101", position=goal)["ok"]
    assert _lost(c) == []
    cycle(100)
    np.testing.assert_allclose(act.pos[:5], goal, atol=1e-6)


def test_endless_commands_stop_and_hold_on_client_loss(rig):  # noqa: F811
    c, act, clock, cycle, req = rig
    assert req("enable")["ok"]
    assert req("servo_jv", "so101", velocity=[0.5, 0, 0, 0, 0])["ok"]
    cycle(10)
    assert _lost(c) == ["control_released"]
    m = c.namespaces["so101"]
    assert m.mode is Mode.STOP  # an integrated velocity brakes at the stop deceleration
    at_loss = act.pos.copy()
    cycle(50)
    assert m.mode is Mode.HOLD
    v, d = 0.5, c.stop_dec[0]
    assert 0 < act.pos[0] - at_loss[0] <= v * v / (2 * d) + v * c.dt  # stopped within its stopping distance
    held = act.pos.copy()
    cycle(50)
    np.testing.assert_allclose(act.pos, held)  # then holds
    assert req("interpolate_jv", "so101", velocity=[0.5, 0, 0, 0, 0])["ok"]
    cycle(10)
    assert _lost(c) == ["control_released"]
    assert m.mode is Mode.STOP
    cycle(50)
    assert m.mode is Mode.HOLD
