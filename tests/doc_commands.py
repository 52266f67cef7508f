"""The documentation's commands, parsed and run as a user runs them (tests/test_docs.py).

Every fenced ``sh`` / ``bash`` / ``console`` block of README.md and docs/*.md is cut into
commands (one per logical line: ``\\`` continues a line, a trailing ``# ...`` is a note, a line
that is only a comment right after a command is the output the doc shows for it, as
docs/simulators.md's ``# crtk-sim: ... ready`` lines; in a ``console`` block ``$ `` lines are
commands and the lines below them their output); every ``python`` block is one command. A table
in the test (``SPEC``) says for each one how it runs: to completion, as a daemon the section's
other commands need, as a command that runs until Ctrl-C, or not at all (with the reason).

Commands run verbatim through ``bash -c`` in a :class:`DocEnv`: the console scripts of an install
(``bin_dir`` first on PATH; the test venv's by default, a non-editable install outside the clone
once the lead wires one in), a working folder outside the clone, ``$XDG_RUNTIME_DIR`` and
``$HOME`` in temporary folders (so ``crtk-ctl state`` finds the daemon that
``crtk-bridge --profile ...`` started at its default socket path, and ``~/...`` stays in the test).
The only rewriting is :attr:`DocEnv.subst`: fixed resources a parallel test run would also take
(Zenoh ports, ``/tmp/...`` paths, a UR simulator's 127.0.0.2) map to private ones.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

ROOT = Path(__file__).resolve().parent.parent
PYTHON_DRIVER = Path(__file__).resolve().parent / "doc_python.py"
SHELL_LANGS = ("sh", "bash", "console")
FENCE = re.compile(r"^```(\w*)[^\n]*\n(.*?)^```", re.S | re.M)
HEADING = re.compile(r"^#{1,6} +(.+?)\s*$", re.M)


@dataclass(frozen=True)
class Command:
    """One command of the documentation (a shell line, or a whole Python block)."""

    doc: str  # path relative to the repository, e.g. "docs/zenoh.md"
    line: int  # line of the doc where the command starts
    lang: str  # "sh" (sh, bash, console) or "python"
    heading: str  # the section it is in (the nearest heading above it)
    text: str  # what runs: the command without its trailing note, or the Python block
    note: str = ""  # the trailing "# ..." comment of a shell line
    output: tuple[str, ...] = ()  # output the doc shows for it

    @property
    def id(self) -> str:
        return f"{self.doc}:{self.line}"

    @property
    def key(self) -> tuple[str, str]:
        return (self.doc, self.text)


def split_comment(line: str) -> tuple[str, str]:
    """``cmd  # note`` -> (``cmd``, ``note``): a ``#`` that starts a word outside quotes."""
    quote = None
    for i, ch in enumerate(line):
        if quote:
            if ch == quote:
                quote = None
        elif ch in "'\"":
            quote = ch
        elif ch == "#" and (i == 0 or line[i - 1].isspace()):
            return line[:i].rstrip(), line[i + 1:].strip()
    return line.rstrip(), ""


def _shell_commands(doc: str, first_line: int, heading: str, body: str, console: bool) -> list[Command]:
    out: list[Command] = []
    lines = body.split("\n")
    i = 0
    while i < len(lines):
        raw, start = lines[i], first_line + i
        i += 1
        if console:
            if not raw.startswith("$ "):
                if out and raw.strip():
                    out[-1] = _with_output(out[-1], raw)
                continue
            raw = raw[2:]
        if not raw.strip():
            continue
        if raw.lstrip().startswith("#"):
            if out:  # a comment line right under a command: the output the doc shows for it
                out[-1] = _with_output(out[-1], raw.lstrip()[1:].strip())
            continue
        while raw.rstrip().endswith("\\") and i < len(lines):
            raw = raw.rstrip()[:-1].rstrip() + " " + lines[i].strip()
            i += 1
        text, note = split_comment(raw)
        out.append(Command(doc, start, "sh", heading, text.strip(), note))
    return out


def _with_output(cmd: Command, line: str) -> Command:
    return Command(cmd.doc, cmd.line, cmd.lang, cmd.heading, cmd.text, cmd.note, cmd.output + (line,))


