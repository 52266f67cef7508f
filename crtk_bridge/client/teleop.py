"""Leader -> follower teleoperation in joint space, as a client of two daemons (``crtk-ctl teleop``).

A leader arm (e.g. the SO-101 leader, torque off, moved by hand) is read with ``measured_js``; its
positions are streamed to the follower with ``interpolate_jp`` (the follower's daemon interpolates
the stream with its own velocity bounds, clips to its joint limits and refuses a step beyond
``safety.servo_step_max``). The states are dVRK's teleoperation component's:

``SETTING_ARMS_STATE``
    both daemons answer; the follower is ENABLED (teleop never enables a robot: it refuses with
    the command that does); namespaces are paired (by position, or as given) with equal joint
    counts; control of the follower is taken (``acquire``).
``ALIGNING``
    nothing is sent to the follower until, on every paired joint, the leader's measured position
    is within ``tolerance`` (rad, TOLERANCE_MIN to TOLERANCE_MAX) of the follower's: the operator
    brings the leader to the follower. With ``align="move"`` the follower is moved to the leader instead, once, by a
    ``move_jp`` (a motion the operator asked for; bounded by the follower's limits).
``ENABLED``
    following: one ``interpolate_jp`` per namespace per tick at ``rate_hz`` (from RATE_MIN_HZ to
    the lower loop rate of the two daemons; default RATE_DEFAULT_HZ, or that loop rate if lower).

Back to ALIGNING, with the follower holding (``hold``), when the leader's data turns invalid
(stamp 0) or not finite, the follower refuses a step (the leader jumped), or the follower is PAUSED: teleop
then gives control up so the operator can ``resume`` it from another session, and takes it
again once the follower is ENABLED (waiting while another session holds it). It ends, the
follower holding, when the follower leaves ENABLED otherwise (FAULT, DISABLED), when either
daemon goes away (:class:`TeleopError` naming which), on ``stop()`` or after ``duration`` s.
Ending never disables or frees the follower.
"""

from __future__ import annotations

import math
import numbers
import threading
import time
from dataclasses import dataclass
from typing import Callable

from crtk_bridge.client.connection import DaemonConnectionError
from crtk_bridge.client.device import Device, Robot
from crtk_bridge.errors import CommandError, CrtkBridgeError, fmt_number

SETTING_ARMS_STATE, ALIGNING, ENABLED, DISABLED = "SETTING_ARMS_STATE", "ALIGNING", "ENABLED", "DISABLED"
#: how often ALIGNING repeats which joint is still off (s)
_ALIGN_REPORT_S = 1.0

#: samples per second (--rate). At most the loop rate of either daemon: the follower's
#: interpolation reaches each sample one estimated command period later, a period it never takes
#: shorter than its loop's, so faster samples only overwrite each other (and the leader's
#: measured_js changes once per its loop). At least RATE_MIN_HZ: that period is the lag the
#: follower adds behind the hand (100 ms at 10 Hz), and it nears the follower's servo watchdog
#: (safety.servo_timeout_s, 0.5 s by default), after which it holds between two samples.
RATE_MIN_HZ = 10.0
RATE_DEFAULT_HZ = 50.0
#: alignment tolerance (--tolerance, rad). The first interpolate_jp after ALIGNING is a step of up
#: to it, made within one sample period and bounded only by the follower's velocity limits: beyond
#: a few tenths of a radian that is a lurch of the follower, not a take-over, and near the
#: follower's safety.servo_step_max (0.35 rad by default) the step is refused and teleop falls
#: back to ALIGNING. Below TOLERANCE_MIN no hand holds a leader still enough (a 4096-tick servo
#: reads in steps of 1.5 mrad, and the measurement is noisy).
TOLERANCE_MIN, TOLERANCE_MAX = 0.01, 0.3


def rate_problem(rate_hz: float, cap_hz: float | None = None, capped_by: str = "") -> str | None:
    """Why ``rate_hz`` is no teleop rate (finite, from RATE_MIN_HZ to ``cap_hz``: the lower loop
    rate of the two daemons, ``capped_by`` naming whose), or ``None``."""
    high = f"{cap_hz:g} Hz ({capped_by})" if cap_hz is not None else "the daemons' loop rate (Hz)"
    if not (math.isfinite(rate_hz) and rate_hz >= RATE_MIN_HZ and (cap_hz is None or rate_hz <= cap_hz)):
        return f"must be from {RATE_MIN_HZ:g} to {high}, got {rate_hz:g}"
    return None


