"""``crtk-ctl calibrate``: guide a calibration by hand, or import a LeRobot calibration file.

By hand (daemon running, robot DISABLED; docs/calibration.md): move every joint to the middle of
its range and press Enter; sweep every joint through its whole range while a bar per joint shows
the range seen so far; close the gripper and press Enter. The daemon's backend turns what it saw
into each joint's calibration keys (raw ticks never leave it); this tool writes them into the
profile, keeping its comments (``crtk_bridge.profile_write``), and the daemon uses them after a
restart.

The prompts read lines from standard input, so a script (or a test) drives it by writing newlines;
the bars redraw in place on a terminal (plain ANSI cursor-up, no curses) and print as blocks of
lines otherwise.
"""

from __future__ import annotations

import json
import math
import os
import select
import time
from pathlib import Path
from typing import Any, Callable, TextIO

from ..errors import CommandError, CrtkBridgeError
from ..profile import joint_bus_id, load_profile
from ..profile_write import write_calibration

BAR_WIDTH = 41  # characters for one turn of a joint, the middle pose at the centre
POLL_S = 0.1  # how often the bars are refreshed
PLAIN_EVERY_S = 1.0  # without a terminal: a block of bars at most this often, when they changed


class CalibrationAborted(CrtkBridgeError):
    """The user (or the end of the script) ended the procedure before it finished."""


def gripper_joints(info: dict) -> list[str]:
    """Joints of the namespaces named ``.../gripper`` (the project's convention for a gripper)."""
    return [j for ns in info.get("namespaces", []) if ns["name"].rsplit("/", 1)[-1] == "gripper"
            for j in ns["joints"]]


