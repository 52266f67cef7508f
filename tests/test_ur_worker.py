"""The ur_rtde worker's own logic (crtk_bridge/backends/ur/worker.py), on stand-in ur_rtde objects:
no controller, no simulator, no ur_rtde in this process."""

from __future__ import annotations

import sys
import types

from crtk_bridge.backends.ur.worker import Worker


class _Recorder:
    """A stand-in RTDEControlInterface recording the calls made on it."""

    def __init__(self, log: list, connected: bool = True, running: bool = False):
        self.log, self.connected, self.running = log, connected, running

    def isConnected(self):  # noqa: N802 - ur_rtde's names
        return self.connected

    def isProgramRunning(self):  # noqa: N802
        return self.running

    def __getattr__(self, attr):
        def call(*args):
            self.log.append(attr)
            return not (attr.endswith("Stop") and not self.running)  # ur_rtde: refused while stopped
        return call


def test_a_stopped_script_is_uploaded_again_only_after_its_command_register_is_cleared(monkeypatch):
    """A stop that ends the control script (protective stop, e-stop, violation, its watchdog)
    leaves the command it ran in input_int_register_0, and a re-uploaded script plays the
    register first: a speedJ running at the stop started again on enable, until the first hold
    (simulated UR5e, speedJ at 0.3 rad/s when a protective stop came: the arm at 0.016-0.08 rad/s,
    up to 0.34 mrad, in 10 of 10 enables measured before; still in all 13 after). With the
    program stopped, a command makes ur_rtde clear the register instead: enable sends one before
    reuploadScript, never after."""
    monkeypatch.setitem(sys.modules, "rtde_control", types.ModuleType("rtde_control"))  # not ur_rtde's
    log: list[str] = []
    w = Worker(None, None, "127.0.0.1", 500.0, 0)
    w.ctl = _Recorder(log)
    w.start_script()
    assert log == ["speedStop", "reuploadScript"], log
    # a script that runs is left alone: no stop, no upload
    log.clear()
    w.ctl = _Recorder(log, running=True)
    w.start_script()
    assert log == []


def test_the_reader_exits_quietly_when_the_backend_resets_the_link(tmp_path):
    """The backend closing its end with the worker's replies unread resets the socket
    (ECONNRESET, not an end of file): the worker's reader ends the worker as for an end of file,
    with no traceback (it printed one when a daemon stopped)."""
    import subprocess
    import textwrap

    script = textwrap.dedent("""
        import socket, types
        from crtk_bridge.backends.ur.worker import Worker
        worker_end, backend_end = socket.socketpair()
        worker_end.sendall(b"a reply the backend never reads")
        backend_end.close()  # unread data: the worker's next recv is reset
        Worker.read_loop(types.SimpleNamespace(sock=worker_end))
        raise SystemExit(3)  # read_loop returned: it must end the process itself
    """)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0 and "Traceback" not in done.stderr, done.stderr


def test_the_loops_wait_takes_one_message_per_wake_up_and_loses_none():
    """The control loop's wait on the worker (UrBackend.wait_cycle) receives the one message
    poll() woke on, then reads the package from shared memory: no second receive that finds the
    socket empty (a system call per cycle, ~10 us of the 500 Hz loop). A message that came with
    the wake-up (a request's reply) is not lost: it wakes the next wait at once, which takes it."""
    import mmap
    import os
    import socket
    from pathlib import Path

    from crtk_bridge.backends.ur.backend import UrBackend
    from crtk_bridge.backends.ur.channel import SEQ, STATE, STATE_BYTES, WorkerHandle, encode
    from crtk_bridge.profile import load_profile

    root = Path(__file__).resolve().parent.parent
    backend = UrBackend(UrBackend.sim_profile(load_profile(root / "profiles" / "ur5e.yaml"), "127.0.0.9"))
    ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    fd = os.memfd_create("test-ur-state")
    os.ftruncate(fd, STATE_BYTES)
    mem = mmap.mmap(fd, STATE_BYTES)
    os.close(fd)
    w = WorkerHandle("127.0.0.9", 500.0)
    ours.setblocking(False)
    w.sock, w.mem = ours, mem
    w.poller.register(ours.fileno(), 1)  # POLLIN
    receives = []

    class Counting:  # the socket, counting its receives
        def __getattr__(self, name):
            return getattr(ours, name)

        def recv_into(self, *args):
            receives.append(1)
            return ours.recv_into(*args)

    w.sock = Counting()
    backend._w, backend._link, backend._rt_checked = w, True, True
    seq = 0

    def package(ts: float) -> None:  # as the worker: the package in shared memory, then a wake-up
        nonlocal seq
        STATE.pack_into(mem, SEQ.size, ts, *[0.1] * 24, 7, 1, 1, 1.0, 7, 1)
        seq += 2
        SEQ.pack_into(mem, 0, seq)
        theirs.send(b"S")

    try:
        import threading
        import time
        package(1.0)
        assert backend.wait_cycle(time.perf_counter())
        assert backend._ts == 1.0
        # the usual cycle: the loop waits in poll() before the package comes
        waiting = threading.Event()
        poll = w.wait
        w.wait = lambda timeout_s: (waiting.set(), poll(timeout_s))

        def worker() -> None:
            waiting.wait(10)
            package(1.002)
            theirs.send(encode(b"R", [5, None, "done"]))  # a reply right behind the wake-up

        t = threading.Thread(target=worker)
        t.start()
        receives.clear()
        assert backend.wait_cycle(time.perf_counter() + 5.0)
        t.join()
        assert backend._ts == 1.002
        assert len(receives) <= 1, f"{len(receives)} receives for one wake-up"
        assert 5 not in w.replies  # still queued: the next wait takes it
        package(1.004)
        assert backend.wait_cycle(time.perf_counter())
        assert backend._ts == 1.004 and w.replies[5] == (None, "done")
    finally:
        backend._w = None
        ours.close()
        theirs.close()
        mem.close()


