"""The control process: the real-time loop around the backend and the controller.

Each cycle, at the ONE effective period (:func:`~crtk_bridge.core.actuator.effective_period_s`:
the profile's rate, or the hardware's when the backend paces the cycle), run by the ONE cycle
runner (core/cycle.py: wait -> read -> requests + state machine -> motion -> limits -> write), then
-> publish snapshot -> push the cycle's sample into the ring (core/samples.py: recording, black
box) -> send replies and events. It asks for SCHED_FIFO and mlockall (and says once,
with a ``realtime_unavailable`` warning, when it cannot), freezes the GC after start-up, and keeps
logging, allocation-heavy work and blocking I/O out of the cycle.

It talks to the front process over one SOCK_SEQPACKET socketpair (msgpack messages, never the
network) and publishes state through :class:`~crtk_bridge.core.snapshot.SnapshotBuffer`, whose
header carries the front's count of the messages it sent: a cycle where it did not move makes no
receive (one at least every RECEIVE_AT_LEAST_S, so the front's loss is seen).
If the front process goes away (EOF on the pair), the loop stops safely, as on SIGTERM / SIGINT
or the front's ``_shutdown``: with ``shutdown.action: park`` an ENABLED (or PAUSED) robot first
moves to its rest pose, the cycle running on (see :meth:`ControlLoop._parking`); then torque off,
exit. A second signal, or a stop command (disable, pause, hold), cuts the park short.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import os
import signal
import socket
import threading
import time
from collections import deque
from typing import Any, Callable

import msgspec

from ..errors import CrtkBridgeError
from ..profile import Profile
from .actuator import Actuator, Fault, Lifecycle, effective_period_s
from .control import Controller
from .cycle import CycleRunner
from .samples import SampleRing
from .snapshot import RING, SnapshotBuffer
from .state import OperatingState

_encode = msgspec.msgpack.Encoder().encode
_decode = msgspec.msgpack.Decoder().decode
MAX_REQUESTS_PER_CYCLE = 64
_STOPS = ("disable", "pause", "hold")  # accepted during a shutdown park: a stop is never refused
MAX_MESSAGE = 1 << 17  # bytes; the front refuses request lines above server.MAX_LINE (64 KiB)
#: the longest (s) the loop goes without a receive on the pair while the front's count of what it
#: sent stands still (the snapshot's ``posted``): a front that died (EOF) is seen within it
RECEIVE_AT_LEAST_S = 0.02


def _threads() -> list[int]:
    """The ids of this process's threads (Linux; 0 alone, "this thread", elsewhere)."""
    try:
        return [0] + [int(t) for t in os.listdir("/proc/self/task") if int(t) != threading.get_native_id()]
    except OSError:
        return [0]


def _each_thread(fn, tid: int, *args) -> None:
    try:
        fn(tid, *args)
    except ProcessLookupError:
        pass  # a thread that ended meanwhile


def request_realtime(priority: int, cpu: int | None) -> list[str]:
    """Ask for SCHED_FIFO and locked memory, for every thread of the process: the threads a
    backend started at open (a bus's receive thread, python-can's notifier for CANopen) carry the
    cycle's data, and left at the normal class a loaded host starves them (the drives answered,
    the loop hears nothing). They get one priority below the calling (loop) thread's, so the loop
    preempts any of them that spins; threads for blocking work started later drop the class they
    inherit (``actuator.background_thread``). Returns what could not be had (empty = all good)."""
    problems = []
    if cpu is not None:
        try:
            for tid in _threads():
                _each_thread(os.sched_setaffinity, tid, {cpu})
        except OSError as exc:
            problems.append(f"CPU affinity {cpu}: {exc.strerror}")
    try:
        for tid in _threads():  # 0 first: the calling (loop) thread
            prio = priority if tid == 0 else max(1, priority - 1)
            _each_thread(os.sched_setscheduler, tid, os.SCHED_FIFO, os.sched_param(prio))
    except (OSError, AttributeError) as exc:
        problems.append(f"SCHED_FIFO priority {priority}: {getattr(exc, 'strerror', exc)} "
                        "(grant CAP_SYS_NICE or LimitRTPRIO, see systemd/README.md)")
    libc_name = ctypes.util.find_library("c")
    if libc_name:
        libc = ctypes.CDLL(libc_name, use_errno=True)
        MCL_CURRENT, MCL_FUTURE = 1, 2
        if libc.mlockall(MCL_CURRENT | MCL_FUTURE) != 0:
            err = ctypes.get_errno()
            problems.append(f"mlockall: {os.strerror(err)} (raise LimitMEMLOCK)")
    return problems


