"""``crtk-ctl replay``: play a recording's joint positions back on the robot (docs/recording.md).

First a ``move_jp`` to the recording's first position (the operator confirms it, or ``--yes``:
never a jump), then the recorded positions at their recorded timing (``--speed`` scales it) as an
``interpolate_jp`` stream: the daemon's bounded streaming command, so the state machine, the
joint limits, ``safety.servo_step_max`` and the velocity limits apply to every sample as to any
client's. ``interpolate_jp`` rather than ``servo_jp``: a recording holds every control cycle
(up to 1 kHz) but a client's samples go out over a socket at tens of Hz with jitter; the daemon
moves the setpoint linearly to each goal over one command period, never faster than the velocity
limits, so the replay is smooth at any rate the client keeps, where ``servo_jp`` samples would
step the setpoint (the cost: one command period of lag). A recording of another robot, or of a
namespace whose joints differ, is refused naming the difference.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from crtk_bridge.client.bagfile import BagError, JointSeries, Recording
from crtk_bridge.client.pacing import Pacing
from crtk_bridge.errors import CommandError, CrtkBridgeError

RATE_DEFAULT_HZ = 50.0


@dataclass
class Plan:
    """What replay sends: ``t`` (s from the first sample, recording clock) and ``q`` (positions)."""

    ns: str
    topic: str
    names: list[str]
    t: np.ndarray
    q: np.ndarray

    @property
    def duration(self) -> float:
        return float(self.t[-1]) if len(self.t) else 0.0

    def at(self, t: float) -> np.ndarray:
        """The recorded position at ``t`` s after the first sample (linear between samples)."""
        return np.array([np.interp(t, self.t, self.q[:, j]) for j in range(self.q.shape[1])])


def plan(rec: Recording, robot_name: str, ns: str, topic: str, joint_names: list[str]) -> Plan:
    """The positions of ``/<ns>/<topic>`` in ``rec``, checked against the robot they go to:
    raises :class:`BagError` naming the difference (robot, namespace, joint names) or when the
    recording holds no positions there."""
    if rec.robot and rec.robot != robot_name:
        raise BagError(f"{rec.path}: recorded on robot {rec.robot!r}, this is {robot_name!r}: replay refused "
                       "(a recording plays back on the robot it was made on)")
    if ns not in rec.namespaces:
        raise BagError(f"{rec.path}: namespace {ns} is not in this recording (recorded: {', '.join(rec.namespaces)}); "
                       "give --ns")
    s: JointSeries = rec.series(ns, topic)
    if s.names != list(joint_names):
        extra = [n for n in s.names if n not in joint_names]
        absent = [n for n in joint_names if n not in s.names]
        diff = "; ".join(x for x in (f"recorded only: {', '.join(extra)}" if extra else "",
                                      f"not recorded: {', '.join(absent)}" if absent else "") if x) or \
            f"the order differs: recorded {', '.join(s.names)}"
        raise BagError(f"{rec.path}: /{ns}/{topic} has joints {', '.join(s.names) or 'none'}, {robot_name} {ns} has "
                       f"{', '.join(joint_names)} ({diff}): replay refused")
    ok = np.isfinite(s.position).all(axis=1) if s.position.size else np.zeros(0, bool)
    if not ok.any():
        raise BagError(f"{rec.path}: /{ns}/{topic} holds no positions (no setpoint was set while recording; "
                       "try --topic measured_js)")
    t = s.t[ok]
    return Plan(ns, topic, list(s.names), t - t[0], s.position[ok])


@dataclass
class Report:
    samples: int
    duration_s: float
    elapsed_s: float


def stream(dev, p: Plan, speed: float, rate_hz: float,
           clock: Callable[[], float] | None = None, sleep: Callable[[float], None] | None = None) -> Report:
    """Send ``p``'s positions as ``interpolate_jp`` goals at ``rate_hz`` for the recording's
    duration divided by ``speed``, each the recorded position at the tick's time (the newest due
    when a reply came late: client/pacing.py). The caller holds on Ctrl-C."""
    import time

    duration = max(p.duration / speed, 1.0 / rate_hz)
    kwargs = {}
    if clock is not None:
        kwargs["clock"] = clock
    if sleep is not None:
        kwargs["sleep"] = sleep
    pacing = Pacing(duration, rate_hz, **kwargs)
    t0 = time.monotonic()
    for tick in pacing:
        at = min(p.duration, tick.index * pacing.period * speed)
        try:
            dev.interpolate_jp(p.at(at).tolist())
        except CommandError:  # a sample refused (step_too_large, a FAULT...): the arm holds, as Device.stream's
            try:
                dev.hold()
            except (CrtkBridgeError, ConnectionError, TimeoutError):
                pass
            raise
    return Report(pacing.sent, duration, time.monotonic() - t0)


def largest_offset(p: Plan, measured: list[float]) -> tuple[float, str]:
    """(rad, joint) of the largest distance from ``measured`` to the recording's first position."""
    d = np.abs(np.asarray(measured, float) - p.q[0])
    j = int(np.argmax(d))
    return float(d[j]), p.names[j]