def parse_doc(path: Path, root: Path = ROOT) -> list[Command]:
    """The commands of one markdown file, in order."""
    text = path.read_text()
    doc = str(path.relative_to(root))
    headings = [(m.start(), m.group(1)) for m in HEADING.finditer(text)]
    fences = [(m.start(), m.end()) for m in FENCE.finditer(text)]
    headings = [(pos, h) for pos, h in headings if not any(a <= pos < b for a, b in fences)]
    out: list[Command] = []
    for m in FENCE.finditer(text):
        lang, body = m.group(1), m.group(2)
        first_line = text.count("\n", 0, m.start()) + 2  # the line after the opening fence
        heading = next((h for pos, h in reversed(headings) if pos < m.start()), "")
        if lang in SHELL_LANGS:
            out += _shell_commands(doc, first_line, heading, body, console=lang == "console")
        elif lang == "python":
            out.append(Command(doc, first_line, "python", heading, body))
    return out


MESSAGE = re.compile(r"^(crtk-bridge|crtk-ctl|crtk-sim)( [\w-]+)?: ")


def parse_messages(path: Path, root: Path = ROOT) -> list[Command]:
    """The messages a doc quotes in unlabelled fences (``crtk-ctl: ...`` lines: what a command
    prints when it refuses), as Commands whose ``text`` is the message (tests/test_docs.py maps
    each to the command that prints it)."""
    text = path.read_text()
    doc = str(path.relative_to(root))
    headings = [(m.start(), m.group(1)) for m in HEADING.finditer(text)]
    out = []
    for m in FENCE.finditer(text):
        if m.group(1):
            continue
        first_line = text.count("\n", 0, m.start()) + 2
        heading = next((h for pos, h in reversed(headings) if pos < m.start()), "")
        for i, line in enumerate(m.group(2).split("\n")):
            if MESSAGE.match(line):
                out.append(Command(doc, first_line + i, "sh", heading, line.strip()))
    return out


def documented_output_pattern(line: str, subst: dict[str, str]) -> re.Pattern:
    """The regex a shown output line must match: verbatim (after :attr:`DocEnv.subst`), except
    what differs on every run (a pty's number)."""
    return re.compile(re.escape(apply_subst(line, subst)).replace(r"/dev/pts/7", r"/dev/pts/\d+"))


def ready_pattern(cmd: Command, how: How, env: DocEnv) -> str:
    """What a background command prints once it is up: ``how.ready``, else the first output line
    the doc shows for it."""
    if how.ready:
        return how.ready
    assert cmd.output, f"{cmd.id}: `{cmd.text}` runs in the background: SPEC must say what it prints once up"
    return documented_output_pattern(cmd.output[0], env.subst).pattern


def apply_subst(text: str, subst: dict[str, str]) -> str:
    for old, new in subst.items():
        text = text.replace(old, new)
    return text


@dataclass(frozen=True)
class How:
    """How one documented command is run (``SPEC`` in tests/test_docs.py).

    kind: ``run`` to completion, exit status ``rc``, stdout+stderr searched for each of ``out``
    (regexes); ``daemon``: started in the background when its ``scene`` is entered (the commands of
    that scene run while it serves), up once its output matches ``ready``; ``job``: a ``cmd &``
    line, started in the background when reached, up once its output matches ``ready``, serving
    until its scene ends; ``forever``: runs until Ctrl-C:
    up once its output matches ``ready``, then SIGINT, then exit status ``rc``; ``skip``: not run,
    ``why`` says why (hardware, sudo, a tool not installed); ``pending``: expected to fail until
    issue 18's ``item`` lands (xfail, strict: it flips when it passes).
    ``run`` replaces the verbatim text where ``why`` says why (README's ``pip install . &&``: the
    install under test is that install); ``setup`` prepares what the doc told the user to do in prose
    just before (``setup(env)``), ``after`` checks what the command left (``after(env)``);
    ``trigger``: a command run (again, until ``ready``) while a ``forever`` one waits for something
    to print (``crtk-ctl events``: an event); ``start``: daemons of a scene start by ascending
    ``start``, then in doc order (a router before the daemons joining it)."""

    kind: str = "run"
    scene: str = "none"
    rc: int = 0
    out: tuple[str, ...] = ()
    ready: str = ""
    why: str = ""
    item: str = ""
    run: str | None = None
    setup: Callable | None = None
    after: Callable | None = None
    trigger: str = ""
    start: int = 0
    timeout: float = 60.0


