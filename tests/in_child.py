"""Run the tests marked ``in_child`` in a child pytest process, so that a process abort in them
fails those tests instead of ending the whole session.

Why: ur_rtde 1.6.5 runs in-process in tests/test_sim_ur.py (ur_rtde's own interfaces driving the
simulated controller; the UR backend runs ur_rtde in a worker process of its own, so its tests
need no child), and its interfaces can abort or crash the process they run in after a link breaks (C++ exceptions reaching ``std::terminate``; the control
interface's own receive thread reconnecting while a command is sent on the same socket: SIGABRT
or SIGSEGV, about one run in ten of those tests under load). pytest-forked forks per test, which
would drop the module-scoped simulators and interfaces these modules share (and fork a process
that runs ur_rtde's threads); this runs the session's selected marked tests in ONE child, in
order, so their module fixtures are shared as before.

The parent runs the child when it reaches the first marked test, then replays the
child's reports (``pytest_report_to_serializable`` / ``_from_serializable``, as pytest-xdist
does) at each test's own place in the session, so ``-x``, ``-ra`` and the summary see them as
usual. A child that dies runs the test it was running once more, alone in a fresh child, with a
line in the session's output naming the signal and the test: the heap ur_rtde corrupts at a link
loss often brings down a LATER test of the same child (a SIGSEGV in a plain ``servoJ``), so the
test that died is not to blame until it dies again on its own. A test that dies twice fails,
naming the signal and showing the end of its output (faulthandler's stacks included). The
remaining tests run in a new child.

Debugging in-process (pdb, ``-s``): ``CRTK_TEST_CHILD=/dev/null pytest ...`` runs everything in
the parent as before.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest
from _pytest.reports import TestReport

MARK = "in_child"
ENV = "CRTK_TEST_CHILD"  # set in the child: the file its reports go to
DIST = "crtk_in_child_dist"  # pytest-xdist: the controller's --dist, in each worker's workerinput
CHILD_TIMEOUT_S = 900.0  # a hung child (a ur_rtde call that never returns) is ended after this
_TAIL_LINES = 80


def pytest_configure(config):
    config.addinivalue_line("markers", f"{MARK}: run the marked tests in one child pytest process "
                            "(tests/in_child.py): a process abort in them fails them, not the session")


# ---------------------------------------------------------------------------------- child side
def _record(config, entry: dict) -> None:
    path = os.environ.get(ENV)
    if not path or path == os.devnull:
        return
    with open(path, "a", encoding="utf-8") as f:  # one line per event, flushed: a crash keeps what came before
        f.write(json.dumps(entry) + "\n")


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_logstart(nodeid, location):
    if os.environ.get(ENV):
        _record(None, {"start": nodeid})


def pytest_runtest_logreport(report):
    if os.environ.get(ENV) and not getattr(report, "_from_child", False):
        config = _CONFIG[0]
        if config is not None:
            _record(config, {"report": config.hook.pytest_report_to_serializable(config=config, report=report)})


_CONFIG: list = [None]


@pytest.hookimpl(tryfirst=True)
def pytest_sessionstart(session):
    _CONFIG[0] = session.config


# --------------------------------------------------------------------------------- parent side
class _Group:
    """The session's marked tests, run together in one child (a child pytest costs ~1.5 s of CPU
    to start); their reports by node id."""

    def __init__(self, items: list[pytest.Item]):
        self.items = items
        self.reports: dict[str, list[TestReport]] = {}
        self.ran = False


def _signal_name(rc: int) -> str:
    try:
        return f"{signal.Signals(-rc).name} (signal {-rc})"
    except ValueError:
        return f"signal {-rc}"


def _run_child(config, group: _Group, rerun: set[str] | None = None) -> None:
    """Run the group's tests in children until each has its reports (a new child after a crash;
    a test that died runs once more alone, see the module's docstring)."""
    todo = list(group.items)
    root = str(config.rootpath)
    rerun = set() if rerun is None else rerun  # tests that died once (run again alone)
    while todo:
        with tempfile.TemporaryDirectory(prefix="crtk-child-") as tmp:
            out_path, log_path = Path(tmp) / "reports.jsonl", Path(tmp) / "output.log"
            out_path.touch()
            env = {**os.environ, ENV: str(out_path)}
            cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "--rootdir", root,
                   *[item.nodeid for item in todo]]
            with open(log_path, "wb") as log:
                proc = subprocess.Popen(cmd, cwd=root, env=env, stdout=log, stderr=subprocess.STDOUT,
                                        stdin=subprocess.DEVNULL)
                try:
                    rc = proc.wait(CHILD_TIMEOUT_S)
                    why = None if rc >= 0 else f"died of {_signal_name(rc)}"
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
                    rc, why = -9, f"hung: killed after {CHILD_TIMEOUT_S:g} s"
            started: list[str] = []
            for line in out_path.read_text(encoding="utf-8").splitlines():
                entry = json.loads(line)
                if "start" in entry:
                    started.append(entry["start"])
                else:
                    rep = config.hook.pytest_report_from_serializable(config=config, data=entry["report"])
                    rep._from_child = True
                    if isinstance(rep.longrepr, list):  # a skip's (path, line, reason): JSON made it a list
                        rep.longrepr = tuple(rep.longrepr)
                    rep.location = tuple(rep.location)
                    group.reports.setdefault(rep.nodeid, []).append(rep)
            tail = "\n".join(log_path.read_text(encoding="utf-8", errors="replace").splitlines()[-_TAIL_LINES:])
        done = {nodeid for nodeid, reps in group.reports.items() if any(r.when == "teardown" for r in reps)}
        by_id = {item.nodeid: item for item in todo}
        if why is None and rc in (0, 1, 5) and all(i.nodeid in done or i.nodeid not in started for i in todo):
            for item in todo:  # collected but not run by the child (a bad node id): fail it, saying so
                if item.nodeid not in started:
                    group.reports[item.nodeid] = [_failed(item, "call", f"not run by the child pytest "
                                                          f"(exit code {rc}):\n{tail}")]
            return
        # the child ended early: the test it was running fails, naming why; the rest run again
        running = next((n for n in started if n not in done and n in by_id), None)
        if running is None:  # it died before starting any (collection): every test fails with its output
            for item in todo:
                group.reports[item.nodeid] = [_failed(item, "setup", f"the child pytest process {why or f'exited {rc}'} "
                                                      f"before running this test:\n{tail}")]
            return
        item = by_id[running]
        rest = [i for i in todo if i.nodeid not in done and i.nodeid != running and i.nodeid not in started]
        if why is not None and running not in rerun:
            rerun.add(running)
            group.reports.pop(running, None)
            _say(config, f"in_child: the child pytest process {why} in {running}; running it again alone in a "
                         f"fresh child (tests/in_child.py). The end of its output:\n{tail}")
            _run_alone_then(config, group, item, rest, rerun)
            return
        phases = [r.when for r in group.reports.get(running, [])]
        when = "teardown" if "call" in phases else ("call" if "setup" in phases else "setup")
        group.reports.setdefault(running, []).append(_failed(
            item, when, f"the child pytest process running this test {why or f'exited {rc}'} in its {when} "
            f"(an abort in native code, e.g. ur_rtde after a link broke; tests/in_child.py); "
            f"the end of its output:\n{tail}"))
        todo = rest