def steady_epoch_clock() -> Callable[[], float]:
    """Seconds since the Unix epoch that never step: the monotonic clock, anchored to the wall
    clock once. The controller times motion with it (servo watchdog, interpolation, transition
    time limits): the wall clock may step back when NTP sets it, which stopped the watchdog and
    ran an interpolation the wrong way. Its stamps stay within the wall clock's slew of epoch time."""
    offset = time.time() - time.monotonic()
    mono = time.monotonic
    return lambda: offset + mono()


class ControlLoop:
    """Owns the backend, the controller and the loop. Runs in the control process."""

    def __init__(self, profile: Profile, actuator: Actuator, chan: socket.socket, snapshot: SnapshotBuffer,
                 realtime: bool = True, samples: SampleRing | None = None):
        self.profile = profile
        #: every cycle's sample for the front (recording, black box): core/samples.py
        self.samples = samples
        self.actuator = actuator
        self.chan = chan
        self.snap = snapshot
        self.realtime = realtime
        self.period = effective_period_s(profile, actuator)  # computed once; everyone uses it
        self.controller = Controller(profile, actuator, steady_epoch_clock(), self.period)
        self.runner = CycleRunner(actuator, self.period)  # the one cycle: wait, read, step, write
        self.pending: deque[bytes] = deque()  # messages the pair could not take yet
        self.running = True
        self.front_alive = True
        self._park_deadline: float | None = None  # perf_counter time limit of a shutdown park
        self._park_t0 = 0.0
        self.abort_park = False  # a second signal: torque off now
        self._signals = 0  # SIGTERM / SIGINT received by this process (request_stop)
        ns = list(self.controller.namespaces.values())
        self._ns = ns
        self._native_rows = [(k, self.controller.native_cartesian[m.name].row, self.controller.native_cartesian[m.name])
                             for k, m in enumerate(ns) if m.name in self.controller.native_cartesian]
        v = snapshot.views
        self._v = v
        # the namespaces' setpoint p, v, f and goal p, v, f: one (6, joints) view of the snapshot,
        # written from each namespace's block (core/motion.py) in one copy
        sl = snapshot.layout.slices
        n = len(profile.joints)
        assert [sl[f].start for f in ("setpoint_p", "setpoint_v", "setpoint_f", "goal_p", "goal_v", "goal_f")] \
            == [sl["setpoint_p"].start + i * n for i in range(6)], "snapshot layout: setpoints and goals in a row"
        self._motion_block = snapshot.data[sl["setpoint_p"].start:sl["goal_f"].stop].reshape(6, n)
        self._ns_blocks = [(k, m, m.cols) for k, m in enumerate(ns)]
        assert [sl[f].start for f in ("measured_p", "measured_v", "measured_f")] \
            == [sl["measured_p"].start + i * n for i in range(3)], "snapshot layout: measured p, v, f in a row"
        self._measured = snapshot.data[sl["measured_p"].start:sl["measured_f"].stop].reshape(3, n)
        # the snapshot's fields _publish writes in every cycle, looked up once
        self._pub = tuple(v[name] for name in (
            "measured_stamp", "ns_setpoint_stamp", "ns_has_p", "ns_has_v", "ns_has_f",
            "ns_goal_stamp", "ns_goal_has_p", "ns_goal_has_v", "ns_goal_has_f"))
        self._native_pub = tuple(v[name] for name in (
            "ns_cart_stamp", "ns_cart_p", "ns_cart_q", "ns_cart_f", "ns_cart_sp_stamp", "ns_cart_sp_p",
            "ns_cart_sp_q", "ns_cart_tw_stamp", "ns_cart_tw", "ns_cart_tw_frame", "ns_cart_goal_stamp",
            "ns_cart_goal_p", "ns_cart_goal_q"))
        # the front's count of its sends on the pair (two per message: odd while one is under way;
        # -1: not counted, receive every cycle), and the even count the last receive that emptied
        # the pair had seen before it began (server/link.py)
        self._posted = snapshot.posted
        self._drained = -1
        self._quiet = 0  # cycles since the last receive
        self._quiet_max = max(0, int(RECEIVE_AT_LEAST_S / self.period) - 1)

    # ---------------------------------------------------------------- messaging
    def _send(self, msg: dict) -> None:
        data = _encode(msg)
        if self.pending:
            self.pending.append(data)
            return
        try:
            self.chan.send(data, socket.MSG_DONTWAIT)
        except BlockingIOError:
            self.pending.append(data)
        except OSError:
            self.front_alive = False

    def _flush(self) -> None:
        out = self.controller.outbox
        if out:
            for msg in out:
                self._send(msg)
            out.clear()
        while self.pending and self.front_alive:
            try:
                self.chan.send(self.pending[0], socket.MSG_DONTWAIT)
                self.pending.popleft()
            except BlockingIOError:
                break
            except OSError:
                self.front_alive = False

    def _receive(self) -> None:
        # nothing sent since the pair was last emptied: no receive (a system call and an exception
        # in every cycle), but one at least every RECEIVE_AT_LEAST_S, so the front's loss is seen
        posted = int(self._posted[0])
        if posted == self._drained and posted >= 0 and self._quiet < self._quiet_max:
            self._quiet += 1
            return
        self._quiet = 0
        for _ in range(MAX_REQUESTS_PER_CYCLE):
            try:
                data = self.chan.recv(MAX_MESSAGE, socket.MSG_DONTWAIT)
            except BlockingIOError:
                # empty: every send the count said done before the receive began was taken (the
                # front counts before its send and after it); an odd count is a send under way,
                # perhaps not on the pair yet: the next cycle receives again
                self._drained = posted - (posted & 1)
                return
            except OSError:
                self.front_alive = False
                return
            if not data:  # EOF: the front process is gone
                self.front_alive = False
                return
            try:
                msg = _decode(data)
            except (msgspec.DecodeError, ValueError):
                continue  # cannot happen with the front's size limit; never a reason to fault
            if msg.get("cmd") == "_shutdown":
                self.running = False
                return
            if msg.get("cmd") == "_torque_off":  # the front's second signal: no park, or cut it short
                self.abort_park = True
                self.running = False
                return
            if self._park_deadline is not None and msg.get("cmd") not in _STOPS:
                if msg.get("cmd") != "_client_lost":  # a client leaving must not cut the park short
                    self.controller.outbox.append({"id": msg.get("id"), "ok": False, "error": {
                        "code": "invalid_state",
                        "message": f"{self.profile.name}: shutting down (parking); only disable, pause or hold"}})
                continue
            self.controller.handle(msg)

    # ---------------------------------------------------------------- snapshot
    def _publish(self) -> None:
        c, fb = self.controller, self.controller.feedback
        mst, st, hp, hv, hf, gst, ghp, ghv, ghf = self._pub
        self.snap.begin()
        # a missed read leaves the last sample, honestly stamped; it turns invalid only with a bus fault
        mst[0] = fb.stamp if c.measured_valid else 0.0
        self._measured[:] = c.measured_block  # measured p, v, f
        block = self._motion_block
        for k, m, cols in self._ns_blocks:
            block[:, cols] = m.block  # setpoint p, v, f and goal p, v, f of its joints
            has_p, has_v, has_f = m.setpoint_fields()
            st[k] = m.setpoint_stamp if (has_p or has_v or has_f) else 0.0
            hp[k] = has_p
            hv[k] = has_v
            hf[k] = has_f
            has_p, has_v, has_f = m.goal_fields()
            gst[k] = m.goal_stamp if (has_p or has_v or has_f) else 0.0
            ghp[k] = has_p
            ghv[k] = has_v
            ghf[k] = has_f
        if self._native_rows:
            self._publish_native()
        self.snap.end()

    def _publish_native(self) -> None:
        c, fb = self.controller, self.controller.feedback
        cst, cp, cq, cf, sst, sp, sq, tst, tw, tfr, gst, gp, gq = self._native_pub
        fc = fb.cartesian
        for k, row, nc in self._native_rows:  # measured_cp straight from a native cartesian backend
            cst[k] = fc.stamp if c.measured_valid else 0.0
            cp[3 * k:3 * k + 3] = fc.position[row]
            cq[4 * k:4 * k + 4] = fc.orientation[row]
            if fc.wrench is not None:
                cf[6 * k:6 * k + 6] = fc.wrench[row]
            sst[k] = nc.setpoint_stamp  # what it was commanded
            sp[3 * k:3 * k + 3] = nc.position
            sq[4 * k:4 * k + 4] = nc.orientation
            tst[k] = nc.twist_stamp
            tw[6 * k:6 * k + 6] = nc.twist
            tfr[k] = nc.frame
            gst[k] = nc.goal_stamp
            gp[3 * k:3 * k + 3] = nc.goal_position
            gq[4 * k:4 * k + 4] = nc.goal_orientation

    # ---------------------------------------------------------------- the loop
    def run(self, ready: dict | None = None) -> int:
        """Run until shutdown or loss of the front process. Returns the exit status.

        ``ready`` is sent to the front process once the first sample is published, so nobody is
        served an all-zero snapshot."""
        c = self.controller
        problems = request_realtime(self.profile.loop.realtime_priority, self.profile.loop.cpu) if self.realtime else ["disabled by --no-realtime"]
        if problems:
            c.event("warning", "realtime_unavailable",
                    f"{self.profile.name}: running without full real-time guarantees: " + "; ".join(problems))
        # prime the measured state before anyone can enable: one cycle, before any request
        runner = self.runner
        runner.cycle(c)
        c.push_state()
        self._publish()
        samples = self.samples
        # the cycle's stamp in the ring: the steady epoch clock of the cycle's start
        epoch = time.time() - time.perf_counter()
        state = self.snap.data[:samples.state] if samples is not None else None
        if samples is not None:
            samples.push(0, epoch + time.perf_counter(), state)
        if ready is not None:
            c.outbox.append(ready)
        self._flush()
        gc.collect()
        gc.freeze()

        v = self._v
        cycles = v["cycles"]
        overruns = v["overruns"]
        ring_index = v["ring_index"]
        lateness = v["lateness"]
        compute = v["compute"]
        clock = time.perf_counter
        receive = self._receive
        runner.restart()
        i = 0
        while (self.running and self.front_alive) or self._parking():
            runner.wait()  # the device's clock (its packet) or the loop's (then the backend's start: a SYNC)
            t0 = runner.t0
            # -- the cycle --
            try:
                runner.work(c, receive)  # read -> requests -> step (transition, motion) -> write
            except Exception as exc:  # a bug must fault the robot, not kill the loop
                c.enter_fault(Fault("internal", f"{self.profile.name}: control loop error: {exc!r}",
                                    transient=False))
            # stats go in before the snapshot is published, so the same seqlock covers them
            i += 1
            slot = i % RING
            lateness[slot] = runner.late
            compute[slot] = clock() - t0
            cycles[0] = i
            ring_index[0] = slot
            self._publish()
            if samples is not None:  # a copy into pre-allocated shared memory, never blocks
                samples.push(i, epoch + t0, state)
            self._flush()
            # -- the next cycle's start; after an overrun, skip ahead instead of bursting --
            runner.schedule()
            overruns[0] = runner.overruns
        self.shutdown()
        return 0

    def _parking(self) -> bool:
        """Called once the loop was asked to end: start the shutdown park, or say whether the one
        running goes on (True: run another cycle). Its start and end are status / warning events."""
        c = self.controller
        sd = self.profile.shutdown
        name = self.profile.name
        now = time.perf_counter()
        if self._park_deadline is None:
            active = c.state in (OperatingState.ENABLED, OperatingState.PAUSED)
            if sd.action != "park" or self.abort_park or not active or not c.park():
                if active:
                    c.event("status", "shutdown_torque_off", f"{name}: shutting down: torque off "
                            f"(shutdown.action: {sd.action})")
                return False
            self._park_t0 = now
            self._park_deadline = now + sd.timeout_s
            c.event("status", "shutdown_park", f"{name}: shutting down: parking at the rest pose "
                    f"(shutdown.action: park, within {sd.timeout_s:g} s), then torque off")
            return True
        took = now - self._park_t0
        if c.state not in (OperatingState.ENABLED, OperatingState.PAUSED):
            c.event("warning", "shutdown_park_aborted", f"{name}: park ended by {c.state.value} after {took:.2f} s; "
                    "torque off")
        elif self.abort_park:
            c.event("warning", "shutdown_park_aborted", f"{name}: park cut short by a second signal after "
                    f"{took:.2f} s; torque off")
        elif now > self._park_deadline:
            c.event("warning", "shutdown_park_timeout", f"{name}: the rest pose was not reached within "
                    f"shutdown.timeout_s = {sd.timeout_s:g} s; torque off")
        elif c.in_motion():
            return True
        elif c.at_rest_pose():
            c.event("status", "shutdown_parked", f"{name}: parked at the rest pose in {took:.2f} s; torque off")
        else:
            c.event("warning", "shutdown_park_aborted", f"{name}: park stopped short of the rest pose after "
                    f"{took:.2f} s (a stop command); torque off")
        return False

    def request_stop(self) -> None:
        """SIGTERM / SIGINT to this process: end the loop; a second one: torque off now.

        Counts this process's own signals, not ``running``: a terminal's Ctrl-C (or systemd's
        control-group kill) reaches the front process too, whose ``_shutdown`` may be read first,
        and must not count as the second signal. A second signal sent to the front process alone
        arrives as its ``_torque_off``."""
        self._signals += 1
        if self._signals > 1:
            self.abort_park = True
        self.running = False

    def shutdown(self) -> None:
        """Stop motion and switch torque off: DISABLED, or FAULT with an error event when a joint
        did not confirm torque off. Never raises."""
        try:
            self.controller.abort_transition()
        except Exception:
            pass
        try:
            self.actuator.disable()
        except Exception as exc:  # never claimed DISABLED: clients hear which joint, state FAULT
            self.controller.torque_off_failed(exc)
        else:
            self.controller.torque_switched_off()
        self.actuator.close()
        # close() could not switch a bus's torque off (a composite's bus whose worker was stuck in
        # a call on it keeps the bus: no second thread on it): said, never DISABLED
        said = self.actuator.take_status()
        if said is not None and said[1] is not None and said[1].code == "torque_off_unconfirmed":
            self.controller.torque_off_failed(CrtkBridgeError(said[1].message))
        self._publish()
        self._flush()