@dataclass
class DocEnv:
    """Where and with what the documented commands run.

    bin_dir: the install's console scripts (and its ``python``); cwd: the folder commands run in
    (outside the clone; a fresh one per scene, :meth:`folder`); profile_cwd: where a command naming
    a repository path (``profiles/...``) runs, ``None``: ``cwd`` too (the install resolves
    ``profiles/NAME.yaml`` from any folder), else e.g. the clone; home, runtime: ``$HOME`` and
    ``$XDG_RUNTIME_DIR``; subst: fixed resources mapped to private ones."""

    bin_dir: Path
    cwd: Path
    profile_cwd: Path | None
    home: Path
    runtime: Path
    subst: dict[str, str] = field(default_factory=dict)

    @classmethod
    def create(cls, tmp: Path, bin_dir: Path | None = None, profile_cwd: Path | None = None,
               subst: dict[str, str] | None = None) -> DocEnv:
        cwd, home, runtime = tmp / "work", tmp / "home", tmp / "run"
        for d in (cwd, home, runtime):
            d.mkdir(parents=True, exist_ok=True)
        runtime.chmod(0o700)
        return cls(bin_dir=bin_dir or Path(sys.executable).parent, cwd=cwd,
                   profile_cwd=profile_cwd, home=home, runtime=runtime, subst=dict(subst or {}))

    def folder(self, name: str) -> Path:
        """Run from here on in a fresh folder ``name`` beside the first one (each scene is a user
        starting afresh: README's ``init-profile ... my_arm.yaml`` meets no file of another section)."""
        self.cwd = self.cwd.parent / name
        self.cwd.mkdir(exist_ok=True)
        return self.cwd

    def environ(self) -> dict[str, str]:
        env = {k: v for k, v in os.environ.items()
               if not k.startswith(("PYTEST", "COV_", "VIRTUAL_ENV")) and k != "PYTHONPATH"}
        env.update(PATH=f"{self.bin_dir}{os.pathsep}{env.get('PATH', '/usr/bin:/bin')}", HOME=str(self.home),
                   XDG_RUNTIME_DIR=str(self.runtime), PYTHONUNBUFFERED="1")
        return env

    def where(self, text: str) -> Path:
        if self.profile_cwd is not None and re.search(r"(^|[\s=])profiles/", text):
            return self.profile_cwd
        return self.cwd

    def argv(self, cmd: Command, text: str, stay: bool = False) -> list[str]:
        if cmd.lang == "python":
            script = self.cwd / f"doc-{Path(cmd.doc).stem}-{cmd.line}.py"
            script.write_text(text)
            return [str(self.bin_dir / "python"), str(PYTHON_DRIVER), str(script)] + (["--stay"] if stay else [])
        return ["bash", "-c", ("exec " if stay else "") + text]

    def text(self, cmd: Command, how: How) -> str:
        text = apply_subst(how.run if how.run is not None else cmd.text, self.subst)
        if how.kind in ("daemon", "job") and cmd.lang == "sh" and text.endswith("&"):
            text = text[:-1].rstrip()  # `cmd &`: a job in the background, as Background runs it
        return text


@dataclass
class Result:
    rc: int
    output: str


def run_to_end(env: DocEnv, cmd: Command, how: How) -> Result:
    text = env.text(cmd, how)
    p = subprocess.run(env.argv(cmd, text), cwd=env.where(text), env=env.environ(), stdin=subprocess.DEVNULL,
                       stdout=subprocess.PIPE, stderr=subprocess.STDOUT, timeout=how.timeout)
    return Result(p.returncode, p.stdout.decode(errors="replace"))


