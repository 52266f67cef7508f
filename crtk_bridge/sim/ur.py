"""A simulated Universal Robots controller (UR5e) on a loopback address, for ur_rtde unmodified.

The controller's fixed ports on a host chosen by the caller (any 127.x address, so simulators
run side by side): RTDE on 30004 (:mod:`crtk_bridge.sim.ur_wire`), the dashboard server on 29999
and the script port 30003, where ur_rtde's ``rtde_control`` program is uploaded and then played
(:mod:`crtk_bridge.sim.ur_script`) against the arm model (:mod:`crtk_bridge.sim.ur_robot`).
Data packages stream at 500 Hz (e-Series, controller 5.11.1) or 125 Hz (CB3, 3.15.7).

Two pieces:

- :class:`URController` serves all of that in the current process (``crtk-sim ur`` runs it).
- :class:`URSimulator` is the handle tests and ``--sim`` use: ``start()`` spawns ``crtk-sim ur``
  as a SUBPROCESS (ur_rtde's constructors hold the GIL while they block, so a controller in
  the client's own interpreter deadlocks it) and returns once its ports accept; ``stop()`` ends
  it. Fault injection goes through the controller's control socket (JSON lines,
  :mod:`crtk_bridge.sim.control`):

  ``{"cmd": "state"}`` modes, joints, TCP pose, program, last error, ``rx_bytes`` (what clients
  sent on every port);
  ``{"cmd": "stop", "kind": K, "cause": "..."}`` K in protective, safeguard, robot_estop,
  system_estop, fault, violation; ``{"cmd": "release", "kind": K}`` (safeguard, e-stops);
  ``{"cmd": "link_loss", "duration_s": S, "ports": ["rtde", "dashboard", "script"]}`` drops
  those connections and refuses new ones for S seconds (default: RTDE only);
  ``{"cmd": "restart", "duration_s": S}`` a controller reboot: every connection dropped, ports
  closed for S s, then powered off with no program; ``{"cmd": "speed_slider", "fraction": F}``;
  ``{"cmd": "hand", "q": [...], "speed": rad/s}`` pushes the arm in teach mode;
  ``{"cmd": "wrench", "force": [6]}`` the TCP force/torque; ``{"cmd": "stall_script", "on": B}``
  the program takes no command while the arm goes on (its watchdog still runs);
  ``{"cmd": "timings", ...}``.

The tool flange: with ``tool_link`` (``crtk-sim ur --tool-link PATH``) the controller also serves
TCP :data:`TOOL_PORT` (54321, as UR's / Robotiq's tool-communication URCap does), relaying the
bytes of one client at a time to and from the serial line behind the tool connector: the serial
device at ``tool_link`` (a Robotiq gripper simulator's pty, at ``tool_baud``), opened when the
client connects. ``link_loss`` / ``restart`` take the port ``tool`` too.
"""

from __future__ import annotations

import logging
import math
import os
import select
import shutil
import signal
import socket
import struct
import subprocess
import tempfile
import threading
import time
import tty

import numpy as np

from ..profile import Profile
from ..spawn import module_argv, module_env
from . import SimulatorError
from .control import ControlServer, control_request
from .loopback import free_loopback_host
from .pty import set_line_baud
from .ur_robot import STOPS, Hand, Limits, N, RobotMode, RuntimeState, Servo, Timings, URRobot
from .ur_script import ControlScript, program_name
from .ur_wire import (HEADER, IN_USE, INPUTS, NOT_FOUND, OUTPUTS, Msg, Recipe, frame, input_register,
                      split_names)

log = logging.getLogger(__name__)

RTDE_PORT, DASHBOARD_PORT, SCRIPT_PORT = 30004, 29999, 30003
PORTS = {"rtde": RTDE_PORT, "dashboard": DASHBOARD_PORT, "script": SCRIPT_PORT}
#: the tool flange's RS-485 as a TCP socket (UR's tool communication: raw bytes both ways)
TOOL_PORT = 54321
#: series -> (controller version major, minor, bugfix, build; data package rate Hz)
SERIES = {"e-series": ((5, 11, 1, 108318), 500.0), "cb3": ((3, 15, 7, 106331), 125.0)}
SERIAL_NUMBER = "20235500001"
WELCOME = "Connected: Universal Robots Dashboard Server"
_PENDING_MAX = 1 << 16  # bytes queued for a client that does not read: newer packages dropped
START_TIMEOUT_S = 15.0


class Registers:
    """The controller's general-purpose RTDE registers and the other inputs clients write."""

    def __init__(self):
        self.reset()

    def reset(self) -> None:
        self.ints = [0] * 48
        self.doubles = [0.0] * 48
        self.out_ints = [0] * 48
        self.out_doubles = [0.0] * 48
        self.digital_out = 0
        self.input_at = 0.0  # clock of the last package writing the command register (watchdog)