def tolerance_problem(tolerance: float) -> str | None:
    """Why ``tolerance`` (rad) is no alignment tolerance, or ``None``."""
    if not (math.isfinite(tolerance) and TOLERANCE_MIN <= tolerance <= TOLERANCE_MAX):
        return f"must be from {TOLERANCE_MIN:g} to {TOLERANCE_MAX:g} rad, got {tolerance:g}"
    return None


class TeleopError(CrtkBridgeError):
    """Teleoperation cannot start or had to end; the message names the robot and namespace."""


@dataclass(frozen=True)
class Pair:
    leader: Device
    follower: Device

    def __str__(self) -> str:
        return f"{self.leader.name} -> {self.follower.name}"


def pair_namespaces(leader: Robot, follower: Robot, pairs: list[str] | None = None) -> list[Pair]:
    """The namespaces to pair: ``pairs`` as ``"LEADER_NS=FOLLOWER_NS"``, else every namespace of
    the leader with the follower's at the same position. Each pair must have the same number of
    joints (joint i follows joint i), and a joint name both sides use at the same index. Raises
    :class:`TeleopError` naming what does not match."""
    if pairs:
        out = []
        for text in pairs:
            lead_ns, sep, follow_ns = text.partition("=")
            if not sep or not lead_ns or not follow_ns:
                raise TeleopError(f"--pair {text!r}: expected LEADER_NS=FOLLOWER_NS")
            try:
                out.append(Pair(leader.device(lead_ns), follower.device(follow_ns)))
            except KeyError as exc:
                raise TeleopError(f"--pair {text!r}: {exc.args[0]}") from None
    else:
        if len(leader.namespaces) != len(follower.namespaces):
            raise TeleopError(
                f"leader {leader.name!r} has namespaces {leader.namespaces}, follower {follower.name!r} "
                f"has {follower.namespaces}: say which follow which with --pair LEADER_NS=FOLLOWER_NS")
        out = [Pair(leader.device(a), follower.device(b)) for a, b in zip(leader.namespaces, follower.namespaces)]
    for p in out:
        if len(p.leader.joint_names) != len(p.follower.joint_names):
            raise TeleopError(f"{p}: the leader has {len(p.leader.joint_names)} joints "
                              f"({', '.join(p.leader.joint_names)}), the follower {len(p.follower.joint_names)} "
                              f"({', '.join(p.follower.joint_names)})")
        lead, follow = list(p.leader.joint_names), list(p.follower.joint_names)
        for i, name in enumerate(lead):  # a joint named on both sides must be at the same index
            if name in follow and follow.index(name) != i:
                raise TeleopError(f"{p}: leader joint {i} is {name!r}, follower joint {i} is {follow[i]!r} "
                                  f"('{name}' is follower joint {follow.index(name)}): joint i follows joint i, so "
                                  f"the profiles must list the joints in the same order")
        if not p.follower.supports("interpolate_jp"):
            raise TeleopError(f"{p.follower.name}: the follower does not offer interpolate_jp")
    return out


