"""Supervision of the controller: what each cycle's read and write say about the device.

Fault counting (``safety.bus_errors_max`` transient faults in a row, or one non-transient),
tracking error (``safety.tracking_error_max`` for TRACKING_CYCLES cycles), the backend's fault
reaction (torque off, retried once a second until the bus confirms it), what the device reports
about itself (ONE table, ``state.DEVICE_STATUS``) and the loss of the controlling client.
"""

from __future__ import annotations

import math

import numpy as np

from ...errors import fmt_number
from ..actuator import DEVICE_NEWS, CommandMode, DeviceStatus, Fault, JointFeedback, Lifecycle
from ..motion import Mode
from ..state import DEVICE_STATUS, OperatingState
from .common import Refused

_STATUS_TEXT = {
    DeviceStatus.OK: "the device reports it is ok again",
    DeviceStatus.PAUSED: "the device paused itself",
    DeviceStatus.POWERED_OFF: "the device powered itself off",
    DeviceStatus.FAULT: "the device reports a fault",
    DeviceStatus.FAULT_CLEARED: "the device's fault cleared (enable or disable to go on)",
    DeviceStatus.WARNING: "the device warns",
    DeviceStatus.NOTICE: "the device reports",
}
_POSITION = int(CommandMode.POSITION)
TRACKING_CYCLES = 3  # consecutive cycles beyond the bound before FAULT (one glitch is not a fault)


