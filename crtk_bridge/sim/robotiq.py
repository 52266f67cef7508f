"""Simulated Robotiq 2F-85 / 2F-140 gripper answering Modbus RTU (``crtk-sim robotiq``).

The gripper's registers and codes are the backend's tables (``backends/robotiq/tables.py``, from
Robotiq's manual); frames are decoded and built with pymodbus's RTU framer and PDUs (its server
side's decoder), the gripper's behaviour is this module's:

* the output words 0x03E8.. (action request, position request, speed, force) are written with
  function 16 (also 6, and 23 read / write); the input words 0x07D0.. (status, fault, position
  request echo, position, finger current) read with function 4 (also 3). A request it does not
  take (another slave id, another address) gets no reply, as the gripper sends no exception
  responses (manual 4.7.1).
* activation: rACT 0 -> 1 starts it (gSTA 1) for ``activation_s`` seconds, during which the
  fingers run to full opening, to full closing and back to full opening (the stroke ends are
  ``open_count`` and ``closed_count``); then gSTA 3. rACT 0 resets (gACT 0, gSTA 0, faults
  cleared). An object between the fingers during activation stops them: activation fault (0x0D).
* motion: with rGTO 1 the fingers move towards the position request at the speed setting
  (tables.Model, linear between the model's extremes); gOBJ 0 while moving, 3 at the request. An
  object at ``object_at`` m of opening stops closing fingers there: gOBJ 2, and the finger
  current follows the force setting (force / ``effort_per_amp`` A, 10 mA per unit). rGTO 0: the
  fingers stop where they are and the current drops (this simulator keeps no grip force then).
* faults injected on the control socket: ``overcurrent`` (gFLT 0x0E) and ``under_voltage``
  (0x0A) are major faults (the fingers stop until a reset, rACT 0 -> 1); ``no_communication``
  silences the gripper (it hears and answers nothing) until cleared, and when it hears again
  after a gap of a second or more it reports the minor fault 0x09 once, as the gripper does;
  ``unplug`` takes the link away (the pty closes, the TCP connections drop).

It serves the same gripper on a pty (a USB-RS485 adapter: ``link``) and / or on a TCP socket
carrying the raw RTU bytes (``tcp=(host, port)``: a UR tool flange's port 54321), one session
per connection; :meth:`RobotiqSimulator.session` gives a byte-stream session for any other
carrier (a UR controller simulator forwarding its tool port). Time runs lazily: the state is
advanced to now whenever a request or a control command arrives.

Control socket (JSON lines, sim/control.py): ``dump``; ``read`` / ``write`` {register}
(``Goal_Position`` = rPR, ``Present_Position`` = gPO, ``Torque_Enable`` = gGTO, ``gSTA``,
``gOBJ``, ``gFLT``, ``gCU``, ``rACT``, ``rGTO``, ``rSP``, ``rFR``); ``object`` {at: m | null};
``fault`` {kind: overcurrent | under_voltage | no_communication}; ``clear_faults``; ``unplug``
{on}; ``activation`` {seconds} (also ``torque_delay``).
"""

from __future__ import annotations

import enum
import logging
import os
import selectors
import socket
import threading
import time
from pathlib import Path
from typing import Any

from pymodbus.framer import FramerRTU
from pymodbus.pdu import DecodePDU
from pymodbus.pdu.register_message import (
    ReadHoldingRegistersResponse,
    ReadInputRegistersResponse,
    ReadWriteMultipleRegistersResponse,
    WriteMultipleRegistersResponse,
    WriteSingleRegisterResponse,
)

from ..backends.robotiq import tables as T
from ..profile import Profile
from . import SimulatorError
from .control import ControlServer
from .pty import PtyPort

log = logging.getLogger(__name__)

