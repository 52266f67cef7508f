"""``crtk-bridge setup-servos``: give each joint's servo its id and the profile's baud rate, one
servo at a time, as ``lerobot-setup-motors`` does (new servos all ship with id 1, so they can only
be told apart alone on the bus).

For each joint, in reverse profile order (as LeRobot: the joint with id 1 comes last, so a servo
still at the factory id 1 is never taken for an already set-up one), the user connects only that
joint's servo. Then:

1. find it: one broadcast ping per baud rate the servos support, the profile's rate first, then
   the factory rate, then the others, until something answers at some rate;
2. refuse when several servos answer there (or replies collide), or when only the servo set up
   just before is still there; refuse when its model number is not the joint's model;
3. torque off (a Dynamixel takes EEPROM writes only then), Feetech: Lock = 0 (so the writes
   persist); ID (unacknowledged: its status comes back under the new id), then a ping at the new
   id; Return_Delay_Time = ``backend.return_delay``; Baud_Rate last (unacknowledged: the servo
   switches at once), then the port switches and pings the new id at the new rate; Feetech: Lock =
   1; read back model, ID and Baud_Rate. The servo is reachable after every step.

Writes only to the one servo found; the daemon must not be running (the port is opened
exclusively). Everything here blocks (lifecycle / command-line code, never the control cycle).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

from ..errors import BackendError, CrtkBridgeError
from .serial_servo import COMM_SUCCESS, SerialServoBackend

EXIT_OK = 0  # every joint's servo set up and verified
EXIT_ERROR = 1  # the profile, the port, or a write / verification failed
EXIT_REFUSED = 3  # the servo found is of another model than the joint's
EXIT_TIMEOUT = 4  # --yes: no single new servo appeared within --timeout
EXIT_INTERRUPTED = 130  # Ctrl-C or end of input at a prompt


class SetupError(CrtkBridgeError):
    """A servo could not be set up (message names robot, joint, id, rate and register)."""


@dataclass
class _Look:
    """What one search of the bus found."""

    kind: str  # "none", "several", "previous", "one"
    baud: int = 0
    servos: dict[int, int] = field(default_factory=dict)  # id -> model number
    garbled: bool = False


class ServoSetup:
    """Sets up the servos of one serial bus's joints. ``emit(event)`` receives one dict per step
    (``event``: connect, waiting, found, configured, then one summary carrying ``exit_code`` and
    the ``error`` that stopped the run, if any); ``ask(prompt)``
    waits for the user (None: ``--yes``, poll until exactly one new servo answers or
    ``timeout_s`` passes)."""

    def __init__(self, backend: SerialServoBackend, emit: Callable[[dict], None],
                 ask: Callable[[str], object] | None, timeout_s: float = 60.0):
        self.b = backend
        self.emit = emit
        self.ask = ask
        self.timeout_s = timeout_s
        self._done: dict[int, str] = {}  # id set up in this run -> joint
        self._results: list[dict] = []
        cfg = backend.config
        rates = [cfg.baudrate, backend.FACTORY_BAUD, *sorted(backend.SUPPORTED_BAUDS, reverse=True)]
        self.bauds = list(dict.fromkeys(b for b in rates if b in backend.SUPPORTED_BAUDS))

    # ------------------------------------------------------------------ the run
    def run(self, joints: list[int]) -> int:
        """Set up the servos of joints ``joints`` (indexes, in the order given). Returns an exit
        code (module constants) after emitting a summary."""
        b = self.b
        try:
            port, _ = b._open_port()
        except CrtkBridgeError as exc:
            return self._finish(EXIT_ERROR, str(exc), len(joints))
        try:
            for k, i in enumerate(joints):
                code, message = self._joint(k, len(joints), i)
                if code != EXIT_OK:
                    return self._finish(code, message, len(joints))
            return self._finish(EXIT_OK, None, len(joints))
        except (KeyboardInterrupt, EOFError):
            return self._finish(EXIT_INTERRUPTED, "interrupted", len(joints))
        finally:
            port.closePort()
            b._port = None

    def _finish(self, code: int, message: str | None, total: int) -> int:
        event = {"event": "summary", "ok": code == EXIT_OK, "exit_code": code, "robot": self.b.robot,
                 "set_up": len(self._results), "of": total, "joints": self._results}
        if message:
            event["error"] = message
        self.emit(event)
        return code

    def _joint(self, k: int, total: int, i: int) -> tuple[int, str | None]:
        b = self.b
        name, j = b.joint_names[i], b.joint_keys[i]
        target, rate = b._ids[i], b.config.baudrate
        self.emit({"event": "connect", "index": k + 1, "of": total, "joint": name, "model": j.model,
                   "id": target, "baudrate": rate, "interactive": self.ask is not None})
        if self.ask is not None:
            self.ask(f"Connect ONLY the servo of joint {name!r} ({j.model}) to the bus, power it, then press "
                     f"Enter. ")
        deadline = time.monotonic() + self.timeout_s
        said = None
        while True:
            look = self._look()
            if look.kind == "one":
                break
            text = self._describe(look, name)
            if self.ask is not None:
                self.emit({"event": "waiting", "joint": name, "reason": look.kind, "message": text})
                self.ask("Fix it, then press Enter (Ctrl-C stops). ")
                continue
            if look.kind != said:
                said = look.kind
                self.emit({"event": "waiting", "joint": name, "reason": look.kind, "message": text})
            if time.monotonic() > deadline:
                return EXIT_TIMEOUT, (f"{b.robot}: joint {name!r}: no single new servo within "
                                      f"{self.timeout_s:g} s: {text}")
        (sid, number), = look.servos.items()
        expected = b.MODEL_NUMBERS[j.model]
        models = {v: m for m, v in b.MODEL_NUMBERS.items()}
        self.emit({"event": "found", "joint": name, "id": sid, "baudrate": look.baud, "model_number": number,
                   "model": models.get(number)})
        if number != expected:
            message = (f"{b.robot}: joint {name!r}: the servo found (id {sid} at {look.baud} baud) is model "
                       f"number {number} ({models.get(number) or 'unknown'}), the profile says {j.model} "
                       f"({expected}): connect the servo the profile names, or correct "
                       f"joints[{b.profile.joint_names.index(name)}] ({name}).model; nothing was written")
            return EXIT_REFUSED, message
        try:
            result = self._configure(i, sid, look.baud)
        except CrtkBridgeError as exc:
            return EXIT_ERROR, str(exc)
        self._done[target] = name
        self._results.append(result)
        self.emit({"event": "configured", **result})
        return EXIT_OK, None

    # ------------------------------------------------------------------ finding the one servo
    def _look(self) -> _Look:
        """One search: a broadcast ping per rate (``self.bauds`` order) until something answers."""
        port = self.b._port
        for baud in self.bauds:
            if not port.setBaudRate(baud):
                continue
            found, garbled = self.b._broadcast_ping()
            if not found and not garbled:
                continue
            if garbled or len(found) > 1:
                return _Look("several", baud, found, garbled)
            (sid, _), = found.items()
            if baud == self.b.config.baudrate and sid in self._done:
                return _Look("previous", baud, found)
            return _Look("one", baud, found)
        return _Look("none")

    def _describe(self, look: _Look, joint: str) -> str:
        if look.kind == "none":
            return (f"no servo answers at any rate ({', '.join(map(str, self.bauds))} baud): check that "
                    f"the servo of joint {joint!r} is connected and powered")
        if look.kind == "previous":
            sid = next(iter(look.servos))
            return (f"only the servo of joint {self._done[sid]!r} (id {sid}) answers: disconnect it and "
                    f"connect the servo of joint {joint!r}")
        ids = ", ".join(map(str, sorted(look.servos))) or "?"
        collide = "; their replies collide (several servos may share an id)" if look.garbled else ""
        return (f"{len(look.servos) or 'several'} servos answer at {look.baud} baud (ids {ids}){collide}: "
                f"connect ONLY the servo of joint {joint!r}")

    # ------------------------------------------------------------------ writing id and rate
    def _configure(self, i: int, sid: int, baud: int) -> dict:
        """Write id, Return_Delay_Time and baud rate (in that order, see the module docstring)
        to the servo found at (``sid``, ``baud``), then verify. Returns the result event."""
        b = self.b
        name, target, rate = b.joint_names[i], b._ids[i], b.config.baudrate
        where = f"{b.robot}: joint {name!r}: the servo found at id {sid}, {baud} baud"
        written = []
        try:
            b._write_register(i, "Torque_Enable", 0, sid=sid)
            b._unlock_eeprom(i, sid)
            if sid != target:
                if not b._write_unacknowledged(i, "ID", target, sid):
                    raise SetupError(f"{where}: writing ID = {target} failed on {b.port_name}")
                self._expect(i, target, f"{where}: did not answer as id {target} after ID = {target}")
                written.append("ID")
            b._write_register(i, "Return_Delay_Time", b.config.return_delay, sid=target)
            written.append("Return_Delay_Time")
            if baud != rate:
                if not b._write_unacknowledged(i, "Baud_Rate", b.BAUD_CODES[rate], target):
                    raise SetupError(f"{where}: writing Baud_Rate = {b.BAUD_CODES[rate]} failed")
                b._port.setBaudRate(rate)
                self._expect(i, target, f"{where}: did not answer at {rate} baud after Baud_Rate = "
                                        f"{b.BAUD_CODES[rate]} ({rate} baud)")
                written.append("Baud_Rate")
            b._lock_eeprom(i, target)
            got_id = b._read_register(i, "ID", sid=target)
            got_baud = b._read_register(i, "Baud_Rate", sid=target)
        except BackendError as exc:
            raise SetupError(f"{where}: {str(exc).removeprefix(f'{b.robot}: ')}") from exc
        if (got_id, got_baud) != (target, b.BAUD_CODES[rate]):
            raise SetupError(f"{where}: reads back ID {got_id}, Baud_Rate {got_baud} after the writes "
                             f"(expected {target}, {b.BAUD_CODES[rate]})")
        return {"joint": name, "id": target, "baudrate": rate, "from_id": sid, "from_baudrate": baud,
                "written": written, "verified": True}

    def _expect(self, i: int, sid: int, failure: str) -> None:
        """Ping ``sid`` (with the lifecycle retries) and check the model. Raises SetupError."""
        b = self.b
        model, result, _ = b._txrx(b._ph.ping, sid)
        if result != COMM_SUCCESS:
            raise SetupError(f"{failure}: {b._result_text(result)}")
        if model != b.MODEL_NUMBERS[b.joint_keys[i].model]:
            raise SetupError(f"{failure}: id {sid} is now model number {model}")
