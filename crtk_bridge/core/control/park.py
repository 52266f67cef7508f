"""The shutdown park (``shutdown.action: park``): the controller's side of it; the loop
(core/loop.py) decides when it starts and ends."""

from __future__ import annotations

import numpy as np

from ..motion import Mode
from ..state import OperatingState


class ParkMixin:
    """The shutdown park of :class:`~.controller.Controller` (whose state it shares)."""

    def park(self) -> bool:
        """Shutdown park (``shutdown.action: park``): a jerk-limited move of every torqued
        namespace to the profile's rest pose, with busy edges. Returns False (nothing started)
        unless the robot is ENABLED or PAUSED with no lifecycle transition under way; a namespace
        left ``free`` stays free."""
        if self.state not in (OperatingState.ENABLED, OperatingState.PAUSED) or self._running is not None:
            return False  # (a lifecycle transition under way: the shutdown aborts it, torque off)
        rest = self.profile.shutdown.rest
        now = self.clock()
        self.homing = False
        for nc in self.native_cartesian.values():
            nc.cancel()  # the joints park from where the backend left them
        started = False
        for m in self.namespaces.values():
            if m.mode is Mode.FREE:
                continue
            here = m.setpoint_p  # a joint the rest pose does not name stops where it is
            m.start_move(np.array([rest.get(name, here[k]) for k, name in enumerate(m.joint_names)]), now)
            started = True
        if started:
            self.busy_seq += 1
            self.push_state()
        return started

    def in_motion(self) -> bool:
        """A move runs or a namespace is still braking (after pause, hold)."""
        return self.is_busy or any(m.mode is Mode.STOP for m in self.namespaces.values())

    def at_rest_pose(self) -> bool:
        """Every parked namespace's setpoint is at its move goal (the park move finished)."""
        return all(m.mode is Mode.FREE or np.allclose(m.setpoint_p, m.goal_p, atol=1e-6)
                   for m in self.namespaces.values())