#: the UR tool flange's RS-485 as a TCP socket (the tool communication URCap's port)
TOOL_PORT = 54321
#: seconds an activation takes here unless told (a real 2F takes a few; tests ask for less)
DEFAULT_ACTIVATION_S = 1.0
#: the simulated gripper's readings at its stroke ends: the backend's nominal ends (tables.py; a
#: choice, not the manual's: its example reads 13/255 at full opening, "the fingers have reached
#: their software limit")
OPEN_COUNT, CLOSED_COUNT = T.NOMINAL_OPEN, T.NOMINAL_CLOSED
#: finger current while moving (the manual's example reads 0x0A, about 100 mA, during motion)
MOVING_CURRENT = 10
#: N of grip force per A of finger current when the profile gives none (not from the manual)
DEFAULT_N_PER_A = 400.0
#: the fault kinds the control socket injects (tests/conftest.py reads FaultKind)
FAULT_CODES = {"overcurrent": T.GFLT_OVERCURRENT, "under_voltage": T.GFLT_UNDER_VOLTAGE}
SILENCE_KINDS = ("no_communication", "silent")
INPUT_WORDS = 8  # bytes 0-15 of the input registers (6-15 reserved, read as zero)


class FaultKind(str, enum.Enum):
    """What the control socket's ``fault`` injects (the e2e suite's ``fault:<kind>`` capability)."""

    overcurrent = "overcurrent"
    under_voltage = "under_voltage"
    no_communication = "no_communication"