def _number(option: str, value: object) -> float:
    """``value`` as a float; a string, None or bool is refused (TeleopError naming ``option``)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise TeleopError(f"{option}: expected a number, got {value!r}")
    return float(value)


class Teleop:
    """Joint-space teleoperation of ``follower`` by ``leader`` (see the module's docstring).
    ``on_state(state, message)`` is called on every state change and with ALIGNING's progress."""

    def __init__(self, leader: Robot, follower: Robot, *, pairs: list[str] | None = None,
                 rate_hz: float | None = None, tolerance: float = 0.1, align: str = "wait",
                 on_state: Callable[[str, str], None] | None = None):
        if leader.connection.path == follower.connection.path:
            raise TeleopError(f"the leader and the follower are the same daemon ({leader.connection.path})")
        cap, capped_by = min((float(robot.info["rate_hz"]), f"the loop rate of the {role} {robot.name!r}")
                             for role, robot in (("follower", follower), ("leader", leader)))
        rate_hz = min(RATE_DEFAULT_HZ, cap) if rate_hz is None else _number("--rate (rate_hz)", rate_hz)
        problem = rate_problem(rate_hz, cap, capped_by)
        if problem:
            raise TeleopError(f"--rate (rate_hz): {problem}")
        tolerance = _number("--tolerance (tolerance)", tolerance)
        problem = tolerance_problem(tolerance)
        if problem:
            raise TeleopError(f"--tolerance (tolerance): {problem}")
        if align not in ("wait", "move"):
            raise TeleopError(f"align must be 'wait' or 'move', got {align!r}")
        self.leader, self.follower = leader, follower
        self.pairs = pair_namespaces(leader, follower, pairs)
        self.period = 1.0 / rate_hz
        self.tolerance = float(tolerance)
        self.align = align
        self.state = DISABLED
        self._on_state = on_state or (lambda state, message: None)
        self._stop = threading.Event()
        self._last_report = 0.0
        self._in_control = False  # holds the follower's control (acquire; given up while PAUSED)

    # -- control from another thread -------------------------------------------------------
    def stop(self) -> None:
        """End :meth:`run` at its next tick (the follower holds)."""
        self._stop.set()

    # -- the loop --------------------------------------------------------------------------
    def run(self, duration: float | None = None) -> None:
        """Teleoperate until :meth:`stop`, ``duration`` s, or an error (:class:`TeleopError`,
        after the follower was told to hold). Ends in state DISABLED."""
        end = None if duration is None else time.monotonic() + duration
        try:
            self._set(SETTING_ARMS_STATE, f"{self.leader.name} -> {self.follower.name}: "
                                          + ", ".join(str(p) for p in self.pairs))
            self._setting_arms_state()
            self._set(ALIGNING, self._align_message())
            tick = time.monotonic()
            while not self._stop.is_set() and (end is None or time.monotonic() < end):
                self._step()
                tick += self.period
                delay = tick - time.monotonic()
                if delay > 0:
                    self._stop.wait(delay)
                else:  # late (a slow daemon): do not try to catch up with a burst
                    tick = time.monotonic()
        finally:
            if self.state in (ENABLED, ALIGNING):
                self._hold_all()
            self._set(DISABLED, "stopped")

    def _setting_arms_state(self) -> None:
        state = self._follower_call(lambda: self.follower.operating_state())
        if state != "ENABLED":
            raise TeleopError(
                f"follower {self.follower.name!r} is {state}: teleop never enables a robot; enable it first "
                f"(crtk-ctl --robot {self.follower.name} enable)")
        self._follower_call(self.follower.acquire)
        self._in_control = True

    def _step(self) -> None:
        lead = [self._leader_position(p) for p in self.pairs]
        if self.state == ALIGNING:
            if not self._follower_ready() or any(q is None for q in lead):
                return
            follow = [self._follower_call(lambda p=p: p.follower.measured_jp()[0]) for p in self.pairs]
            worst = self._worst(lead, follow)
            if worst is None:
                self._set(ENABLED, "following")
            elif self.align == "move":
                self._move_follower(lead)
            else:
                self._report_alignment(worst)
            return
        if any(q is None for q in lead):
            self._realign("the leader's measured_js is invalid (stamp 0)")
            return
        for p, q in zip(self.pairs, lead):
            try:
                self._follower_call(lambda p=p, q=q: p.follower.interpolate_jp(q))
            except CommandError as exc:
                self._refused(p, exc)
                return

    def _follower_ready(self) -> bool:
        """ALIGNING: True when the follower is ENABLED and under our control. PAUSED: False,
        control given up so the operator can resume it from another session (a resume is not a
        stop: only the controlling session may send it). FAULT / DISABLED: TeleopError."""
        state = self._follower_call(lambda: self.follower.operating_state())
        if state == "PAUSED":
            if self._in_control:
                self._in_control = False
                self._follower_call(self.follower.release)
            self._report(f"follower {self.follower.name!r} is PAUSED: waiting for resume "
                         f"(crtk-ctl --robot {self.follower.name} resume)")
            return False
        if state != "ENABLED":
            raise TeleopError(f"follower {self.follower.name!r} is {state}: teleop ended")
        if not self._in_control:
            try:
                self._follower_call(self.follower.acquire)
            except CommandError as exc:  # the operator's resume session may not have closed yet
                self._report(f"follower {self.follower.name!r}: waiting for control ({exc.message})")
                return False
            self._in_control = True
        return True

    def _leader_position(self, p: Pair) -> np.ndarray | None:
        try:
            q, ts = p.leader.measured_jp()
        except (DaemonConnectionError, ConnectionError, TimeoutError) as exc:
            raise TeleopError(f"leader {self.leader.name!r} went away: {exc}") from exc
        # invalid (stamp 0), short or non-finite data is no position to follow or align on
        import numpy as np  # here, not at the top: crtk-ctl's other commands need no numpy
        valid = ts != 0.0 and len(q) == len(p.leader.joint_names) and bool(np.all(np.isfinite(q)))
        return q if valid else None

    def _follower_call(self, fn):
        try:
            return fn()
        except (DaemonConnectionError, ConnectionError, TimeoutError) as exc:
            raise TeleopError(f"follower {self.follower.name!r} went away: {exc}") from exc

    def _refused(self, p: Pair, exc: CommandError) -> None:
        if exc.code == "step_too_large":
            self._realign(f"{p.follower.name} refused the leader's step: {exc.message}")
            return
        if exc.code == "invalid_state":  # PAUSED: ALIGNING waits for resume; FAULT / DISABLED: it ends
            self._realign(f"{p.follower.name} refused interpolate_jp: {exc.message}")
            return
        raise TeleopError(f"{p.follower.name}: interpolate_jp refused ({exc.code}): {exc.message}") from exc

    def _realign(self, why: str) -> None:
        self._hold_all()
        self._set(ALIGNING, why)

    def _hold_all(self) -> None:
        for p in self.pairs:
            try:
                p.follower.hold()
            except (CrtkBridgeError, ConnectionError, TimeoutError):
                pass  # a PAUSED / FAULT / lost follower is stopped by its own daemon

    def _worst(self, lead: list[np.ndarray], follow: list[np.ndarray]) -> tuple[Pair, int, float] | None:
        """The pair and joint furthest from alignment, when any is beyond the tolerance."""
        import numpy as np
        worst = None
        for p, a, b in zip(self.pairs, lead, follow):
            err = np.abs(np.asarray(a) - np.asarray(b))
            j = int(np.argmax(err))
            if err[j] > self.tolerance and (worst is None or err[j] > worst[2]):
                worst = (p, j, float(err[j]))
        return worst

    def _report_alignment(self, worst: tuple[Pair, int, float]) -> None:
        p, j, err = worst
        self._report(f"{p.leader.name} joint {p.leader.joint_names[j]!r} is {fmt_number(err)} rad "
                     f"from {p.follower.name} joint {p.follower.joint_names[j]!r} "
                     f"(tolerance {fmt_number(self.tolerance)}): move the leader to the follower")

    def _report(self, message: str) -> None:
        """ALIGNING's progress, at most once per _ALIGN_REPORT_S."""
        now = time.monotonic()
        if now - self._last_report >= _ALIGN_REPORT_S:
            self._last_report = now
            self._on_state(ALIGNING, message)

    def _move_follower(self, lead: list[np.ndarray]) -> None:
        self._on_state(ALIGNING, "moving the follower to the leader (move_jp)")
        for p, q in zip(self.pairs, lead):
            try:
                handle = self._follower_call(lambda p=p, q=q: p.follower.move_jp(q))
            except CommandError as exc:
                raise TeleopError(f"{p.follower.name}: cannot move to the leader ({exc.code}): {exc.message}") from exc
            deadline = time.monotonic() + 30.0
            while not self._follower_call(lambda h=handle: h.wait(timeout=0.1)):
                if self._stop.is_set():
                    return  # run() ends at once and holds the follower
                if time.monotonic() > deadline:
                    raise TeleopError(f"{p.follower.name}: the move to the leader did not end within 30 s")
        # the leader may have moved meanwhile: the next tick checks the alignment again

    def _align_message(self) -> str:
        if self.align == "move":
            return "moving the follower to the leader"
        return f"waiting until every leader joint is within {fmt_number(self.tolerance)} rad of the follower's"

    def _set(self, state: str, message: str) -> None:
        self.state = state
        self._last_report = time.monotonic()
        self._on_state(state, message)