class Background:
    """A documented command running in the background (its own process group, as a terminal
    job), its output in a log file."""

    def __init__(self, env: DocEnv, cmd: Command, how: How, log: Path):
        self.cmd, self.how, self.log_path = cmd, how, log
        text = env.text(cmd, how)
        self._log = open(log, "wb")
        self.proc = subprocess.Popen(env.argv(cmd, text, stay=True), cwd=env.where(text), env=env.environ(),
                                     stdin=subprocess.DEVNULL, stdout=self._log, stderr=subprocess.STDOUT,
                                     start_new_session=True)

    def output(self) -> str:
        return self.log_path.read_text(errors="replace")  # the child writes the file directly

    def wait_ready(self, pattern: str, timeout: float = 30.0) -> re.Match:
        """Until the output matches ``pattern``; AssertionError naming the command, with its
        output, when it exits first or ``timeout`` passes."""
        rx = re.compile(pattern, re.M)
        deadline = time.monotonic() + timeout
        while True:
            m = rx.search(self.output())
            if m:
                return m
            if self.proc.poll() is not None:
                raise AssertionError(f"{self.cmd.id}: `{self.cmd.text}` exited {self.proc.returncode} before "
                                     f"printing /{pattern}/:\n{self.output()}")
            if time.monotonic() > deadline:
                raise AssertionError(f"{self.cmd.id}: `{self.cmd.text}` printed no /{pattern}/ within "
                                     f"{timeout:g} s:\n{self.output()}")
            time.sleep(0.05)

    def interrupt(self, timeout: float = 20.0) -> int:
        """Ctrl-C as a terminal sends it (SIGINT to the job's process group); its exit status."""
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGINT)
        try:
            return self.proc.wait(timeout)
        finally:
            self.stop()

    def stop(self) -> None:
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(20)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait()
        self._log.close()


class Scenes:
    """The daemons each scene's commands need, one scene alive at a time (two cores are shared):
    entering a scene stops the previous one's daemons and starts this one's (its ``daemon``
    commands, in doc order). A daemon that does not come up fails every command of its scene with
    its output."""

    def __init__(self, env: DocEnv, commands: list[Command], spec: Callable[[Command], How], logs: Path):
        self.env, self.commands, self.spec, self.logs = env, commands, spec, logs
        self.name: str | None = None
        self.daemons: list[Background] = []
        self.error: str | None = None

    def enter(self, name: str, jobs: bool = False) -> list[Background]:
        """Make ``name`` the live scene; ``jobs``: also start its ``cmd &`` jobs now, in doc order,
        unless running (for a check after the section ran, where its jobs are its first lines)."""
        if name != self.name:
            self.close()
            self.name = name
            self.env.folder(f"work-{name}")
            try:
                mine = [c for c in self.commands if self.spec(c).kind == "daemon" and self.spec(c).scene == name]
                for cmd in sorted(mine, key=lambda c: self.spec(c).start):  # stable: doc order within
                    how = self.spec(cmd)
                    if how.setup is not None:
                        how.setup(self.env)
                    d = Background(self.env, cmd, how, self.logs / f"{Path(cmd.doc).stem}-{cmd.line}.log")
                    self.daemons.append(d)
                    d.wait_ready(ready_pattern(cmd, how, self.env))
            except AssertionError as e:
                self.error = str(e)
        if self.error:
            raise AssertionError(f"scene {name!r} did not start: {self.error}")
        if jobs:
            running = {d.cmd for d in self.daemons if d.proc.poll() is None}
            for cmd in self.commands:
                how = self.spec(cmd)
                if how.kind == "job" and how.scene == name and cmd not in running:
                    self.job(cmd, how)
        return self.daemons

    def daemon(self, cmd: Command) -> Background:
        return next(d for d in self.daemons if d.cmd == cmd)

    def job(self, cmd: Command, how: How) -> Background:
        """Start ``cmd &`` in the current scene (it serves until the scene ends), once it is up."""
        d = Background(self.env, cmd, how, self.logs / f"{Path(cmd.doc).stem}-{cmd.line}.log")
        self.daemons.append(d)
        d.wait_ready(ready_pattern(cmd, how, self.env))
        return d

    def close(self) -> None:
        for d in reversed(self.daemons):
            try:
                d.interrupt()  # Ctrl-C, as the user stops it
            except Exception:  # noqa: BLE001 - teardown: SIGTERM / SIGKILL in stop()
                d.stop()
        self.daemons, self.name, self.error = [], None, None