class Gripper:
    """The gripper's state and behaviour (thread-safe: one lock)."""

    def __init__(self, model: T.Model, *, slave_id: int = T.SLAVE_ID, activation_s: float = DEFAULT_ACTIVATION_S,
                 n_per_a: float = DEFAULT_N_PER_A, open_count: int = OPEN_COUNT, closed_count: int = CLOSED_COUNT,
                 activated: bool = False):
        self.model = model
        self.slave_id = slave_id
        self.activation_s = float(activation_s)
        self.n_per_a = float(n_per_a)
        self.open_count, self.closed_count = open_count, closed_count
        self.lock = threading.RLock()
        # robot output (what the master wrote): action, position request, speed, force
        self.action = self.rpr = self.rsp = self.rfr = 0
        # gripper state
        self.gact = False
        self.gsta = T.GSTA_RESET
        self.gobj = T.GOBJ_MOVING
        self.fault = T.GFLT_NONE
        self.pos = float(open_count)
        self.current = 0
        self.object_at: float | None = None  # m of opening where an object is, None: none
        self.silent = False
        self._act_t0 = 0.0
        self._act_from = float(open_count)
        self._act_read: set[str] = set()  # the stroke ends a master read during this activation
        self._act_k = 0.0  # how far the activation's course is (0..1)
        self._t = time.monotonic()
        self._last_heard = time.monotonic()
        self.requests = 0  # requests answered
        if activated:  # activated earlier (a gripper keeps its activation while powered)
            self.action, self.gact, self.gsta, self.gobj = T.RACT, True, T.GSTA_ACTIVE, T.GOBJ_AT_REQUEST

    # ---------------------------------------------------------------- time
    def advance(self, now: float | None = None) -> None:
        with self.lock:
            now = time.monotonic() if now is None else now
            dt, self._t = max(0.0, now - self._t), now
            if T.FAULTS.get(self.fault) is not None and T.FAULTS[self.fault].major:
                self.current = 0
                return
            if not self.gact:
                return
            if self.gsta == T.GSTA_ACTIVATING:
                self._activation(now)
            elif self.gsta == T.GSTA_ACTIVE:
                if self.action & T.RGTO:
                    self._move(dt)
                else:
                    self.current = 0

    def _object_count(self) -> float | None:
        if self.object_at is None:
            return None
        m = self.model
        return self.closed_count - self.object_at / m.stroke_m * (self.closed_count - self.open_count)

    #: the activation's course: (fraction of ``activation_s`` at which each leg ends, where to)
    #: to full opening, a pause, to full closing, a pause, back to full opening, a pause
    _COURSE = ((0.2, "open"), (0.3, "open"), (0.55, "closed"), (0.65, "closed"), (0.9, "open"), (1.0, "open"))

    #: the pauses at the stroke's ends: (where the pause ends, which end)
    _PAUSES = ((0.3, "open"), (0.65, "closed"))

    def _activation(self, now: float) -> None:
        """Open, close, open again over ``activation_s`` (pausing at each end: the readings there
        are the stroke's ends); an object between the fingers stops it: activation fault 0x0D.
        A pause lasts until a master has read the position there at least once (a short
        simulated activation on a loaded PC: the master's reads may be further apart than the
        pause; a real gripper's activation takes seconds)."""
        span = max(self.activation_s, 1e-3)
        k = (now - self._act_t0) / span
        for end, where in self._PAUSES:
            if k > end and where not in self._act_read:
                self._act_t0 += (k - end) * span  # the clock of the activation waits
                k = end
                break
        self._act_k = k
        ends = {"open": float(self.open_count), "closed": float(self.closed_count)}
        if k >= 1.0:
            self.pos, self.gsta, self.current = ends["open"], T.GSTA_ACTIVE, 0
            self.gobj = T.GOBJ_AT_REQUEST
            return
        start, frm = 0.0, self._act_from
        for end, where in self._COURSE:
            if k < end:
                to = ends[where]
                pos = frm + (to - frm) * (k - start) / (end - start)
                break
            start, frm = end, ends[where]
        obj = self._object_count()
        if obj is not None and pos >= obj:
            self.pos, self.fault, self.gsta, self.current = obj, T.GFLT_ACTIVATION, T.GSTA_RESET, 0
            return
        self.pos, self.current = pos, MOVING_CURRENT

    def _move(self, dt: float) -> None:
        m = self.model
        target = float(min(max(self.rpr, self.open_count), self.closed_count))
        speed = m.speed_min + (m.speed_max - m.speed_min) * self.rsp / 255.0  # m/s
        step = speed / m.stroke_m * (self.closed_count - self.open_count) * dt
        obj = self._object_count()
        pos = self.pos
        if obj is not None and target > pos - 1e-9 and pos <= obj + 1e-9 and target >= obj:
            # closing towards an object: it stops the fingers there
            if pos + step >= obj:
                self.pos, self.gobj = obj, T.GOBJ_CONTACT_CLOSING
                force = m.force_min + (m.force_max - m.force_min) * self.rfr / 255.0
                self.current = min(255, round(force / self.n_per_a / T.CURRENT_A_PER_UNIT))
                return
            self.pos, self.gobj, self.current = pos + step, T.GOBJ_MOVING, MOVING_CURRENT
            return
        if abs(target - pos) <= step:
            self.pos, self.gobj, self.current = target, T.GOBJ_AT_REQUEST, 0
        else:
            self.pos = pos + step if target > pos else pos - step
            self.gobj, self.current = T.GOBJ_MOVING, MOVING_CURRENT

    # ---------------------------------------------------------------- registers
    def output_words(self) -> list[int]:
        return T.pack_output(self.action, self.rpr, self.rsp, self.rfr)

    def input_words(self) -> list[int]:
        with self.lock:
            if self.gsta == T.GSTA_ACTIVATING:  # a master read an end of the stroke (see _activation)
                if round(self.pos) == self.open_count and self._act_k >= self._COURSE[0][0]:
                    self._act_read.add("open")
                elif round(self.pos) == self.closed_count:
                    self._act_read.add("closed")
            status = T.status_byte(self.gact, bool(self.action & T.RGTO) and self.gact, self.gsta, self.gobj)
            words = T.pack_input(status, self.fault, self.rpr, round(self.pos), self.current)
        return words + [0] * (INPUT_WORDS - len(words))

    def write_output(self, offset: int, values: list[int]) -> bool:
        """Words written from 0x03E8 + ``offset``; False when outside the output block."""
        words = self.output_words() + [0] * 5
        if offset < 0 or offset + len(values) > INPUT_WORDS:
            return False
        words[offset:offset + len(values)] = values
        action, rpr, rsp, rfr = T.unpack_output(words[:T.WORDS])
        with self.lock:
            self.advance()
            was = self.action
            self.action, self.rpr, self.rsp, self.rfr = action, rpr, rsp, rfr
            if not action & T.RACT:  # reset: every fault cleared
                self.gact, self.gsta, self.gobj, self.fault, self.current = False, T.GSTA_RESET, T.GOBJ_MOVING, 0, 0
            elif not was & T.RACT or not self.gact:  # rising edge: activation
                if self.fault in T.FAULTS and T.FAULTS[self.fault].major:
                    pass  # a major fault needs the reset first
                else:
                    self.gact, self.gsta, self.fault = True, T.GSTA_ACTIVATING, 0
                    self._act_t0, self._act_from = time.monotonic(), self.pos
                    self._act_read, self._act_k = set(), 0.0
            elif action & T.RGTO and self.gsta == T.GSTA_ACTIVATING:
                self.fault = 0x05  # priority fault: the activation must complete first
            if action & T.RGTO and not action & T.RACT:
                self.fault = 0x07  # priority fault: the activation bit must be set first
        return True

    def heard(self) -> None:
        """A request for this gripper arrived: a gap of a second or more is the minor fault 0x09
        (reported in this reply, then gone)."""
        now = time.monotonic()
        with self.lock:
            if now - self._last_heard >= 1.0 and self.gact and self.fault == T.GFLT_NONE:
                self.fault = T.GFLT_NO_COMMUNICATION
            elif self.fault == T.GFLT_NO_COMMUNICATION:
                self.fault = T.GFLT_NONE
            self._last_heard = now

    # ---------------------------------------------------------------- faults and control
    def inject(self, kind: str) -> None:
        with self.lock:
            self.advance()
            if kind in SILENCE_KINDS:
                self.silent = True
            elif kind in FAULT_CODES:
                self.fault, self.current = FAULT_CODES[kind], 0
            else:
                raise SimulatorError(f"unknown fault kind {kind!r}; valid: {', '.join(k.value for k in FaultKind)}")

    def clear_faults(self) -> None:
        """The injected causes removed (silence ends); a major gFLT stays until a reset."""
        with self.lock:
            self.silent = False

    def dump(self) -> dict[str, Any]:
        with self.lock:
            self.advance()
            return {"slave_id": self.slave_id, "model": self.model.name, "rACT": int(bool(self.action & T.RACT)),
                    "rGTO": int(bool(self.action & T.RGTO)), "rPR": self.rpr, "rSP": self.rsp, "rFR": self.rfr,
                    "gACT": int(self.gact), "gGTO": int(bool(self.action & T.RGTO) and self.gact), "gSTA": self.gsta,
                    "gOBJ": self.gobj, "gFLT": self.fault, "gPO": round(self.pos), "gCU": self.current,
                    "position": self.pos, "object_at": self.object_at, "silent": self.silent,
                    "activation_s": self.activation_s, "open_count": self.open_count,
                    "closed_count": self.closed_count, "requests": self.requests}

    REGISTERS = {"Goal_Position": "rPR", "Present_Position": "gPO", "Torque_Enable": "gGTO"}

    def read(self, register: str) -> int:
        name = self.REGISTERS.get(register, register)
        value = self.dump().get(name)
        if not isinstance(value, int):
            raise SimulatorError(f"unknown register {register!r}")
        return value

    def write(self, register: str, value: int) -> None:
        name = self.REGISTERS.get(register, register)
        with self.lock:
            self.advance()
            if name == "gPO":  # a hand moves the fingers
                self.pos = float(min(max(value, 0), 255))
            elif name in ("rPR", "rSP", "rFR"):
                setattr(self, name.lower(), int(value) & 0xFF)
            else:
                raise SimulatorError(f"register {register!r} is not writable here")