def bar(lo: float, hi: float, now: float, width: int = BAR_WIDTH) -> str:
    """One joint's bar: a whole turn (-pi..pi from the middle pose) across ``width`` cells, the
    range seen as ``=``, the middle pose ``|``, where the joint is now ``#``."""
    def cell(rad: float) -> int:
        return max(0, min(width - 1, int(round((rad + math.pi) / (2 * math.pi) * (width - 1)))))

    cells = ["."] * width
    for k in range(cell(lo), cell(hi) + 1):
        cells[k] = "="
    cells[width // 2] = "|"
    cells[cell(now)] = "#"
    return "[" + "".join(cells) + "]"


def bar_lines(seen: dict[str, list[float]]) -> list[str]:
    w = max((len(n) for n in seen), default=0)
    return [f"  {name:<{w}} {bar(lo, hi, now)} {math.degrees(lo):+7.1f} .. {math.degrees(hi):+7.1f} deg"
            for name, (lo, hi, now) in seen.items()]


class Prompter:
    """Lines from ``fd`` (standard input): :meth:`wait_enter` blocks for one; :meth:`entered`
    polls for one while the caller keeps drawing. End of input aborts the procedure."""

    def __init__(self, fd: int, out: TextIO):
        self.fd = fd
        self.out = out
        self._buf = b""

    def _line(self, timeout: float | None) -> bool:
        while b"\n" not in self._buf:
            ready, _, _ = select.select([self.fd], [], [], timeout)
            if not ready:
                return False
            chunk = os.read(self.fd, 4096)
            if not chunk:
                raise CalibrationAborted("calibrate: input ended before the procedure finished; nothing written")
            self._buf += chunk
        self._buf = self._buf.split(b"\n", 1)[1]
        return True

    def wait_enter(self, text: str) -> None:
        print(text, file=self.out, flush=True)
        self._line(None)

    def entered(self, timeout: float) -> bool:
        return self._line(timeout)


def sweep(robot: Any, prompt: Prompter, out: TextIO, grippers: list[str],
          clock: Callable[[], float] = time.monotonic) -> dict[str, dict]:
    """The guided sweep against the daemon; returns the joints' calibration keys. A failure or
    Ctrl-C after it began cancels the daemon's sweep."""
    prompt.wait_enter("1/3  Move every joint by hand to the middle of its range (the middle pose), "
                      "then press Enter.")
    robot.calibrate("begin", timeout=10.0)
    try:
        print("2/3  Move every joint through its whole range, to both of its ends, one after the "
              "other; press Enter when done.", file=out, flush=True)
        tty = out.isatty()
        drawn = 0
        shown: list[str] = []
        last_plain = clock()
        while True:
            done = prompt.entered(POLL_S)
            lines = bar_lines(robot.calibrate("status")["seen"])
            if tty:
                if drawn:
                    out.write(f"\x1b[{drawn}A")
                out.write("".join(f"\r{line}\x1b[K\n" for line in lines))
                out.flush()
                drawn = len(lines)
            elif done or (lines != shown and clock() - last_plain >= PLAIN_EVERY_S):
                print("\n".join(lines), file=out, flush=True)
                shown, last_plain = lines, clock()
            if done:
                break
        if grippers:
            prompt.wait_enter(f"3/3  Close the gripper{'s' if len(grippers) > 1 else ''} fully "
                              f"({', '.join(grippers)}), then press Enter.")
        return robot.calibrate("end", grippers=grippers)["calibration"]
    except BaseException:
        try:
            robot.calibrate("cancel", timeout=2.0)
        except (CrtkBridgeError, OSError, TimeoutError):
            pass
        raise


def summary(calibration: dict[str, dict]) -> list[str]:
    w = max((len(n) for n in calibration), default=0)
    out = []
    for name, keys in calibration.items():
        extra = "".join(f"  {k} {v}" for k, v in keys.items() if k not in ("offset", "direction", "range"))
        out.append(f"  {name:<{w}}  offset {keys.get('offset')}  direction {keys.get('direction'):+d}  "
                   f"range {keys.get('range')}{extra}")
    return out


def profile_mismatch(info: dict, profile_path: Path) -> str | None:
    """Why the profile at ``profile_path`` is not the daemon's robot (``info``: its ``list``
    reply), naming the first difference: robot name, backend, a joint, or a joint's bus id;
    None when they agree. Raises ProfileError when the profile does not load."""
    profile = load_profile(profile_path)
    where = f"--profile {profile_path}"
    if profile.name != info.get("robot"):
        return f"{where} is robot {profile.name!r}, the daemon serves {info.get('robot')!r}"
    if profile.backend_type != info.get("backend"):
        return f"{where} has backend {profile.backend_type!r}, the daemon's robot {info.get('backend')!r}"
    ours = {j.name: joint_bus_id(j) for j in profile.joints}
    namespaces = info.get("namespaces", [])
    has_ids = all("ids" in ns for ns in namespaces)  # a daemon older than the ids says none
    theirs: dict[str, Any] = {}
    for ns in namespaces:
        theirs.update(zip(ns.get("joints", []), ns.get("ids") or [None] * len(ns.get("joints", []))))
    for name in theirs:
        if name not in ours:
            return f"{where} has no joint {name!r}, a joint of the daemon's robot"
    for name, bus_id in ours.items():
        if name not in theirs:
            return f"{where} has a joint {name!r} the daemon's robot does not have"
        if has_ids and bus_id != theirs[name]:
            return f"{where}: joint {name!r} has id {bus_id}, on the daemon's robot id {theirs[name]}"
    return None


def run(robot: Any, profile: str, grippers: list[str] | None, import_path: str | None,
        stdin_fd: int, out: TextIO) -> int:
    """``crtk-ctl calibrate``. Returns the exit status; raises CommandError (the daemon refused),
    ProfileError (the profile could not be written), CalibrationAborted, Failure-like errors."""
    info = robot.list()
    if grippers is None:
        grippers = gripper_joints(info)
    profile_path = Path(profile)
    if not profile_path.is_file():
        raise CrtkBridgeError(f"calibrate: --profile {profile}: no such file (the daemon's profile, to write into)")
    mismatch = profile_mismatch(info, profile_path)  # never write one robot's calibration into another's
    if mismatch is not None:
        raise CrtkBridgeError(f"calibrate: {mismatch}: give the profile the daemon runs (or a copy of it)")
    if import_path is not None:
        try:
            data = json.loads(Path(import_path).read_text())
        except (OSError, ValueError) as exc:
            raise CrtkBridgeError(f"calibrate: --import {import_path}: not a readable JSON file: {exc}") from exc
        calibration = robot.calibrate("import", format="lerobot", file=data, grippers=grippers)["calibration"]
        print(f"Imported {import_path} (LeRobot calibration; docs/calibration.md says what maps and what is lost):",
              file=out)
    else:
        state = robot.connection.operating_state or {}
        if state.get("state") not in (None, "DISABLED"):
            raise CommandError("invalid_state", f"{robot.name}: calibrate needs the robot DISABLED (it is "
                                                f"{state.get('state')}): the joints are moved by hand with torque "
                                                f"off; disable it first (crtk-ctl disable)")
        calibration = sweep(robot, Prompter(stdin_fd, out), out, grippers)
        print("Calibration:", file=out)
    print("\n".join(summary(calibration)), file=out)
    written = write_calibration(profile_path, calibration)
    print(f"Wrote {written}. Restart the daemon to use it (e.g. systemctl restart crtk-bridge@{robot.name}).",
          file=out, flush=True)
    return 0