def _run_alone_then(config, group: _Group, item: pytest.Item, rest: list[pytest.Item], rerun: set[str]) -> None:
    """Run ``item`` alone in a fresh child (it died once), then ``rest`` in another."""
    for batch in ([item], rest):
        if batch:
            sub = _Group(batch)
            sub.reports = group.reports
            _run_child(config, sub, rerun)


def _say(config, text: str) -> None:
    tr = config.pluginmanager.get_plugin("terminalreporter")
    if tr is not None:
        tr.write_line("")
        for line in text.splitlines():
            tr.write_line(line)
    else:
        print(text, file=sys.stderr)


def _failed(item: pytest.Item, when: str, text: str) -> TestReport:
    rep = TestReport(item.nodeid, item.location, {k: 1 for k in item.keywords}, "failed", text, when)
    rep._from_child = True
    return rep


def _group(item: pytest.Item) -> _Group:
    """The session's marked tests. A pytest-xdist worker collects the whole session but runs only
    the tests it is given, so no marked test may run in two workers' children: with ``--dist
    loadfile`` (what this suite's ``-n`` means: tests/conftest.py) a worker is given whole files
    and its group is ``item``'s file's marked tests; with another ``--dist``, ``item`` alone."""
    session = item.session
    key = None
    if hasattr(item.config, "workerinput"):  # (a worker's own option says nothing of the --dist)
        key = item.path if item.config.workerinput.get(DIST) == "loadfile" else item.nodeid
    groups = session.__dict__.setdefault("_crtk_child_groups", {})
    if key not in groups:
        groups[key] = _Group([i for i in session.items if i.get_closest_marker(MARK)
                              and key in (None, i.path, i.nodeid)])
    return groups[key]


@pytest.hookimpl(optionalhook=True)
def pytest_configure_node(node):
    """pytest-xdist's controller, for each worker: the ``--dist`` its tests come by (:func:`_group`)."""
    node.workerinput[DIST] = node.config.option.dist


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_protocol(item, nextitem):
    if os.environ.get(ENV) or item.get_closest_marker(MARK) is None:
        return None  # the child itself, or an ordinary test: pytest runs it here
    group = _group(item)
    if not group.ran:
        group.ran = True
        _run_child(item.config, group)
    item.ihook.pytest_runtest_logstart(nodeid=item.nodeid, location=item.location)
    reports = list(group.reports.get(item.nodeid, []))
    try:  # what the parent set up for the tests before this one and the next one does not need
        item.session._setupstate.teardown_exact(nextitem)
    except Exception as exc:  # a fixture's finalizer failed: as pytest's own teardown reports it
        reports.append(_failed(item, "teardown", f"tearing down before {nextitem and nextitem.nodeid}: {exc!r}"))
    for rep in reports:
        item.ihook.pytest_runtest_logreport(report=rep)
    item.ihook.pytest_runtest_logfinish(nodeid=item.nodeid, location=item.location)
    return True
