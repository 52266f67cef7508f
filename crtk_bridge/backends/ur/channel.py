"""What passes between the UR backend (in the control process) and its ur_rtde worker process
(:mod:`.worker`), and the backend's handle on one worker (:class:`WorkerHandle`).

Why a process of its own: ur_rtde 1.6.5 corrupts its heap when a link drops while it is called
(each interface handles the loss on its own thread), and its constructors hold the GIL. In a
worker, an abort ends the worker only: the backend sees it die in the cycle that notices and
faults, naming the signal; a link loss ends the worker (no reconnect in place, so no leaked
sockets), and a fresh one is started once the controller answers again.

Two channels, chosen for latency and for "the newest wins":

* **State: shared memory under a seqlock** (a ``memfd`` both map; one writer, the worker). The
  worker writes each RTDE data package there as it arrives and then sends a one-byte wake-up on
  the socket, so the backend's ``wait_cycle`` blocks in ``poll()`` (no spinning) and reads the
  NEWEST package, whatever it missed: a socket queue of full states would hand a backend that
  stalled (a long GC, a test that stops cycling) a backlog of old packages, the newest dropped
  once the queue is full. Wake-ups that find the queue full are dropped: they carry no data.
* **Everything else: one ``SOCK_SEQPACKET`` Unix socketpair**: reliable, ordered, one message per
  send (no framing, no partial reads), and it closes when either process dies (the other sees
  end of file at once). Per-cycle commands are a fixed :data:`COMMAND` struct (packed in about a
  microsecond, no object tree); lifecycle requests and their replies, a few per transition, are
  msgspec msgpack. The backend sends with ``MSG_DONTWAIT``: a worker that stops taking commands
  fills the send buffer (the default 208 KB: ~270 commands, 0.55 s at 500 Hz, of the order of
  the --sim link timeout, so a loaded PC's scheduling hiccup is not a fault) and the next command
  is DROPPED and the robot FAULTs (``worker_stalled``); the cycle never blocks. A worker that
  also stops forwarding packages faults first, at ``link_timeout_s``. The worker acts only on the newest realtime
  command of what it finds queued (a late servoJ target is never replayed after a newer one).
  An unchanged realtime command (a hold) is sent again only every keep-alive period (20 ms;
  :meth:`WorkerHandle.command`): the script repeats it by itself; its RTDE watchdog, fed by what
  the worker forwards, stops the arm within its period when the worker stops forwarding
  (a stalled worker then fills the buffer in ~5 s of a hold, not 0.55 s).

Messages on the socket, first byte the kind:

| kind | from | payload |
|---|---|---|
| ``H`` hello | worker | msgpack ``error`` (None: the receive interface and the dashboard are up) |
| ``S`` wake-up | worker | none: a new package is in shared memory |
| ``R`` reply | worker | msgpack ``[id, error, result]`` of request ``id`` (error None: done) |
| ``F`` refused | worker | msgpack ``[op, error]``: a realtime command returned False or raised |
| ``C`` command | backend | :data:`COMMAND`: op, six values, then acceleration, time, lookahead, gain |
| ``Q`` request | backend | msgpack ``[id, name, args]``, one of :data:`REQUESTS` |
| ``P`` priority | backend | msgpack int: SCHED_FIFO priority for the worker's cycle threads |

Exit statuses of the worker (anything else, or a signal, is a death): :data:`EXIT_OPEN_FAILED`,
:data:`EXIT_LINK_LOST`, :data:`EXIT_CONTROL_LINK_LOST`, 0 when the backend closed its end.
"""

from __future__ import annotations

import math
import mmap
import os
import select
import signal
import socket
import struct
import subprocess
import time
from typing import Any

import msgspec
import numpy as np

from ...spawn import module_argv, module_env

#: the RTDE outputs read every package (a small recipe: ur_rtde's default asks for ~58)
VARIABLES = ["timestamp", "actual_q", "actual_qd", "actual_TCP_pose", "actual_TCP_force", "robot_mode",
             "safety_mode", "runtime_state", "target_speed_fraction", "robot_status_bits",
             "safety_status_bits"]