#: dashboard commands with a fixed reply: command -> (reply, what it does to the arm); the
#: replies are the dashboard server's (UR "Dashboard server e-Series" manual; ur_rtde compares
#: some verbatim)
_DASHBOARD = {
    "get serial number": (SERIAL_NUMBER, None),
    "get robot model": ("UR5", None),
    "power on": ("Powering on", URRobot.power_on),
    "power off": ("Powering off", URRobot.power_off),
    "brake release": ("Brake releasing", URRobot.brake_release),
    "close safety popup": ("closing safety popup", None),
    "restart safety": ("Restarting safety", URRobot.restart_safety),
    "is in remote control": ("true", None),
    "close popup": ("closing popup", None),
    "quit": ("Disconnected", None),
    "shutdown": ("Shutting down", None),
}


class _RtdeClient:
    """One RTDE connection: its recipes and an outgoing queue (a slow reader loses packages)."""

    def __init__(self, sock: socket.socket):
        self.sock = sock
        self.output: Recipe | None = None
        self.every = 1  # ticks per data package
        self.inputs: dict[int, Recipe] = {}
        self.next_id = 1
        self.started = False
        self.pending = b""
        self.send_lock = threading.Lock()
        self.closed = False

    def send(self, data: bytes, droppable: bool = False) -> None:
        with self.send_lock:
            if self.closed:
                return
            if droppable and len(self.pending) > _PENDING_MAX:
                return
            self.pending += data
            try:
                n = self.sock.send(self.pending, socket.MSG_DONTWAIT)
                self.pending = self.pending[n:]
            except BlockingIOError:
                pass
            except OSError:
                self.closed = True