class Session:
    """One byte stream to the gripper (a pty, a TCP connection): RTU frames in, replies out."""

    def __init__(self, gripper: Gripper):
        self.gripper = gripper
        self._buf = b""
        self._framer = FramerRTU(DecodePDU(True))

    def feed(self, data: bytes) -> bytes:
        """Take ``data``; -> the replies to every complete request in it (maybe b"")."""
        self._buf += data
        out = b""
        while self._buf:
            try:
                used, pdu = self._framer.handleFrame(self._buf, 0, 0)
            except Exception:  # a frame pymodbus cannot decode: dropped, as the gripper would
                used, pdu = len(self._buf), None
            if not used and pdu is None:
                break  # incomplete: wait for more
            self._buf = self._buf[used:]
            if pdu is None:
                continue
            reply = self._answer(pdu)
            if reply is not None:
                out += self._framer.buildFrame(reply)
        return out

    def _answer(self, pdu) -> Any:
        g = self.gripper
        if pdu.dev_id != g.slave_id or g.silent:
            return None
        g.heard()
        g.advance()
        g.requests += 1
        fc = pdu.function_code
        sid = g.slave_id
        if fc in (3, 4):
            regs = self._read(pdu.address, pdu.count)
            if regs is None:
                return None
            cls = ReadInputRegistersResponse if fc == 4 else ReadHoldingRegistersResponse
            return cls(registers=regs, dev_id=sid)
        if fc == 16:
            if not g.write_output(pdu.address - T.OUTPUT_ADDRESS, list(pdu.registers)):
                return None
            return WriteMultipleRegistersResponse(address=pdu.address, count=pdu.count, dev_id=sid)
        if fc == 6:
            if not g.write_output(pdu.address - T.OUTPUT_ADDRESS, [pdu.registers[0]] if pdu.registers else []):
                return None
            return WriteSingleRegisterResponse(address=pdu.address, registers=list(pdu.registers), dev_id=sid)
        if fc == 23:
            if not g.write_output(pdu.write_address - T.OUTPUT_ADDRESS, list(pdu.write_registers)):
                return None
            regs = self._read(pdu.read_address, pdu.read_count)
            if regs is None:
                return None
            return ReadWriteMultipleRegistersResponse(registers=regs, dev_id=sid)
        return None

    def _read(self, address: int, count: int) -> list[int] | None:
        g = self.gripper
        for base, words in ((T.INPUT_ADDRESS, g.input_words()), (T.OUTPUT_ADDRESS, g.output_words() + [0] * 5)):
            if base <= address and address + count <= base + INPUT_WORDS:
                return words[address - base:address - base + count]
        return None