#: shared state: seq (uint64) | timestamp, q[6], qd[6], tcp pose[6], tcp force[6], robot mode,
#: safety mode, runtime state, speed fraction, flags (:data:`CTL_UP` ...), packages forwarded
SEQ = struct.Struct("<Q")
STATE = struct.Struct("<d6d6d6d6diiidIQ")
STATE_BYTES = SEQ.size + STATE.size
CTL_UP, CTL_CONNECTED, CTL_RUNNING = 1, 2, 4  # the control interface exists / its link is up / script plays

#: a realtime command: kind b"C", op, six values, acceleration, time, lookahead time, gain
COMMAND = struct.Struct("<cB6d4d")
SERVOJ, SPEEDJ, SERVOL, SPEEDL, KICK = 1, 2, 3, 4, 5
OP_NAMES = {SERVOJ: "servoJ", SPEEDJ: "speedJ", SERVOL: "servoL", SPEEDL: "speedL", KICK: "kickWatchdog"}

#: the lifecycle requests the worker runs (each on a thread of its own), by name
REQUESTS = ("powerOn", "brakeRelease", "powerOff", "unlockProtectiveStop", "closeSafetyPopup", "restartSafety",
            "play", "dashboard_connect", "start_script", "stop_script", "setWatchdog", "teachMode", "endTeachMode",
            "isPoseWithinSafetyLimits", "joints_within")

EXIT_OPEN_FAILED, EXIT_LINK_LOST, EXIT_CONTROL_LINK_LOST = 2, 3, 4
HELLO_TIMEOUT_S = 10.0  # interpreter start, imports, RTDE and dashboard connections
_RECV_BYTES = 65536
_KIND_COMMAND = b"C"[0]


def encode(kind: bytes, obj: Any) -> bytes:
    return kind + msgspec.msgpack.encode(obj)


def decode(data: bytes | memoryview) -> Any:
    return msgspec.msgpack.decode(data)


def exit_cause(returncode: int) -> tuple[str, str]:
    """(fault code, what happened) for a worker that ended with ``returncode`` (Popen's: -N for
    signal N)."""
    if returncode in (EXIT_LINK_LOST, EXIT_CONTROL_LINK_LOST):
        return "link_lost", "RTDE link lost" if returncode == EXIT_LINK_LOST else "RTDE control link lost"
    if returncode < 0:
        try:
            name = signal.Signals(-returncode).name
        except ValueError:
            name = f"signal {-returncode}"
        return "worker_died", f"ur_rtde worker died ({name})"
    return "worker_died", f"ur_rtde worker exited with status {returncode}"


