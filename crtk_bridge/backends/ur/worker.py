"""The ur_rtde worker: the one process that holds ur_rtde objects for a UR backend.

Started by the backend (``python -m crtk_bridge.backends.ur.worker --sock FD --state FD --host H
--rate HZ --parent PID``; see :mod:`.channel` for what passes on the socket and in the shared
state). It talks to the UR controller only, and only on the backend's behalf:

* its main thread waits for each RTDE data package (``RTDEReceiveInterface``, polled as the backend
  once did: sleep until shortly before the package is due, then every 0.1 ms), writes it to the
  shared state and sends a wake-up: the robot paces the daemon's loop through it;
* its reader thread carries out the backend's realtime commands (``servoJ`` / ``speedJ`` /
  ``servoL`` / ``speedL`` / ``kickWatchdog``) as they come, the newest of a queued run only, and
  starts each lifecycle request (dashboard calls, the control script's upload, goal checks) on a
  thread of its own that replies when done.

It never moves the arm by itself: it sends a command only when the backend's message asks, and
never repeats one; the control script's RTDE watchdog, fed only by those commands, stops the arm
when the backend stops sending. It ends (``os._exit``, never ur_rtde's destructors, which throw
on a broken link) when:

* the receive link drops or falls silent for good (exit 3), or the control interface's link drops
  (exit 4): ur_rtde is never asked to reconnect in place (its own threads race our calls there:
  heap corruption), the backend starts a fresh worker once the controller answers;
* the backend's end of the socket closes (the backend closed, or its process died: the kernel
  closes the socket with it), seen at once by the reader thread; and, as a second line, its
  parent is no longer the process that started it (checked every package). (Not
  ``PR_SET_PDEATHSIG``: it fires when the THREAD that forked exits, and respawns after a link
  loss come from a short-lived thread.)
"""

from __future__ import annotations

import argparse
import mmap
import os
import re
import socket
import sys
import threading
import time
from typing import Any, Callable

from .channel import (COMMAND, CTL_CONNECTED, CTL_RUNNING, CTL_UP, EXIT_CONTROL_LINK_LOST, EXIT_LINK_LOST,
                      EXIT_OPEN_FAILED, KICK, REQUESTS, SEQ, SERVOJ, SERVOL, SPEEDJ, SPEEDL, STATE,
                      STATE_BYTES, VARIABLES, decode, encode)

#: a package not seen for this long with the link said up is a link that will not come back
#: here (the backend's own link_timeout_s, shorter, has faulted the robot long before)
_SILENT_S = 2.0


#: what ur_rtde (boost.asio) says when nothing, or something that is not a UR controller, is
#: at the address: the connection refused, reset, closed at once ("read: End of file"), timed out
_UNREACHABLE = re.compile(r"connect|read:|write:|end of file|refused|reset by peer|timed out|unreachable|"
                          r"no route|host is down|broken pipe", re.IGNORECASE)


def unreachable(host: str, service: str, port: int, exc: BaseException) -> str | None:
    """The one-line error for a controller that did not answer ``service`` at ``host:port``
    (ur_rtde's own words kept at the end), or None when ``exc`` is not about reaching it."""
    text = " ".join(str(exc).split())
    if not _UNREACHABLE.search(text):
        return None
    return (f"the UR controller at {host} did not answer {service} (port {port}): check backend.host "
            f"(the arm's IP address), the network to it, and that the arm is in remote control "
            f"(pendant: Settings > System > Remote Control) ({text})")