class URController:
    """The controller's servers, arm and program in this process (see the module docstring).

    ``start()`` binds the three ports on ``host`` (raises SimulatorError naming the address if
    one is taken) and the control socket, then returns; ``stop()`` is idempotent.
    """

    def __init__(self, host: str, *, q0=None, limits: Limits | None = None, series: str = "e-series",
                 timings: Timings | None = None, control: str | os.PathLike | None = None,
                 tool_link: str | os.PathLike | None = None, tool_baud: int = 115200):
        if series not in SERIES:
            raise SimulatorError(f"ur: series {series!r} unknown; valid: {', '.join(SERIES)}")
        self.host = host
        self.series = series
        self.version, self.rate_hz = SERIES[series]
        self._lock = threading.Lock()
        self._t0 = time.monotonic()
        self.robot = URRobot(q0 if q0 is not None else [0.0, -math.pi / 2, math.pi / 2, -math.pi / 2, -math.pi / 2, 0.0],
                             limits or Limits(), timings or Timings(), clock=self.clock)
        self.robot.step_s = 1.0 / self.rate_hz
        self.reg = Registers()
        self._control = ControlServer(control, self.control) if control else None
        self.control_path = str(control) if control else None
        #: the ports served: the controller's three, and the tool flange's with a tool link
        self.ports = {**PORTS, **({"tool": TOOL_PORT} if tool_link else {})}
        self.tool_link = str(tool_link) if tool_link else None
        self.tool_baud = int(tool_baud)
        self._listeners: dict[str, socket.socket] = {}
        self._refused_until: dict[str, float] = {}
        self._clients: dict[str, set[socket.socket]] = {p: set() for p in self.ports}
        self._rtde: list[_RtdeClient] = []
        self._input_owner: dict[str, _RtdeClient] = {}
        self._threads: list[threading.Thread] = []
        self._stopping = threading.Event()
        self._restart_at: float | None = None
        self.ticks = 0
        #: bytes received from clients on every port (RTDE, dashboard, script): what reached the
        #: controller, as a serial bus simulator counts what reached its servos
        self.rx_bytes = 0
        self._rx_lock = threading.Lock()
        self.running = False
        self._getters = self._output_getters()

    def clock(self) -> float:
        return time.monotonic() - self._t0

    # ---- lifecycle ----
    def start(self) -> None:
        for name in self.ports:
            self._listen(name)
        if self._control is not None:
            self._control.start()
        self.running = True
        self._spawn(self._tick_loop, "ur-tick")
        self._spawn(self._accept_loop, "ur-accept")

    def stop(self) -> None:
        if self._stopping.is_set():
            return
        self._stopping.set()
        for t in self._threads:
            if t is not threading.current_thread() and t.name in ("ur-tick", "ur-accept"):
                t.join(2.0)
        with self._lock:
            for name in list(self._listeners):
                self._close_listener(name)
            self._drop(tuple(self.ports))
        if self._control is not None:
            self._control.stop()
        self.running = False

    def _spawn(self, target, name: str, *args) -> None:
        t = threading.Thread(target=target, args=args, name=name, daemon=True)
        self._threads = [x for x in self._threads if x.is_alive()]
        self._threads.append(t)
        t.start()

    def _listen(self, name: str) -> None:
        s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((self.host, self.ports[name]))
        except OSError as exc:
            s.close()
            raise SimulatorError(f"ur: cannot bind {self.host}:{self.ports[name]} ({name}): {exc.strerror or exc}") from exc
        s.listen(16)
        s.setblocking(False)
        self._listeners[name] = s

    def _close_listener(self, name: str) -> None:
        s = self._listeners.pop(name, None)
        if s is not None:
            try:
                # stop listening NOW: a bare close() leaves the socket listening until the
                # accept thread's select() lets go of it, and connections queued meanwhile
                # are accepted by the kernel, then reset
                s.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            s.close()

    def _drop(self, names) -> None:
        """Close every connection on the ports ``names`` (caller holds the lock)."""
        for name in names:
            for c in self._clients[name]:
                try:
                    c.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
                c.close()
            self._clients[name].clear()
        if "rtde" in names:
            for r in self._rtde:
                r.closed = True
            self._rtde.clear()
            self._input_owner.clear()

    # ---- accepting ----
    def _accept_loop(self) -> None:
        handlers = {"rtde": self._serve_rtde, "dashboard": self._serve_dashboard, "script": self._serve_script,
                    "tool": self._serve_tool}
        while not self._stopping.is_set():
            with self._lock:
                now = self.clock()
                for name in self.ports:
                    until = self._refused_until.get(name)
                    if until is not None and now >= until and not (self._restart_at and now < self._restart_at):
                        try:
                            self._listen(name)
                            del self._refused_until[name]
                        except SimulatorError as exc:
                            log.error("%s", exc)
                listeners = list(self._listeners.items())
            if not listeners:
                time.sleep(0.01)
                continue
            try:
                ready, _, _ = select.select([s for _, s in listeners], [], [], 0.05)
            except (OSError, ValueError):
                continue  # a listener closed under us by a link loss
            for name, s in listeners:
                if s not in ready:
                    continue
                try:
                    conn, _ = s.accept()
                except OSError:
                    continue
                conn.settimeout(None)
                conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                with self._lock:
                    if self._listeners.get(name) is not s:  # refused meanwhile
                        conn.close()
                        continue
                    if name == "tool" and self._clients[name]:  # the tool's serial line: one client
                        conn.close()
                        continue
                    self._clients[name].add(conn)
                self._spawn(handlers[name], f"ur-{name}", conn)

    def _received(self, data: bytes) -> None:
        with self._rx_lock:  # not the controller's lock: the tick must not wait on a client
            self.rx_bytes += len(data)

    def _forget(self, name: str, conn: socket.socket) -> None:
        with self._lock:
            self._clients[name].discard(conn)
        try:
            conn.close()
        except OSError:
            pass

    # ---- RTDE ----
    def _serve_rtde(self, conn: socket.socket) -> None:
        client = _RtdeClient(conn)
        with self._lock:
            self._rtde.append(client)
        buf = b""
        try:
            while not self._stopping.is_set():
                data = conn.recv(65536)
                if not data:
                    break
                self._received(data)
                buf += data
                while len(buf) >= HEADER.size:
                    size, kind = HEADER.unpack_from(buf)
                    if size < HEADER.size:
                        raise ValueError(f"RTDE message of size {size}")
                    if len(buf) < size:
                        break
                    payload, buf = buf[HEADER.size:size], buf[size:]
                    self._rtde_message(client, kind, payload)
        except (OSError, ValueError) as exc:
            log.debug("rtde client: %s", exc)
        finally:
            with self._lock:
                client.closed = True
                if client in self._rtde:
                    self._rtde.remove(client)
                for name in [n for n, c in self._input_owner.items() if c is client]:
                    del self._input_owner[name]
            self._forget("rtde", conn)

    def _rtde_message(self, client: _RtdeClient, kind: int, payload: bytes) -> None:
        if kind == Msg.REQUEST_PROTOCOL_VERSION:
            client.send(frame(kind, b"\x01"))
        elif kind == Msg.GET_URCONTROL_VERSION:
            client.send(frame(kind, struct.pack(">IIII", *self.version)))
        elif kind == Msg.CONTROL_PACKAGE_SETUP_OUTPUTS:
            (freq,) = struct.unpack_from(">d", payload)
            names = split_names(payload[8:])
            recipe = Recipe(1, names, [OUTPUTS.get(n, NOT_FOUND) for n in names])
            with self._lock:
                client.output = recipe if recipe.valid else None
                client.every = max(1, round(self.rate_hz / freq)) if freq > 0 else 1
            if not recipe.valid:
                log.warning("rtde: output recipe refused: %s", [n for n, t in zip(names, recipe.types) if t == NOT_FOUND])
            client.send(frame(kind, recipe.setup_reply()))
        elif kind == Msg.CONTROL_PACKAGE_SETUP_INPUTS:
            names = split_names(payload)
            with self._lock:
                types = []
                for n in names:
                    owner = self._input_owner.get(n)
                    types.append(INPUTS.get(n, NOT_FOUND) if owner in (None, client) else IN_USE)
                recipe = Recipe(client.next_id, names, types)
                client.next_id += 1
                log.debug("rtde: input recipe %d: %s", recipe.id, ",".join(names))
                if recipe.valid:
                    client.inputs[recipe.id] = recipe
                    for n in names:
                        self._input_owner[n] = client
                else:
                    log.warning("rtde: input recipe refused: %s", list(zip(names, types)))
            client.send(frame(kind, recipe.setup_reply()))
        elif kind == Msg.CONTROL_PACKAGE_START:
            with self._lock:
                client.started = client.output is not None
            client.send(frame(kind, b"\x01" if client.started else b"\x00"))
        elif kind == Msg.CONTROL_PACKAGE_PAUSE:
            with self._lock:
                client.started = False
            client.send(frame(kind, b"\x01"))
        elif kind == Msg.DATA_PACKAGE:
            recipe = client.inputs.get(payload[0]) if payload else None
            if recipe is None:
                log.warning("rtde: data package for unknown input recipe %s", payload[:1].hex())
                return
            try:
                values = recipe.unpack(payload)
            except (ValueError, struct.error) as exc:
                log.warning("rtde: %s", exc)
                return
            with self._lock:
                self._apply_inputs(values)
        elif kind == Msg.TEXT_MESSAGE:
            pass  # a client's text message: the controller only logs it
        else:
            log.warning("rtde: unknown message type %d", kind)

    def _apply_inputs(self, values: dict) -> None:
        reg = self.reg
        for name, v in values.items():
            r = input_register(name)
            if r is not None:
                (reg.ints if r[0] == "int" else reg.doubles)[r[1]] = v
        if values.get("speed_slider_mask", 0) & 1:
            self.robot.speed_fraction = min(1.0, max(0.0, float(values.get("speed_slider_fraction", 1.0))))
        if "standard_digital_output_mask" in values:
            mask = values["standard_digital_output_mask"]
            reg.digital_out = (reg.digital_out & ~mask) | (values.get("standard_digital_output", 0) & mask)
        if "input_int_register_0" in values or "input_int_register_24" in values:
            reg.input_at = self.clock()  # what the script's rtde_set_watchdog watches

    def _output_getters(self) -> dict:
        r, reg = self.robot, self.reg
        zeros6 = [0.0] * N
        g = {
            "timestamp": lambda: self.ticks / self.rate_hz,  # controller time: one period per tick
            "target_q": lambda: r.target_q.tolist(),
            "target_qd": lambda: r.qd.tolist(),
            "actual_q": lambda: r.q.tolist(),
            "actual_qd": lambda: r.qd.tolist(),
            "actual_TCP_pose": lambda: self._pose,
            "target_TCP_pose": lambda: self._pose,
            "actual_TCP_speed": lambda: self._speed,
            "target_TCP_speed": lambda: self._speed,
            "actual_TCP_force": lambda: r.tcp_force.tolist(),
            "ft_raw_wrench": lambda: r.tcp_force.tolist(),
            "tcp_force_scalar": lambda: float(np.linalg.norm(r.tcp_force[:3])),
            "robot_mode": lambda: int(r.robot_mode),
            "joint_mode": lambda: r.joint_mode,
            "safety_mode": lambda: int(r.safety_mode),
            "safety_status": lambda: int(r.safety_mode),
            "runtime_state": lambda: int(r.runtime_state),
            "robot_status_bits": lambda: r.robot_status_bits,
            "safety_status_bits": lambda: r.safety_status_bits,
            "target_speed_fraction": lambda: r.speed_fraction,
            "speed_scaling": lambda: r.speed_fraction if r.may_move else 0.0,
            "actual_digital_output_bits": lambda: reg.digital_out,
            "joint_temperatures": lambda: [30.0] * N,
            "actual_main_voltage": lambda: 48.0,
            "actual_robot_voltage": lambda: 48.0 if r.robot_status_bits & 1 else 0.0,
            "actual_joint_voltage": lambda: [48.0 if r.robot_status_bits & 1 else 0.0] * N,
            "actual_tool_accelerometer": lambda: [0.0, 0.0, 9.81],
            "actual_execution_time": lambda: 0.1,  # ms of controller compute per tick
        }
        for name, kind in OUTPUTS.items():
            if name in g:
                continue
            reg_name = name.startswith(("output_int_register_", "output_double_register_",
                                        "input_int_register_", "input_double_register_"))
            if reg_name:
                i = int(name.rsplit("_", 1)[1])
                table = {"output_int": reg.out_ints, "output_double": reg.out_doubles,
                         "input_int": reg.ints, "input_double": reg.doubles}["_".join(name.split("_")[:2])]
                g[name] = (lambda t, k: lambda: t[k])(table, i)
            elif kind == "VECTOR6D":
                g[name] = lambda: zeros6
            elif kind == "VECTOR3D":
                g[name] = lambda: [0.0, 0.0, 0.0]
            elif kind == "VECTOR6INT32":
                g[name] = lambda: [0] * N
            elif kind == "DOUBLE":
                g[name] = lambda: 0.0
            else:
                g[name] = lambda: 0
        return g

    # ---- the controller tick ----
    def _tick_loop(self) -> None:
        period = 1.0 / self.rate_hz
        dt = period
        deadline = time.monotonic()
        try:
            while not self._stopping.is_set():
                deadline += period
                with self._lock:
                    self._tick(dt)
                    streams = [(c, c.output) for c in self._rtde if c.started and c.output is not None
                               and self.ticks % c.every == 0]
                    if streams:
                        values = {}
                        for _, recipe in streams:
                            for n in recipe.names:
                                if n not in values:
                                    values[n] = self._getters[n]()
                        packets = [(c, frame(Msg.DATA_PACKAGE, recipe.pack(values))) for c, recipe in streams]
                    else:
                        packets = []
                for c, data in packets:
                    c.send(data, droppable=True)
                rest = deadline - time.monotonic()
                if rest > 0:
                    time.sleep(rest)
                elif rest < -10 * period:
                    deadline = time.monotonic()  # far behind (host stalled): do not burst
        except Exception:
            log.exception("ur: the controller tick died")
            self.running = False

    def _tick(self, dt: float) -> None:
        self.ticks += 1
        now = self.clock()
        if self._restart_at is not None and now >= self._restart_at:
            self._restart_at = None
            log.info("controller booted")
        self.robot.step(dt)
        self._pose = self.robot.tcp_pose()
        self._speed = self.robot.tcp_speed()

    # ---- the tool flange ----
    def _serve_tool(self, conn: socket.socket) -> None:
        """Relay one client's bytes to and from the serial line behind the tool connector (the
        device at ``tool_link``), unchanged both ways, until either side closes."""
        try:
            fd = os.open(self.tool_link, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        except OSError as exc:
            log.warning("tool port: no serial device at %s (%s): connection closed", self.tool_link, exc)
            self._forget("tool", conn)
            return
        try:
            tty.setraw(fd)
            set_line_baud(fd, self.tool_baud)
            while not self._stopping.is_set():
                ready, _, _ = select.select([conn, fd], [], [], 0.2)
                if conn in ready:
                    data = conn.recv(4096)
                    if not data:
                        break
                    self._received(data)
                    while data:
                        try:
                            data = data[os.write(fd, data):]
                        except BlockingIOError:
                            select.select([], [fd], [], 0.1)
                if fd in ready:
                    try:
                        data = os.read(fd, 4096)
                    except BlockingIOError:
                        continue
                    if not data:
                        break
                    conn.sendall(data)
        except OSError as exc:  # the client went, or the device's line did (EIO)
            log.info("tool port: relay ended: %s", exc)
        finally:
            os.close(fd)
            self._forget("tool", conn)

    # ---- dashboard ----
    def _serve_dashboard(self, conn: socket.socket) -> None:
        try:
            conn.sendall((WELCOME + "\n").encode())
            f = conn.makefile("rb")
            for raw in f:
                self._received(raw)
                line = raw.decode("utf-8", "replace").strip()
                with self._lock:
                    reply = self.dashboard(line)
                conn.sendall((reply + "\n").encode())
                if line == "quit":
                    break
        except OSError:
            pass
        finally:
            self._forget("dashboard", conn)

    def dashboard(self, line: str) -> str:
        """The dashboard server's answer to one command line (caller holds the lock)."""
        r = self.robot
        cmd = line.strip()
        low = cmd.lower()
        if low == "polyscopeversion":
            v = self.version
            return f"URSoftware {v[0]}.{v[1]}.{v[2]}.{v[3]} (Mar 22 2022)"
        simple = _DASHBOARD.get(low)
        if simple is not None:
            reply, action = simple
            if action is not None:
                action(r)
            return reply
        if low == "unlock protective stop":
            return r.unlock_protective_stop()
        if low == "robotmode":
            return f"Robotmode: {r.robot_mode.name}"
        if low == "safetymode":
            return f"Safetymode: {r.safety_mode.name}"
        if low == "safetystatus":
            return f"Safetystatus: {r.safety_mode.name}"
        if low == "programstate":
            state = {RuntimeState.PLAYING: "PLAYING", RuntimeState.PAUSED: "PAUSED"}.get(r.runtime_state, "STOPPED")
            return f"{state} {r.program or r.loaded_program or '<unnamed>'}"
        if low == "running":
            return f"Program running: {'true' if r.runtime_state == RuntimeState.PLAYING else 'false'}"
        if low == "stop":
            r.stop_program("dashboard stop")
            return "Stopped"
        if low == "pause":
            if r.runtime_state != RuntimeState.PLAYING:
                return "Failed to execute: pause"
            r.pause_program()
            return "Pausing program"
        if low == "play":
            if r.runtime_state == RuntimeState.PAUSED and r.program is not None:
                r.runtime_state = RuntimeState.PLAYING
                return "Starting program"
            if r.loaded_program is None or not r.start_program(r.loaded_program):
                return "Failed to execute: play"
            return "Starting program"
        if low.startswith("load "):
            r.loaded_program = cmd[5:].strip()
            return f"Loading program: {r.loaded_program}"
        if low == "get loaded program":
            return f"Loaded program: {r.loaded_program}" if r.loaded_program else "No program loaded"
        if low == "isprogramsaved":
            return f"true {r.loaded_program or '<unnamed>'}"
        if low.startswith("popup "):
            return "showing popup"
        return f"could not understand: '{cmd}'"

    # ---- script port ----
    def _serve_script(self, conn: socket.socket) -> None:
        text = ""
        try:
            while not self._stopping.is_set():
                data = conn.recv(65536)
                if not data:
                    break
                self._received(data)
                text += data.decode("utf-8", "replace")
                text = self._run_scripts(text)
        except OSError:
            pass
        finally:
            self._forget("script", conn)

    def _run_scripts(self, text: str) -> str:
        """Start every complete program in ``text`` (``def name(): ... end`` with the ``end``
        at column 0); returns what is left, waiting for more."""
        while True:
            start = text.find("def ")
            if start < 0:
                if text.strip() and text.endswith("\n"):
                    log.warning("script port: a statement outside a program is not simulated: %.60r", text)
                    return ""
                return text
            end = _program_end(text, start)
            if end < 0:
                return text
            program, text = text[start:end], text[end:]
            name = program_name(program)
            with self._lock:
                if name == "rtde_control":
                    self.robot.start_program(name, ControlScript(self.robot, self.reg, program))
                else:
                    log.warning("script port: program %s is not simulated: it runs without effect", name)
                    self.robot.start_program(name or "<unnamed>")

    # ---- control socket ----
    def control(self, request: dict) -> dict:
        cmd = request.get("cmd")
        with self._lock:
            r = self.robot
            if cmd == "state":
                return {"ok": True, **self.state()}
            if cmd == "stop":
                kind = request.get("kind", "protective")
                if kind not in STOPS:
                    return {"ok": False, "error": f"stop kind {kind!r} unknown; valid: {', '.join(STOPS)}"}
                r.inject_stop(kind, str(request.get("cause", f"{kind} stop injected")))
                return {"ok": True}
            if cmd == "release":
                kind = request.get("kind", "safeguard")
                if kind in ("protective", "fault", "violation"):
                    how = "unlock protective stop" if kind == "protective" else "restart safety"
                    return {"ok": False, "error": f"a {kind} stop is not released by a button: the dashboard's "
                                                  f"'{how}' clears it"}
                if not r.release_stop(kind):
                    return {"ok": False, "error": f"no {kind} stop to release (safety mode {r.safety_mode.name})"}
                return {"ok": True}
            if cmd == "link_loss":
                ports = request.get("ports", ["rtde"])
                bad = [p for p in ports if p not in self.ports]
                if bad:
                    return {"ok": False, "error": f"ports {bad} unknown; valid: {', '.join(self.ports)}"}
                self._refuse(ports, float(request.get("duration_s", 1.0)))
                return {"ok": True}
            if cmd == "restart":
                duration = float(request.get("duration_s", 1.0))
                self._refuse(list(self.ports), duration)
                self._restart_at = self.clock() + duration
                r.restart_safety()
                r.loaded_program = None
                self.reg.reset()
                return {"ok": True}
            if cmd == "speed_slider":
                f = float(request.get("fraction", 1.0))
                if not 0.0 <= f <= 1.0:
                    return {"ok": False, "error": f"speed slider fraction {f} outside [0, 1]"}
                r.speed_fraction = f
                return {"ok": True}
            if cmd == "hand":
                if not r.teach_mode:
                    return {"ok": False, "error": "the arm is not in teach mode: its brakes hold it"}
                q = request.get("q")
                if not isinstance(q, list) or len(q) != N:
                    return {"ok": False, "error": "hand: q must be a list of 6 joint angles (rad)"}
                r.motion = Hand(q, float(request.get("speed", 0.5)))
                return {"ok": True}
            if cmd == "wrench":
                f = request.get("force")
                if not isinstance(f, list) or len(f) != 6:
                    return {"ok": False, "error": "wrench: force must be a list of 6 numbers (N, N*m)"}
                r.tcp_force = np.asarray(f, dtype=float)
                return {"ok": True}
            if cmd == "stall_script":
                r.script_stalled = bool(request.get("on", True))
                return {"ok": True}
            if cmd == "timings":
                for k in ("power_on_s", "brake_release_s", "unlock_delay_s"):
                    if k in request:
                        setattr(r.timings, k, float(request[k]))
                return {"ok": True}
        return {"ok": False, "error": f"unknown command {cmd!r}; valid: state, stop, release, link_loss, "
                                      "restart, speed_slider, hand, wrench, stall_script, timings"}

    def _refuse(self, ports: list[str], duration_s: float) -> None:
        """Drop the connections of ``ports`` and refuse new ones for ``duration_s`` (lock held)."""
        until = self.clock() + duration_s
        for p in ports:
            self._close_listener(p)
            self._refused_until[p] = until
        self._drop(ports)

    def state(self) -> dict:
        r = self.robot
        return {
            "host": self.host, "robot_mode": r.robot_mode.name, "safety_mode": r.safety_mode.name,
            "runtime_state": r.runtime_state.name, "program": r.program, "teach_mode": r.teach_mode,
            "q": r.q.tolist(), "qd": r.qd.tolist(), "tcp_pose": r.tcp_pose(),
            # the joint target the controller follows: servoj's, else where the arm is held
            "target_q": (r.motion.target if isinstance(r.motion, Servo) else r.target_q).tolist(),
            "speed_fraction": r.speed_fraction, "stop_cause": r.stop_cause, "last_error": r.last_error,
            "motion": type(r.motion).__name__ if r.motion is not None else None,
            "rtde_clients": len(self._rtde), "ticks": self.ticks, "rate_hz": self.rate_hz,
            "out_int_0": self.reg.out_ints[0], "command": self.reg.ints[0], "rx_bytes": self.rx_bytes,
            "tool_link": self.tool_link, "tool_clients": len(self._clients.get("tool", ())),
        }


def _program_end(text: str, start: int) -> int:
    """Index just past the column-0 ``end`` line closing the program at ``start``, or -1."""
    pos = text.find("\n", start)
    while pos >= 0:
        nxt = text.find("\n", pos + 1)
        line = text[pos + 1: nxt if nxt >= 0 else len(text)]
        if line.rstrip() == "end" and nxt >= 0:
            return nxt + 1
        pos = nxt
    return -1


# ---------------------------------------------------------------------------------------------
# The handle: the controller as a subprocess


def _die_with_parent() -> None:
    """In the child before exec: SIGTERM it when the process that started it dies, however it
    dies (a test run killed by a timeout must not leave a controller holding the address).
    Linux sends it when the THREAD that spawned the child ends: call start() from a thread that
    lives as long as the simulator (the main thread)."""
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM, 0, 0, 0)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass  # not Linux: stop() still ends it