def control_main(profile: Profile, make_actuator: Callable[[], Actuator], chan: socket.socket,
                 snapshot: SnapshotBuffer, realtime: bool = True, samples: SampleRing | None = None) -> int:
    """Entry point of the control process (forked by the daemon). Returns its exit status.

    Opens and configures the backend (lifecycle path, may block), tells the front process it is
    ready (or why not), then runs the loop.
    """
    signals = {"count": 0}  # SIGTERM / SIGINT received, the loop's or not
    loop_ref: dict[str, Any] = {}

    def on_signal(signum: int, frame: Any) -> None:
        signals["count"] += 1
        if "loop" in loop_ref:
            loop_ref["loop"].request_stop()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)

    try:
        actuator = make_actuator()  # the entry layer's choice of backend
        actuator.open()
        actuator.configure()
    except CrtkBridgeError as exc:
        chan.send(_encode({"event": "_startup_failed", "data": {"message": str(exc)}}))
        return 1
    except Exception as exc:
        chan.send(_encode({"event": "_startup_failed", "data": {"message": f"{profile.name}: {exc!r}"}}))
        return 1
    traits = actuator.traits
    caps = traits.capabilities
    loop = ControlLoop(profile, actuator, chan, snapshot, realtime=realtime, samples=samples)
    loop_ref["loop"] = loop
    c = loop.controller

    def as_dict(cap: Any) -> dict:
        return {k: getattr(cap, k) for k in cap.__dataclass_fields__}

    ready = {"event": "_ready", "data": {
        "commands": c.supported_commands(),  # what some namespace offers
        "capabilities": as_dict(caps),
        "period_s": loop.period,  # the ONE effective period: the front's rates and statistics
        # the longest a state command may take before the loop itself replies (its time limit)
        "transition_timeout_s": 2 * max(traits.timeout_s(k) for k in Lifecycle
                                        if k is not Lifecycle.HOME or traits.native_homing),
        "namespace_commands": c.namespace_commands(),  # motion commands per namespace
        "namespace_capabilities": {ns: as_dict(cap) for ns, cap in c.ns_caps.items()},
        "native_cartesian": list(c.native_cartesian),  # namespaces whose backend does cartesian control
        "lerobot_maps": actuator.lerobot_maps(),  # per joint: LeRobot's numbers of its SI value (list)
    }}
    for _ in range(signals["count"] - loop._signals):  # those that came before the loop existed
        loop.request_stop()
    try:
        return loop.run(ready)
    except Exception:
        loop.shutdown()
        raise