def test_an_unchanged_realtime_command_is_sent_again_only_every_keep_alive_period():
    """ur_rtde's control script repeats its realtime command by itself (its servo thread servoes
    to the last target every tick), so a hold (the same servoJ every cycle) is not sent to the
    worker every cycle (a send, the worker's wake-up, an RTDE package and the controller's
    receive, 500 times a second): the same command goes out again only every keep-alive period
    (the script's RTDE watchdog stays fed); a changed one, another op, or the first after any
    other message (a request may run a command on the script) goes out at once."""
    import socket

    from crtk_bridge.backends.ur.channel import COMMAND, KICK, SERVOJ, SPEEDJ, WorkerHandle

    ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    theirs.setblocking(False)
    w = WorkerHandle("127.0.0.9", 500.0)
    ours.setblocking(False)
    w.sock = ours
    now = [100.0]
    w.clock = lambda: now[0]

    def received() -> list:
        out = []
        while True:
            try:
                data = theirs.recv(4096)
            except BlockingIOError:
                return out
            out.append(COMMAND.unpack(data)[1:8] if data[:1] == b"C" else data[:1])

    try:
        q = [0.1, -1.5, 1.5, -1.5, -1.5, 0.2]
        for _ in range(5):  # a hold: five cycles, 2 ms apart
            assert w.command(SERVOJ, q, 0.0, 0.002, 0.05, 600.0, repeat_s=0.02)
            now[0] += 0.002
        assert received() == [(SERVOJ, *q)]
        now[0] += 0.011  # 21 ms after the first: sent again (the script's watchdog is fed)
        assert w.command(SERVOJ, q, 0.0, 0.002, 0.05, 600.0, repeat_s=0.02)
        assert received() == [(SERVOJ, *q)]
        moved = [*q[:5], 0.2001]  # a changed target: at once
        assert w.command(SERVOJ, moved, 0.0, 0.002, 0.05, 600.0, repeat_s=0.02)
        assert w.command(SPEEDJ, [0.0] * 6, 1.0, 0.0, repeat_s=0.02)  # another op: at once
        assert w.command(SERVOJ, moved, 0.0, 0.002, 0.05, 600.0, repeat_s=0.02)  # and back
        assert received() == [(SERVOJ, *moved), (SPEEDJ, *[0.0] * 6), (SERVOJ, *moved)]
        assert w.request("isJointsWithinSafetyLimits", moved) is not None  # a request on the script
        assert w.command(SERVOJ, moved, 0.0, 0.002, 0.05, 600.0, repeat_s=0.02)
        assert [m if m == b"Q" else m[0] for m in received()] == [b"Q", SERVOJ]
        assert w.command(KICK, [0.0] * 6) and w.command(KICK, [0.0] * 6)  # repeat_s 0: every time
        assert [m[0] for m in received()] == [KICK, KICK]
    finally:
        ours.close()
        theirs.close()


def test_the_keep_alive_period_stays_under_the_scripts_watchdog_period():
    """The keep-alive (an unchanged command repeated, or a kick when none went out) is a fifth of
    the watchdog's period, at most 20 ms: a fast watchdog is fed often enough."""
    from pathlib import Path

    import msgspec

    from crtk_bridge.backends.ur.backend import UrBackend
    from crtk_bridge.profile import load_profile

    profile = load_profile(Path(__file__).resolve().parent.parent / "profiles" / "ur5e.yaml")
    for hz, keepalive in ((10.0, 0.02), (2.0, 0.02), (50.0, 0.004), (500.0, 0.0004)):
        backend = dict(profile.backend, host="127.0.0.9", watchdog_hz=hz)
        b = UrBackend(msgspec.structs.replace(profile, backend=backend))
        assert abs(b._keepalive_s - keepalive) < 1e-12, (hz, b._keepalive_s)