class WorkerHandle:
    """One worker process seen from the backend: its Popen, its end of the socket, the shared
    state. :meth:`start` spawns it (``python -m crtk_bridge.backends.ur.worker``: exec'd, never a
    fork of the control process); :meth:`hello` waits until it connected. Real-time methods
    (:meth:`pump`, :meth:`command`, :meth:`read_state`) never block.
    """

    def __init__(self, host: str, rate_hz: float, rt_priority: int = 0):
        self.host, self.rate_hz = host, rate_hz
        self.proc: subprocess.Popen | None = None
        self.sock: socket.socket | None = None
        self.mem: mmap.mmap | None = None
        self.poller = select.poll()
        self.rt_priority = rt_priority
        self.ready = False  # hello received without error
        self.dead = False  # its socket closed (it exited, or is exiting)
        self.wakeups = 0  # wake-ups seen (a new package each)
        self.replies: dict[int, tuple[str | None, Any]] = {}
        self.refused: tuple[int, str | None] | None = None  # the last refused realtime command
        self._next_id = 0
        self._buf = bytearray(_RECV_BYTES)
        self._view = memoryview(self._buf)
        self._cmd = bytearray(COMMAND.size)
        self._sent = bytearray(COMMAND.size)  # the last realtime command sent, and when (command)
        self._sent_at = -math.inf
        self.clock = time.perf_counter  # (a test's fake clock)
        self._seq_last = 0  # the seqlock's count at the last read, and what it read
        self._state: tuple | None = None

    # ---------------------------------------------------------------- lifecycle (blocking)
    def start(self) -> None:
        """Spawn the worker. Blocks for the fork/exec only (milliseconds)."""
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        fd = os.memfd_create("crtk-ur-state", os.MFD_CLOEXEC)
        try:
            os.ftruncate(fd, STATE_BYTES)
            self.mem = mmap.mmap(fd, STATE_BYTES)
            # this package's worker, whatever the current folder holds (spawn.py)
            self.proc = subprocess.Popen(
                module_argv("crtk_bridge.backends.ur.worker", "--sock", str(theirs.fileno()),
                            "--state", str(fd), "--host", self.host, "--rate", repr(self.rate_hz),
                            "--parent", str(os.getpid()), "--rt-priority", str(self.rt_priority)),
                pass_fds=(theirs.fileno(), fd), stdin=subprocess.DEVNULL, env=module_env(), close_fds=True)
        finally:
            theirs.close()  # the worker's end lives in the worker only: its death closes the socket
            os.close(fd)
        ours.setblocking(False)
        self.sock = ours
        self.poller.register(ours.fileno(), select.POLLIN)

    def hello(self, timeout_s: float = HELLO_TIMEOUT_S) -> str | None:
        """Wait for the worker's hello. Blocks. None: it is up; else why not (it then exits)."""
        deadline = time.monotonic() + timeout_s
        while True:
            for kind, body in self._messages():
                if kind == b"H":
                    error = decode(body)
                    self.ready = error is None
                    return error
            if self.dead:
                return self.cause()[1]
            left = deadline - time.monotonic()
            if left <= 0:
                return f"no answer from the ur_rtde worker within {timeout_s:g} s"
            self.poller.poll(math.ceil(left * 1000))

    def close(self, timeout_s: float = 2.0) -> None:
        """End the worker: its socket closed (it exits at once, never running ur_rtde's
        destructors), else killed; reaped. Blocks up to ``timeout_s``. Idempotent."""
        if self.sock is not None:
            try:
                self.poller.unregister(self.sock.fileno())
            except (KeyError, ValueError):
                pass
            self.sock.close()
            self.sock = None
        self.dead = True
        p = self.proc
        if p is not None and p.poll() is None:
            try:
                p.wait(timeout_s)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        if self.mem is not None:
            self.mem.close()
            self.mem = None

    def kill(self) -> None:
        """SIGKILL the worker (it stops talking to the controller at once); reaped by :meth:`close`."""
        p = self.proc
        if p is not None and p.poll() is None:
            try:
                p.kill()
            except ProcessLookupError:
                pass

    def cause(self) -> tuple[str, str]:
        """(fault code, text) of a dead worker: its exit status or signal, waited for up to 5 ms
        (its socket closes just before the kernel records the exit)."""
        p = self.proc
        rc = p.poll() if p is not None else None
        end = time.monotonic() + 0.005
        while rc is None and time.monotonic() < end:
            time.sleep(0.0002)
            rc = p.poll()
        if rc is None:
            return "worker_died", "ur_rtde worker closed its channel"
        return exit_cause(rc)

    # ---------------------------------------------------------------- real-time path
    def _messages(self):
        """Every message waiting on the socket, (kind, body). Never blocks. Sets ``dead`` at end
        of file (the worker exited)."""
        sock = self.sock
        if sock is None:
            self.dead = True
            return
        while True:
            try:
                n = sock.recv_into(self._buf)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                n = 0
            if n == 0:
                self.dead = True
                return
            yield bytes(self._view[:1]), self._view[1:n]

    def pump(self) -> bool:
        """Take every message waiting. Never blocks. True: a wake-up came (a new package)."""
        woke = False
        for kind, body in self._messages():
            woke = self._note(kind, body) or woke
        return woke

    def pump_one(self) -> bool:
        """Take ONE message (the one :meth:`wait` woke on). Never blocks. True: a wake-up.

        The loop's wait takes one message per wake-up and no more: the receive that would find
        the socket empty (EAGAIN) is a system call of ~10 us per cycle for nothing (bench_cpu.py);
        a message left queued wakes the next :meth:`wait` at once, which takes it then."""
        sock = self.sock
        if sock is None:
            self.dead = True
            return False
        try:
            n = sock.recv_into(self._buf)
        except (BlockingIOError, InterruptedError):
            return False
        except OSError:
            n = 0
        if n == 0:
            self.dead = True
            return False
        view = self._view
        return self._note(bytes(view[:1]), view[1:n])

    def _note(self, kind: bytes, body: memoryview) -> bool:
        if kind == b"S":
            self.wakeups += 1
            return True
        if kind == b"R":
            rid, error, result = decode(body)
            self.replies[rid] = (error, result)
        elif kind == b"F":
            op, error = decode(body)
            self.refused = (op, error)
        return False

    def wait(self, timeout_s: float) -> None:
        """Block in poll() until a message (or end of file) comes, at most ``timeout_s``."""
        if self.sock is not None and timeout_s > 0:
            self.poller.poll(math.ceil(timeout_s * 1000))

    def fresh(self) -> bool:
        """The shared state changed since :meth:`read_state` last read it (no system call)."""
        mem = self.mem
        return mem is not None and SEQ.unpack_from(mem, 0)[0] != self._seq_last

    def read_state(self) -> tuple | None:
        """The newest package (STATE's fields), None before the first. Never blocks: retries a
        torn read (the worker writing meanwhile) a few times."""
        mem = self.mem
        if mem is None:
            return None
        for _ in range(100):
            s1 = SEQ.unpack_from(mem, 0)[0]
            if s1 & 1:
                continue
            if s1 == self._seq_last:
                return self._state  # nothing new since the last read: no unpacking
            fields = STATE.unpack_from(mem, SEQ.size)
            if SEQ.unpack_from(mem, 0)[0] == s1:
                if not s1:
                    return None
                self._seq_last, self._state = s1, fields
                return fields
        return None

    def command(self, op: int, values, a: float = 0.0, t: float = 0.0, lookahead: float = 0.0,
                gain: float = 0.0, repeat_s: float = 0.0) -> bool:
        """Send one realtime command. Never blocks: False when the socket is full (the worker is
        not taking commands) or closed; the command was dropped.

        ``repeat_s`` > 0: a command the same as the last one sent (op, values and parameters, bit
        for bit), sent less than ``repeat_s`` ago with nothing else sent since, is not sent
        again (True: the worker has it). ur_rtde's control script repeats its realtime command
        by itself (its servo thread servoes to the last ``servo_target`` every controller tick,
        its speed thread holds the last speed) until another command comes, so an unchanged
        command (a hold: the same servoJ target every cycle) does nothing new on the arm; sent
        every cycle it cost a send here, a wake-up of the worker, ur_rtde's RTDE package and the
        controller's receive, 500 times a second (bench_cpu.py, ENABLED idle). It still goes out
        every ``repeat_s`` (the caller keeps that under the script's RTDE watchdog period), and
        at once after any other message (a request may run a command on the script)."""
        if isinstance(values, np.ndarray):
            values = values.tolist()  # Python floats: unpacking an array yields numpy scalars, slowly
        cmd = self._cmd
        COMMAND.pack_into(cmd, 0, b"C", op, *values, a, t, lookahead, gain)
        now = self.clock()
        if repeat_s > 0.0 and now - self._sent_at < repeat_s and cmd == self._sent:
            return True
        if not self.send(cmd):
            return False
        self._sent[:] = cmd
        self._sent_at = now
        return True

    def request(self, name: str, *args: Any) -> int | None:
        """Send lifecycle request ``name`` (one of :data:`REQUESTS`); its reply lands in
        :attr:`replies` under the returned id. Never blocks: None when it could not be sent."""
        self._next_id += 1
        rid = self._next_id
        if self.send(encode(b"Q", [rid, name, list(args)])):
            return rid
        return None

    def send(self, data: bytes | bytearray) -> bool:
        """One message to the worker. Never blocks: False when the socket is full or closed."""
        sock = self.sock
        if sock is None:
            return False
        if data[0] != _KIND_COMMAND:
            self._sent_at = -math.inf  # the next realtime command goes out, whatever it repeats
        try:
            sock.send(data, socket.MSG_DONTWAIT)
        except (BlockingIOError, InterruptedError):
            return False
        except OSError:
            self.dead = True
            return False
        return True