class Worker:
    def __init__(self, sock: socket.socket, mem: mmap.mmap, host: str, rate_hz: float, parent: int):
        self.sock, self.mem, self.host, self.rate_hz, self.parent = sock, mem, host, rate_hz, parent
        self.dt = 1.0 / rate_hz
        self.rcv: Any = None
        self.dash: Any = None
        self.ctl: Any = None
        self.seq = 0
        self.count = 0
        self.job_tids: set[int] = set()  # native ids of request threads (kept at SCHED_OTHER)
        self.priority = 0  # SCHED_FIFO priority of the package thread, the reader and ur_rtde's threads

    # ---------------------------------------------------------------- messages
    def send(self, data: bytes, droppable: bool = False) -> None:
        """One message to the backend. No lock: a SOCK_SEQPACKET send is atomic, so a reply that
        waits for room (the backend not reading for a while) holds up only its own thread, never
        the package thread or the reader. ``droppable`` (wake-ups, refusal notices) never waits."""
        try:
            self.sock.send(data, socket.MSG_DONTWAIT if droppable else 0)
        except (BlockingIOError, InterruptedError):
            pass  # a wake-up the backend will not miss: the state is in shared memory
        except OSError:
            os._exit(0)  # the backend is gone

    def open(self) -> None:
        import dashboard_client
        import rtde_receive

        try:
            self.rcv = rtde_receive.RTDEReceiveInterface(self.host, self.rate_hz, VARIABLES)
        except RuntimeError as exc:
            self.send(encode(b"H", unreachable(self.host, "RTDE", 30004, exc) or (
                f"cannot open RTDE to the UR controller at {self.host}:30004 at "
                f"{self.rate_hz:g} Hz (backend.series / rate_hz): {exc}")))
            os._exit(EXIT_OPEN_FAILED)
        try:
            dash = dashboard_client.DashboardClient(self.host)
            dash.connect()
        except RuntimeError as exc:
            self.send(encode(b"H", unreachable(self.host, "the dashboard server", 29999, exc)
                             or f"cannot reach the UR dashboard server at {self.host}:29999: {exc}"))
            os._exit(EXIT_OPEN_FAILED)
        self.dash = dash
        self.publish()  # the first package before hello: the backend reads a state at once
        self.send(encode(b"H", None))

    # ---------------------------------------------------------------- main thread: the packages
    def publish(self) -> None:
        r = self.rcv
        ctl = self.ctl
        flags = 0
        if ctl is not None:
            flags = CTL_UP
            if ctl.isConnected():
                flags |= CTL_CONNECTED
                if ctl.isProgramRunning():
                    flags |= CTL_RUNNING
        self.count += 1
        fields = (r.getTimestamp(), *r.getActualQ(), *r.getActualQd(), *r.getActualTCPPose(),
                  *r.getActualTCPForce(), r.getRobotMode(), r.getSafetyMode(), r.getRuntimeState(),
                  r.getTargetSpeedFraction(), flags, self.count)
        mem = self.mem
        self.seq += 1
        SEQ.pack_into(mem, 0, self.seq)  # odd: being written
        STATE.pack_into(mem, SEQ.size, *fields)
        self.seq += 1
        SEQ.pack_into(mem, 0, self.seq)

    def run(self) -> None:
        r = self.rcv
        clock = time.perf_counter
        last = r.getTimestamp()
        arrived = clock()
        while True:
            if not r.isConnected():
                os._exit(EXIT_LINK_LOST)
            ctl = self.ctl
            if ctl is not None and not ctl.isConnected():
                os._exit(EXIT_CONTROL_LINK_LOST)
            if os.getppid() != self.parent:
                os._exit(0)  # the backend's process is gone (the socket said so already, normally)
            now = clock()
            due = arrived + self.dt - 0.0003
            if due > now:
                time.sleep(due - now)
            while True:
                ts = r.getTimestamp()
                if ts != last:
                    break
                if clock() - arrived > _SILENT_S:
                    os._exit(EXIT_LINK_LOST)
                if not r.isConnected():
                    os._exit(EXIT_LINK_LOST)
                time.sleep(0.0001)
            last = ts
            arrived = clock()
            try:
                self.publish()
            except RuntimeError:  # the link went down between the checks and the getters
                os._exit(EXIT_LINK_LOST)
            self.send(b"S", droppable=True)

    # ---------------------------------------------------------------- reader thread: the backend's messages
    def read_loop(self) -> None:
        buf = bytearray(65536)
        view = memoryview(buf)
        sock = self.sock
        while True:
            try:
                n = sock.recv_into(buf)
            except OSError:  # ECONNRESET: the backend closed its end with replies unread
                n = 0
            latest = None
            while True:
                if n == 0:
                    os._exit(0)  # the backend closed its end, or its process died
                kind = buf[0]
                if kind == ord("C"):
                    latest = COMMAND.unpack_from(buf, 0)  # the newest realtime command of a run wins
                else:
                    if latest is not None:  # it went before the request: it is carried out before
                        self.realtime(latest)  # (a servoJ racing a goal check's register handshake
                        latest = None  # stops the control script)
                    if kind == ord("Q"):
                        rid, name, args = decode(view[1:n])
                        self.start_job(rid, name, args)
                    elif kind == ord("P"):
                        self.set_priority(int(decode(view[1:n])))
                try:
                    n = sock.recv_into(buf, 0, socket.MSG_DONTWAIT)
                except (BlockingIOError, InterruptedError):
                    break
                except OSError:  # reset by the backend: as its end closed
                    n = 0
            if latest is not None:
                self.realtime(latest)

    def realtime(self, msg: tuple) -> None:
        op = msg[1]
        v = list(msg[2:8])
        a, t, lookahead, gain = msg[8:12]
        ctl = self.ctl
        try:
            if ctl is None:
                raise RuntimeError("no control interface")
            if op == SERVOJ:
                ok = ctl.servoJ(v, 0.0, 0.0, t, lookahead, gain)
            elif op == SPEEDJ:
                ok = ctl.speedJ(v, a, t)
            elif op == SERVOL:
                ok = ctl.servoL(v, 0.0, 0.0, t, lookahead, gain)
            elif op == SPEEDL:
                ok = ctl.speedL(v, a, t)
            elif op == KICK:
                ok = ctl.kickWatchdog()
            else:
                raise RuntimeError(f"unknown realtime op {op}")
            error = None
        except RuntimeError as exc:
            ok, error = False, str(exc)
        if not ok:
            self.send(encode(b"F", [op, error]), droppable=True)

    # ---------------------------------------------------------------- lifecycle requests
    def start_job(self, rid: int, name: str, args: list) -> None:
        def run() -> None:
            self.job_tids.add(threading.get_native_id())
            try:
                if os.sched_getscheduler(0) != os.SCHED_OTHER:
                    # a call that spins (on a dying link) must not starve the package thread
                    os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
            except OSError:
                pass
            try:
                if name not in REQUESTS:
                    raise RuntimeError(f"unknown request {name!r}")
                result, error = self.job(name, args), None
            except Exception as exc:  # carried to the backend, which names the call
                result, error = None, str(exc) or type(exc).__name__
            finally:
                self.job_tids.discard(threading.get_native_id())
            self.send(encode(b"R", [rid, error, result]))

        threading.Thread(target=run, name=f"ur {name}", daemon=True).start()

    def job(self, name: str, args: list) -> Any:
        dash, ctl = self.dash, self.ctl
        if name == "dashboard_connect":
            if not dash.isConnected():
                dash.connect()
            return None
        if name in ("powerOn", "brakeRelease", "powerOff", "unlockProtectiveStop", "closeSafetyPopup",
                    "restartSafety", "play"):
            getattr(dash, name)()
            return None
        if name == "start_script":
            return self.start_script()
        if ctl is None:
            raise RuntimeError("the control script is not running (no control interface)")
        if name == "stop_script":
            return self.stop_script(*args)
        if name == "joints_within":
            return self.joints_within(*args)
        fn: Callable = getattr(ctl, name)
        return fn(*args)

    def start_script(self) -> None:
        """The control interface up and its script running (built, or the script re-uploaded)."""
        import rtde_control

        ctl = self.ctl
        if ctl is None:
            self.ctl = rtde_control.RTDEControlInterface(self.host, self.rate_hz)  # holds the GIL ~16 ms
            # its threads were started by this request thread, at SCHED_OTHER: up with the others,
            # or servoJ on the reader waits on a starved one (seen: the channel filled under load)
            self.set_priority(self.priority)
            return
        if not ctl.isConnected():  # (the main thread ends this worker: never reconnected in place)
            raise RuntimeError("the RTDE control link is down")
        if not ctl.isProgramRunning():
            # A stop that ended the script (protective stop, e-stop, violation) left its last
            # command in the command register (input_int_register_0), and a re-uploaded script
            # plays the register first: a speedJ / speedL running at the stop would start again
            # before the first hold. With the program stopped, any command makes ur_rtde only
            # clear the register (over RTDE; it returns False): done here, and a few controller
            # cycles let the controller take it before the script goes out on port 30003.
            ctl.speedStop(4.0)
            time.sleep(3.0 / self.rate_hz)
            ctl.reuploadScript()

    def stop_script(self, teach: bool, last_kind: str) -> None:
        """Decelerate whatever runs, leave teach mode, end the control script."""
        ctl = self.ctl
        try:
            if teach:
                ctl.endTeachMode()
            if last_kind in ("speedj", "speedl"):
                ctl.speedStop(4.0)
            elif last_kind in ("servoj", "servol"):
                ctl.servoStop(4.0)
        finally:
            ctl.stopScript()

    def joints_within(self, goal: list, here: list) -> dict:
        """isJointsWithinSafetyLimits(goal); when refused, the first joint whose goal alone is."""
        ctl = self.ctl
        if ctl.isJointsWithinSafetyLimits(goal):
            return {"ok": True, "joint": None}
        for i in range(len(goal)):
            q = list(here)
            q[i] = goal[i]
            if not ctl.isJointsWithinSafetyLimits(q):
                return {"ok": False, "joint": i}
        return {"ok": False, "joint": None}

    # ---------------------------------------------------------------- scheduling
    def set_priority(self, priority: int) -> None:
        """The package thread and ur_rtde's own threads at SCHED_FIFO ``priority`` (the control
        loop's minus one, as a backend's threads in the control process), request threads left
        at SCHED_OTHER; 0: nothing to do."""
        self.priority = max(self.priority, priority)
        if priority <= 0:
            return
        for name in os.listdir("/proc/self/task"):
            tid = int(name)
            if tid in self.job_tids:
                continue
            try:
                os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(priority))
            except OSError:
                return  # not permitted: the control process said so already


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="crtk_bridge.backends.ur.worker")
    ap.add_argument("--sock", type=int, required=True)
    ap.add_argument("--state", type=int, required=True)
    ap.add_argument("--host", required=True)
    ap.add_argument("--rate", type=float, required=True)
    ap.add_argument("--parent", type=int, required=True)
    ap.add_argument("--rt-priority", type=int, default=0)
    args = ap.parse_args(argv)
    if os.getppid() != args.parent:
        return 0  # its parent died before it started
    sock = socket.socket(fileno=args.sock)
    mem = mmap.mmap(args.state, STATE_BYTES)
    os.close(args.state)
    w = Worker(sock, mem, args.host, args.rate, args.parent)
    reader = threading.Thread(target=w.read_loop, name="ur worker reader", daemon=True)
    w.set_priority(args.rt_priority)  # before ur_rtde's threads start: they inherit it
    w.open()
    reader.start()
    w.run()
    return 0


if __name__ == "__main__":
    sys.exit(main())