def profile_options(profile: Profile) -> dict:
    """What the simulated controller takes from a robot profile: the first six joints' safety
    limits and home pose (where the arm rests at start), and ``backend.series``."""
    if len(profile.joints) != N:
        raise SimulatorError(f"{profile.name}: a UR arm has {N} joints, the profile has {len(profile.joints)}")
    backend = profile.backend or {}
    return {
        "q0": [0.0 if j.home is None else j.home for j in profile.joints],
        "lower": [j.limits.position_min for j in profile.joints],
        "upper": [j.limits.position_max for j in profile.joints],
        "series": str(backend.get("series", "e-series")),
    }


class URSimulator:
    """``crtk-sim ur`` as a child process; see the module docstring. ``port`` is the host the
    controller serves on (the endpoint ``--sim`` writes into the profile)."""

    device = "ur"

    def __init__(self, profile_path: str | os.PathLike, host: str | None = None,
                 control: str | os.PathLike | None = None, series: str | None = None,
                 timings: Timings | None = None, tmpdir: str | None = None,
                 tool_link: str | os.PathLike | None = None):
        self.profile_path = str(profile_path)
        self.tool_link = str(tool_link) if tool_link else None
        self._auto_host = host is None
        self.host = host
        self.series = series
        self.timings = timings or Timings()
        self._tmpdir = tmpdir
        self._own_tmpdir = tmpdir is None
        self.control_path = str(control) if control else None
        self.proc: subprocess.Popen | None = None
        self.log_path: str | None = None

    @classmethod
    def from_profile(cls, profile: Profile, host: str | None = None, control: str | os.PathLike | None = None,
                     series: str | None = None, tool_link: str | os.PathLike | None = None,
                     **timings: float) -> URSimulator:
        """A simulator for ``profile`` (written to a temp file for the child). ``host`` None:
        a free 127.0.0.N is chosen at start. ``timings``: power_on_s, brake_release_s,
        unlock_delay_s (see :class:`Timings`)."""
        import msgspec
        import yaml

        profile_options(profile)  # fail here, in the caller, on a profile that is no UR arm
        tmpdir = tempfile.mkdtemp(prefix="crtk-ursim-")
        path = os.path.join(tmpdir, "profile.yaml")
        with open(path, "w") as f:
            yaml.safe_dump(msgspec.to_builtins(profile), f)
        sim = cls(path, host=host, control=control, series=series, timings=Timings(**timings), tmpdir=tmpdir,
                  tool_link=tool_link)
        sim._own_tmpdir = True
        return sim

    @classmethod
    def attach(cls, control: str | os.PathLike) -> URSimulator:
        """A handle on a controller another process started (``crtk-bridge --sim``), reached over
        its control socket ``control``: the control calls work, ``start`` / ``stop`` do nothing."""
        sim = cls("", control=control)
        sim._attached = True
        sim.host = sim.state().get("host")
        return sim

    _attached = False

    @property
    def port(self) -> str | None:
        return self.host

    @property
    def running(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def start(self, timeout_s: float = START_TIMEOUT_S) -> None:
        """Spawn the controller and return once its three ports accept (raises SimulatorError
        with the child's last log lines otherwise; the child is then ended). Blocks up to
        ``timeout_s``. Call it from a long-lived thread (see :func:`_die_with_parent`)."""
        if self.running or self._attached:
            return
        if self._tmpdir is None:
            self._tmpdir = tempfile.mkdtemp(prefix="crtk-ursim-")
        if self.control_path is None:
            self.control_path = os.path.join(self._tmpdir, "ur.ctl")
        self.log_path = os.path.join(self._tmpdir, "ur.log")
        for attempt in range(3 if self._auto_host else 1):
            if self._auto_host:
                self.host = free_loopback_host(PORTS.values())
            try:
                self._spawn(timeout_s)
                return
            except SimulatorError:
                if attempt == (2 if self._auto_host else 0):
                    raise

    def _spawn(self, timeout_s: float) -> None:
        env = module_env()  # this package's simulator, whatever the current folder holds (spawn.py)
        t = self.timings
        argv = module_argv(
            "crtk_bridge.sim.cli", "ur", "--profile", self.profile_path,
            "--host", self.host, "--control", self.control_path, "--log-level", "info",
            "--power-on-s", str(t.power_on_s), "--brake-release-s", str(t.brake_release_s),
            "--unlock-delay-s", str(t.unlock_delay_s), *(["--series", self.series] if self.series else []),
            *(["--tool-link", self.tool_link] if self.tool_link else []),
            "--parent-pid", str(os.getpid()))  # it also stops once this process is gone
        with open(self.log_path, "ab") as logf:
            self.proc = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=logf, stderr=logf, env=env,
                                         start_new_session=True, preexec_fn=_die_with_parent)
        deadline = time.monotonic() + timeout_s
        while True:
            if self.proc.poll() is not None:
                raise SimulatorError(f"ur simulator on {self.host} exited with status {self.proc.returncode}: "
                                     f"{self.log_tail()}")
            if os.path.exists(self.control_path) and self._accepts():
                return
            if time.monotonic() > deadline:
                self.stop()
                raise SimulatorError(f"ur simulator on {self.host}: ports not accepting after {timeout_s:g} s: "
                                     f"{self.log_tail()}")
            time.sleep(0.02)

    def _accepts(self) -> bool:
        for port in PORTS.values():
            try:
                socket.create_connection((self.host, port), timeout=0.2).close()
            except OSError:
                return False
        return True

    def log_tail(self, lines: int = 5) -> str:
        try:
            with open(self.log_path, errors="replace") as f:
                return " | ".join(f.read().splitlines()[-lines:]) or "(no output)"
        except (OSError, TypeError):
            return "(no log)"

    def stop(self) -> None:
        """End the child (SIGTERM, then SIGKILL after 5 s). Idempotent."""
        if self._attached:
            return
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(5.0)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        if self._own_tmpdir and self._tmpdir and os.path.isdir(self._tmpdir) and self.proc is not None:
            shutil.rmtree(self._tmpdir, ignore_errors=True)
            self._tmpdir = None
            self.control_path = None

    def __enter__(self) -> URSimulator:
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    # ---- control socket ----
    def control(self, request: dict, timeout: float = 2.0) -> dict:
        """One control-socket request (see the module docstring); raises SimulatorError when it
        is refused or unanswered."""
        reply = control_request(self.control_path, request, timeout)
        if not reply.get("ok"):
            raise SimulatorError(f"ur simulator on {self.host}: {request.get('cmd')}: {reply.get('error')}")
        return reply

    def state(self) -> dict:
        return self.control({"cmd": "state"})

    def inject_stop(self, kind: str = "protective", cause: str = "") -> None:
        self.control({"cmd": "stop", "kind": kind, **({"cause": cause} if cause else {})})

    def release(self, kind: str = "safeguard") -> None:
        self.control({"cmd": "release", "kind": kind})

    def link_loss(self, duration_s: float, ports: tuple[str, ...] = ("rtde",)) -> None:
        self.control({"cmd": "link_loss", "duration_s": duration_s, "ports": list(ports)})

    def restart(self, duration_s: float = 1.0) -> None:
        self.control({"cmd": "restart", "duration_s": duration_s})

    def set_speed_slider(self, fraction: float) -> None:
        self.control({"cmd": "speed_slider", "fraction": fraction})