class SupervisorMixin:
    """Faults, fault reaction, device status and client loss of :class:`~.controller.Controller`
    (whose state it shares)."""

    def _client_lost(self) -> None:
        """The controlling session went away. Commands with an end (a move, home, an
        interpolate_jp/jr goal) run to it; commands without one (servo streams, velocity and
        effort setpoints and goals) stop and hold (docs/protocol.md, Client loss)."""
        endless = [m for m in self.namespaces.values() if m.streaming and m.mode is not Mode.INTERP_P]
        native = [nc for nc in self.native_cartesian.values() if nc.active and not nc.busy]  # a native move runs on
        if self.state is OperatingState.ENABLED and (endless or native):
            for m in endless:
                m.stop()
            for nc in native:
                nc.cancel()
            names = [m.name for m in endless] + [nc.motion.name for nc in native]
            self.event("warning", "control_released",
                       f"{self.robot}: controlling client disconnected; holding {', '.join(names)}")

    def enter_fault(self, fault: Fault) -> None:
        """FAULT with ``fault`` as the cause, and the backend's fault reaction (also the loop's
        way to fault the robot on its own error)."""
        self.fault_cause = fault
        run = self._running
        torque_going_off = run is not None and run.transition.kind is Lifecycle.DISABLE and not run.rids
        if run is not None and not torque_going_off:
            self._abort_running(f"{run.transition.kind.value} aborted: {fault.message}")
        self._abort_motion()
        message = fault.message
        if not torque_going_off:  # every backend's reaction: torque off (the DISABLE transition)
            message += self._torque_off()
        self.event("error", fault.code, message, joint=fault.joint, register=fault.register,
                   value=fault.value)
        self._set_state(OperatingState.FAULT)

    def _torque_off(self) -> str:
        """Start the DISABLE transition of a fault (no request waits for it). Returns what to add
        to the fault's message when its first step could not confirm torque off."""
        said: list[str] = []
        first = [True]

        def done() -> None:
            if self._torque_unconfirmed:
                self.event("status", "torque_off_confirmed", f"{self.robot}: torque off confirmed on every joint")
            self._torque_unconfirmed = False

        def failed(exc: Exception) -> Refused:  # the bus may be gone: say so, retry once it answers
            if not self._torque_unconfirmed:
                text = f"; torque off not confirmed ({exc}); retrying when the bus answers"
                if first[0]:
                    said.append(text)  # goes into the fault's own error event
                else:
                    self.event("error", "torque_off_unconfirmed", f"{self.robot}{text}")
            self._torque_unconfirmed = True
            return Refused("fault", str(exc))

        self._start(self.actuator.begin(Lifecycle.DISABLE), done, failed, reply=False)
        first[0] = False
        return said[0] if said else ""

    def _retry_torque_off(self) -> None:
        """In FAULT with torque off unconfirmed: the bus answered again, switch torque off now."""
        if self._running is None:
            self._torque_off()

    def _device_status(self, status: DeviceStatus, cause: Fault | None) -> None:
        """What the device reported, mapped onto the CRTK state by ``state.DEVICE_STATUS``."""
        target, kind, code = DEVICE_STATUS[(self.state, status)]
        if target is OperatingState.FAULT:
            if self.state is not OperatingState.FAULT:
                self.enter_fault(cause or Fault("device_fault", f"{self.robot}: the device reports a fault",
                                                 transient=False))
            return
        if kind is not None:
            what = _STATUS_TEXT[status]
            message = f"{self.robot}: {what}" + (f": {cause.message}" if cause is not None else "")
            if status in DEVICE_NEWS and cause is not None:  # which register said what
                self.event(kind, code, message, joint=cause.joint, register=cause.register, value=cause.value)
            else:
                self.event(kind, code, message, joint=cause.joint if cause else None)
            if status is DeviceStatus.NOTICE and cause is not None and cause.joint is not None:
                self._device_notices[cause.joint] = {"register": cause.register, "value": cause.value,
                                                     "message": cause.message}
                self.push_state()  # operating_state carries each joint's latest notice
        if target is OperatingState.PAUSED and self.state is OperatingState.ENABLED:
            self._abort_running("aborted: the device paused itself")
            self._stop_all()
            self.homing = False
            self._set_state(OperatingState.PAUSED)
        elif target is OperatingState.DISABLED and self.state is not OperatingState.DISABLED:
            self._abort_running("aborted: the device powered itself off")
            self._abort_motion()
            # the device is off already; the transition only brings the backend's side along
            self._start(self.actuator.begin(Lifecycle.DISABLE), lambda: None,
                        lambda exc: Refused("fault", str(exc)), reply=False)
            self.fault_cause = None
            self._set_state(OperatingState.DISABLED)

    def on_read(self, feedback: JointFeedback, fault: Fault | None) -> None:
        """Account for this cycle's read. A fault (after ``safety.bus_errors_max`` transient ones
        in a row, or at once for a non-transient one) puts the robot in FAULT, torque off. A joint
        whose measured position stays farther than ``safety.tracking_error_max`` from its position
        command for TRACKING_CYCLES cycles does too (not while the backend homes natively: the
        drive moves by itself then, and core takes the homed position when it ends)."""
        self._cycle += 1
        active = self.state in (OperatingState.ENABLED, OperatingState.PAUSED)
        news = self.actuator.take_status()
        if fault is not None:
            self._consecutive_bus_errors += 1
            if active and (not fault.transient or self._consecutive_bus_errors >= self.safety.bus_errors_max):
                self.enter_fault(fault)
            if news is not None:
                self._device_status(*news)
            return
        if news is not None:
            self._device_status(*news)
        self._consecutive_bus_errors = 0
        speed = self.actuator.speed_fraction if self.traits.speed_scaling else math.nan
        if speed == speed and abs(speed - self._speed_fraction) >= 0.005 or (speed == speed) != (
                self._speed_fraction == self._speed_fraction):
            self._speed_fraction = speed  # the operator moved the slider: clients hear of it
            self.push_state()
        if self._torque_unconfirmed and self.state is OperatingState.FAULT:
            now = self.clock()
            if now - self._last_torque_retry >= 1.0:  # acknowledged writes: at most once a second
                self._last_torque_retry = now
                self._retry_torque_off()
        f = self.feedback
        f.position[:] = feedback.position
        f.velocity[:] = feedback.velocity
        f.effort[:] = feedback.effort
        f.stamp = feedback.stamp
        if f.cartesian is not None and feedback.cartesian is not None:
            f.cartesian.copy_from(feedback.cartesian)  # the tip pose a native cartesian backend measures
        run = self._running
        native_home = run is not None and run.transition.kind is Lifecycle.HOME  # the drive moves itself
        if active and self._written and not native_home:
            cmd = self.command
            # the worst joint in position mode beyond the bound; Python floats over a few joints cost
            # a fifth of the numpy expression (an enum compare, argmax) in every cycle (bench_cpu.py)
            bound = self.safety.tracking_error_max
            j, worst = -1, bound
            for i, (p, c, m) in enumerate(zip(f.position.tolist(), cmd.position.tolist(), cmd.mode.tolist())):
                e = abs(p - c)
                if m == _POSITION and e > worst:
                    j, worst = i, e
            if j >= 0:
                err = np.abs(f.position - cmd.position)
                self._tracking_cycles += 1
                if self._tracking_cycles >= TRACKING_CYCLES:
                    name = self.profile.joints[j].name
                    self.enter_fault(Fault(
                        "tracking_error",
                        f"{self.robot}: joint {name!r} is {fmt_number(err[j], 3)} rad from its setpoint {fmt_number(cmd.position[j], 3)} "
                        f"(safety.tracking_error_max = {self.safety.tracking_error_max}): blocked or not following",
                        joint=name, value=float(err[j]), transient=False))
            else:
                self._tracking_cycles = 0

    def on_write(self, fault: Fault | None) -> None:
        """Account for this cycle's write: as for reads, ``safety.bus_errors_max`` failed writes in
        a row (or one non-transient) put the robot in FAULT; counted apart from reads, so good
        reads cannot hide a bus that takes no commands."""
        if fault is None:
            self._consecutive_write_errors = 0
            return
        self._consecutive_write_errors += 1
        if self.state in (OperatingState.ENABLED, OperatingState.PAUSED) and (
            not fault.transient or self._consecutive_write_errors >= self.safety.bus_errors_max
        ):
            self.enter_fault(fault)