class RobotiqSimulator:
    """A simulated 2F gripper on a pty (``link``) and / or a TCP socket (``tcp=(host, port)``)
    with a control socket (``control``). ``start()``, ``stop()``, ``running``, ``port`` (the
    endpoint a backend opens: the pty, else ``socket://host:port``), ``pty_path``, ``tcp_address``,
    ``control_path``; ``session()`` for another carrier; ``control(request)`` for the control
    socket's commands in process."""

    def __init__(self, model: str = "2f85", *, slave_id: int = T.SLAVE_ID, link: str | os.PathLike | None = None,
                 pty: bool | None = None, tcp: tuple[str, int] | None = None, control: str | os.PathLike | None = None,
                 activation_s: float = DEFAULT_ACTIVATION_S, baudrate: int = T.BAUDRATE,
                 n_per_a: float = DEFAULT_N_PER_A, activated: bool = False):
        if model not in T.MODELS:
            raise SimulatorError(f"robotiq simulator: model {model!r} unknown; valid: {', '.join(T.MODELS)}")
        self.gripper = Gripper(T.MODELS[model], slave_id=slave_id, activation_s=activation_s, n_per_a=n_per_a,
                               activated=activated)
        self.rx_bytes = 0  # bytes received from masters on every carrier
        self.baudrate = baudrate
        self.ids = [slave_id]
        use_pty = pty if pty is not None else (link is not None or tcp is None)
        self._pty = PtyPort(link, baudrate=baudrate) if use_pty else None
        self._tcp_want = tcp
        self.tcp_address: tuple[str, int] | None = None
        self.control_path = Path(control) if control is not None else None
        self._control: ControlServer | None = None
        self._listener: socket.socket | None = None
        self._sel: selectors.BaseSelector | None = None
        self._thread: threading.Thread | None = None
        self._stop = False
        self._wake_r = self._wake_w = -1
        self._pty_session: Session | None = None
        self._conns: dict[socket.socket, Session] = {}
        self._unplugged = False
        self._error: BaseException | None = None
        self._pending = None  # work for the serving thread (set_unplugged)

    @classmethod
    def from_profile(cls, profile: Profile, link: str | os.PathLike | None = None, control: str | os.PathLike | None = None,
                     host: str | None = None, *, tcp_port: int = TOOL_PORT, **kw) -> RobotiqSimulator:
        """The profile's one gripper joint (``model``, ``id``, ``effort_per_amp``); ``host``: serve
        its raw RTU bytes on TCP ``host:tcp_port`` (a UR tool flange) instead of a pty."""
        if len(profile.joints) != 1:
            raise SimulatorError(f"profile {profile.name!r}: a robotiq gripper is one joint, the profile has "
                                 f"{len(profile.joints)}")
        keys = profile.joints[0].backend
        model = keys.get("model", "2f85")
        sid = keys.get("id", T.SLAVE_ID)
        if not isinstance(sid, int) or isinstance(sid, bool) or not 0 <= sid <= 255:
            raise SimulatorError(f"profile {profile.name!r}: joints[0].id must be a slave id 0..255, got {sid!r}")
        n_per_a = keys.get("effort_per_amp") or DEFAULT_N_PER_A
        baud = (profile.backend or {}).get("baudrate", T.BAUDRATE)
        return cls(model, slave_id=sid, link=link, tcp=(host, tcp_port) if host else None, control=control,
                   baudrate=baud if isinstance(baud, int) else T.BAUDRATE, n_per_a=float(n_per_a), **kw)

    # ---------------------------------------------------------------- lifecycle
    @property
    def pty_path(self) -> str | None:
        return self._pty.path if self._pty is not None and self._pty.slave_path is not None else None

    @property
    def port(self) -> str:
        if self._pty is not None:
            return self._pty.path
        if self.tcp_address is not None:
            return f"socket://{self.tcp_address[0]}:{self.tcp_address[1]}"
        raise SimulatorError("robotiq simulator: not started")

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def session(self) -> Session:
        return Session(self.gripper)

    def start(self) -> None:
        if self._thread is not None:
            return
        self._sel = selectors.DefaultSelector()
        self._wake_r, self._wake_w = os.pipe()
        self._sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        try:
            if self._pty is not None:
                self._plug_pty()
            if self._tcp_want is not None:
                sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                try:
                    sock.bind(self._tcp_want)
                except OSError as exc:
                    sock.close()
                    raise SimulatorError(f"robotiq simulator: cannot listen on {self._tcp_want[0]}:{self._tcp_want[1]}: "
                                         f"{exc.strerror or exc}") from exc
                sock.listen(4)
                sock.setblocking(False)
                self._listener = sock
                self.tcp_address = sock.getsockname()[:2]
                self._sel.register(sock, selectors.EVENT_READ, "listen")
            if self.control_path is not None:
                self._control = ControlServer(self.control_path, self.control)
                self._control.start()
        except BaseException:
            self._teardown()
            raise
        self._stop = False
        self._thread = threading.Thread(target=self._run, name="sim-robotiq", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        if self._thread is None:
            return
        self._stop = True
        os.write(self._wake_w, b"x")
        self._thread.join(timeout=5)
        self._thread = None
        self._teardown()

    def _teardown(self) -> None:
        if self._control is not None:
            self._control.stop()
            self._control = None
        for conn in list(self._conns):
            conn.close()
        self._conns.clear()
        if self._listener is not None:
            self._listener.close()
            self._listener = None
        if self._pty is not None:
            self._pty.close()
        if self._sel is not None:
            self._sel.close()
            self._sel = None
        for fd in (self._wake_r, self._wake_w):
            if fd >= 0:
                os.close(fd)
        self._wake_r = self._wake_w = -1

    def __enter__(self) -> RobotiqSimulator:
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def _plug_pty(self) -> None:
        assert self._pty is not None
        if self._pty.master_fd is None:
            if self._pty.slave_path is None:
                self._pty.open()
            else:
                self._pty.plug()
        self._pty_session = Session(self.gripper)
        self._sel.register(self._pty.master_fd, selectors.EVENT_READ, "pty")

    # ---------------------------------------------------------------- serving
    def _run(self) -> None:
        try:
            while not self._stop:
                for key, _ in self._sel.select(timeout=0.5):
                    what = key.data
                    if what == "wake":
                        os.read(self._wake_r, 64)
                        pending, self._pending = self._pending, None
                        if pending is not None:
                            pending()
                    elif what == "pty":
                        self._serve_pty()
                    elif what == "listen":
                        self._accept()
                    else:
                        self._serve_conn(key.fileobj)
        except BaseException as exc:  # noqa: BLE001 - said, and `running` turns False
            self._error = exc
            log.exception("robotiq simulator thread died")

    def _serve_pty(self) -> None:
        fd = self._pty.master_fd
        try:
            data = os.read(fd, 4096)
        except BlockingIOError:
            return
        except OSError:
            return  # no client has the slave open (EIO): nothing to answer
        self.rx_bytes += len(data)
        reply = self._pty_session.feed(data)
        if reply:
            try:
                os.write(fd, reply)
            except OSError:
                pass

    def _accept(self) -> None:
        try:
            conn, _ = self._listener.accept()
        except OSError:
            return
        if self._unplugged:
            conn.close()
            return
        conn.setblocking(True)
        conn.settimeout(1.0)
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._conns[conn] = Session(self.gripper)
        self._sel.register(conn, selectors.EVENT_READ, "conn")

    def _serve_conn(self, conn: socket.socket) -> None:
        try:
            data = conn.recv(4096)
        except OSError:
            data = b""
        if not data:
            self._drop(conn)
            return
        self.rx_bytes += len(data)
        reply = self._conns[conn].feed(data)
        if reply:
            try:
                conn.sendall(reply)
            except OSError:
                self._drop(conn)

    def _drop(self, conn: socket.socket) -> None:
        try:
            self._sel.unregister(conn)
        except (KeyError, ValueError):
            pass
        self._conns.pop(conn, None)
        conn.close()

    # ---------------------------------------------------------------- control
    def set_object(self, at: float | None) -> None:
        """An object at ``at`` m of opening between the fingers (None: none)."""
        with self.gripper.lock:
            self.gripper.advance()
            self.gripper.object_at = None if at is None else float(at)

    def set_fault(self, device_id: int | None, kind: str, code: int = 0) -> None:
        self.gripper.inject(kind)

    def clear_faults(self) -> None:
        self.gripper.clear_faults()

    def set_torque_delay(self, seconds: float) -> None:
        self.set_activation_s(seconds)

    def set_activation_s(self, seconds: float) -> None:
        self.gripper.activation_s = max(0.0, float(seconds))

    def set_unplugged(self, on: bool) -> None:
        """The adapter (or the tool cable) pulled out / plugged back."""
        self._call_in_thread(lambda: self._unplug(on))

    def _unplug(self, on: bool) -> None:
        self._unplugged = bool(on)
        if on:
            if self._pty is not None and self._pty.master_fd is not None:
                try:
                    self._sel.unregister(self._pty.master_fd)
                except (KeyError, ValueError):
                    pass
                self._pty.unplug()
            for conn in list(self._conns):
                self._drop(conn)
        elif self._pty is not None and self._pty.master_fd is None:  # plugged back (a no-op if in)
            self._plug_pty()

    def _call_in_thread(self, fn) -> None:
        """Run ``fn`` where it cannot race the serving thread's use of the fds: now when not
        serving, else between two selects (the selector and fds are the thread's)."""
        if not self.running:
            fn()
            return
        done = threading.Event()
        box: dict[str, BaseException] = {}

        def run() -> None:
            try:
                fn()
            except BaseException as exc:  # noqa: BLE001
                box["exc"] = exc
            finally:
                done.set()

        self._pending = run  # the serving thread runs it on the wake-up
        os.write(self._wake_w, b"c")
        if not done.wait(5):
            raise SimulatorError("robotiq simulator: the serving thread did not answer")
        if "exc" in box:
            raise box["exc"]

    def control(self, request: dict) -> dict:
        """One control-socket request (module docstring) -> its reply."""
        cmd = request.get("cmd")
        g = self.gripper
        try:
            if cmd == "dump":
                d = g.dump()
                return {"ok": True, **d, "servos": {str(g.slave_id): d}}
            if cmd == "read":
                return {"ok": True, "value": g.read(str(request.get("register")))}
            if cmd == "write":
                g.write(str(request.get("register")), int(request.get("value", 0)))
                return {"ok": True}
            if cmd == "object":
                at = request.get("at")
                self.set_object(None if at is None else float(at))
                return {"ok": True}
            if cmd == "fault":
                g.inject(str(request.get("kind")))
                return {"ok": True}
            if cmd == "clear_faults":
                g.clear_faults()
                return {"ok": True}
            if cmd == "unplug":
                self.set_unplugged(bool(request.get("on", True)))
                return {"ok": True}
            if cmd in ("activation", "torque_delay"):
                self.set_activation_s(float(request.get("seconds", DEFAULT_ACTIVATION_S)))
                return {"ok": True}
        except (SimulatorError, ValueError, TypeError) as exc:
            return {"ok": False, "error": str(exc)}
        return {"ok": False, "error": f"unknown command {cmd!r}; valid: dump, read, write, object, fault, "
                                      f"clear_faults, unplug, activation"}


__all__ = ["RobotiqSimulator", "Gripper", "Session", "FaultKind", "TOOL_PORT"]
