"""LeRobot's console scripts (``lerobot-record``, ``lerobot-replay``, ``lerobot-teleoperate``...)
started from one interpreter that imported LeRobot once: each run is a fork of it that calls the
script's entry point (the ``console_scripts`` entry the command line runs) with the run's argv,
working folder, environment additions and log file as its stdout / stderr. Importing LeRobot takes
5-15 s of CPU (torch, torchvision, datasets); the LeRobot tests run seven commands.

Run by the LeRobot venv's python (tests/lerobot/venv.py), with the plugin folder on PYTHONPATH and
HF_LEROBOT_HOME / HF_HUB_OFFLINE in its environment (what LeRobot reads at import). One JSON request
per line on stdin, one reply per line on stdout: ``{"op": "run", "command": "lerobot-record",
"args": [...], "log": path, "cwd": path, "env": {...}}`` -> ``{"ok": true, "pid": N}``;
``{"op": "poll", "pid": N}`` -> ``{"ok": true, "returncode": null | int}`` (negative: the signal).
Forks exit with the launcher (PR_SET_PDEATHSIG). This process never runs LeRobot code itself, so
no thread of LeRobot's exists when it forks.

Each command's argument parser (draccus) reads the help of every config field of every choice
class from its class's source (``inspect.getsource``: ~1500 parses of whole modules, 10-25 s of CPU
per command). The launcher memoizes that lookup (a pure function of the class and the field: the
sources do not change during a test session) and fills the memo once by building the three
commands' parsers (``--help``) before the first fork.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import importlib
import io
import json
import os
import signal
import sys
import traceback
from importlib.metadata import entry_points

PRELOAD = ("lerobot.scripts.lerobot_record", "lerobot.scripts.lerobot_replay", "lerobot.scripts.lerobot_teleoperate")
PR_SET_PDEATHSIG = 1


def _child(entry, req: dict) -> None:
    code = 1
    try:
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
        fd = os.open(req["log"], os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        os.dup2(fd, 1)
        os.dup2(fd, 2)
        os.close(fd)
        null = os.open(os.devnull, os.O_RDONLY)
        os.dup2(null, 0)
        os.close(null)
        sys.stdin = open(0, closefd=False)
        sys.stdout = open(1, "w", buffering=1, closefd=False)
        sys.stderr = open(2, "w", buffering=1, closefd=False)
        os.chdir(req["cwd"])
        os.environ.update(req.get("env", {}))
        sys.argv = [req["command"], *req["args"]]
        rc = entry.load()()
        code = rc if isinstance(rc, int) else 0
    except SystemExit as exc:
        if exc.code is None or isinstance(exc.code, int):
            code = exc.code or 0
        else:
            print(exc.code, file=sys.stderr)
            code = 1
    except BaseException:  # noqa: BLE001 - what the console script would print
        traceback.print_exc()
        code = 1
    finally:
        try:
            sys.stdout.flush()
            sys.stderr.flush()
        finally:
            os._exit(code)


def _warm_parsers() -> None:
    import draccus
    from draccus.wrappers import docstring

    docstring.get_attribute_docstring = functools.lru_cache(maxsize=None)(docstring.get_attribute_docstring)
    from lerobot.scripts.lerobot_record import RecordConfig
    from lerobot.scripts.lerobot_replay import ReplayConfig
    from lerobot.scripts.lerobot_teleoperate import TeleoperateConfig

    for config in (RecordConfig, ReplayConfig, TeleoperateConfig):
        with contextlib.redirect_stdout(io.StringIO()), contextlib.suppress(SystemExit):
            draccus.parse(config_class=config, args=["--help"])


def main() -> int:
    for m in PRELOAD:
        importlib.import_module(m)
    _warm_parsers()
    scripts = {ep.name: ep for ep in entry_points(group="console_scripts")}
    out = sys.stdout
    sys.stdout = sys.stderr
    out.write(json.dumps({"ok": True, "ready": True}) + "\n")
    out.flush()
    for line in sys.stdin:
        if not line.strip():
            continue
        req = json.loads(line)
        try:
            if req["op"] == "run":
                entry = scripts[req["command"]]
                out.flush()
                sys.stderr.flush()
                pid = os.fork()
                if pid == 0:
                    _child(entry, req)
                reply = {"pid": pid}
            elif req["op"] == "poll":
                pid, status = os.waitpid(req["pid"], os.WNOHANG)
                reply = {"returncode": None if pid == 0 else os.waitstatus_to_exitcode(status)}
            else:
                raise ValueError(f"unknown op {req['op']!r}")
            out.write(json.dumps({"ok": True, **reply}) + "\n")
        except Exception as exc:  # noqa: BLE001 - reported to the test, which fails naming it
            traceback.print_exc()
            out.write(json.dumps({"ok": False, "error": f"{type(exc).__name__}: {exc}"}) + "\n")
        out.flush()
    return 0


if __name__ == "__main__":
    main()
    os._exit(0)  # end of input: nothing to clean up, and a torch interpreter's teardown takes seconds
