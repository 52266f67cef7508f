"""tests/in_child.py: the tests marked ``in_child`` run in a child pytest, so a process abort there
(ur_rtde after a link broke) does not end the whole session: the test that died runs once more
alone, and fails if it dies again."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent

CONFTEST = """
import os

import in_child

os.environ.setdefault("PARENT_PID", str(os.getpid()))  # the children inherit the parent's


def pytest_configure(config):
    config.pluginmanager.register(in_child, "crtk-in-child")
"""

ABORTING = """
import os

import pytest

PARENT = int(os.environ["PARENT_PID"])

pytestmark = pytest.mark.in_child


@pytest.fixture(scope="module")
def shared():
    return {"pid": os.getpid(), "n": 0}


def test_first(shared):
    shared["n"] += 1
    assert shared["pid"] != PARENT  # in a child


def test_aborts(shared):
    if shared["n"] == 1:  # the same child as test_first: module fixtures are shared as in one process
        open(os.path.join(os.environ["MARKS"], "shared"), "w").close()
    os.abort()  # every time: it dies again when run alone, so it fails


def test_dies_once():
    # dies the first time only (as a test brought down by a heap an earlier test corrupted):
    # run again alone, it passes
    mark = os.path.join(os.environ["MARKS"], "died")
    if not os.path.exists(mark):
        open(mark, "w").close()
        os.abort()


@pytest.mark.skip(reason="skipped, reported as such")
def test_skipped():
    pass


def test_after_the_abort(shared):
    assert shared["n"] == 0  # a new child ran the rest of the module
"""


def test_an_abort_fails_its_test_and_the_session_goes_on(tmp_path):
    marks = tmp_path / "marks"
    marks.mkdir()
    shutil.copy(HERE / "in_child.py", tmp_path / "in_child.py")
    (tmp_path / "conftest.py").write_text(CONFTEST)
    (tmp_path / "test_aborting.py").write_text(ABORTING)
    (tmp_path / "test_plain.py").write_text("def test_plain():\n    pass\n")
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-rfs", "-p", "no:cacheprovider",
                           "--rootdir", str(tmp_path), str(tmp_path)], cwd=tmp_path, capture_output=True,
                          text=True, timeout=120, env={**os.environ, "MARKS": str(marks)})
    out = proc.stdout + proc.stderr
    assert proc.returncode == 1, out  # tests failed; the session itself was not aborted (-6)
    assert "1 failed, 4 passed, 1 skipped" in out, out
    assert (marks / "shared").exists() and (marks / "died").exists(), out
    # a test that died once is run again alone, and says so; one that dies again fails
    assert "died of SIGABRT (signal 6) in test_aborting.py::test_dies_once; running it again alone" in out, out
    assert "FAILED test_aborting.py::test_dies_once" not in out, out
    assert "FAILED test_aborting.py::test_aborts" in out, out
    assert "died of SIGABRT (signal 6)" in out, out
    assert "Fatal Python error: Aborted" in out, out  # the child's faulthandler output is shown
    assert "SKIPPED [1] test_aborting.py" in out and "skipped, reported as such" in out, out


def test_tests_in_the_parent_around_child_tests_set_up_and_tear_down_as_usual(tmp_path):
    """An unmarked test, then a marked one last in its module (the conformance suite's UR row
    after the others), then another module's test: the parent still tears the first module down
    before the next one's (pytest: "previous item was not torn down properly" otherwise)."""
    shutil.copy(HERE / "in_child.py", tmp_path / "in_child.py")
    (tmp_path / "test_mixed.py").write_text(
        "import os\nimport pytest\n\nPARENT = int(os.environ['PARENT_PID'])\n\n\n"
        "@pytest.fixture(scope='module')\ndef where():\n    yield os.getpid()\n\n\n"
        "@pytest.mark.parametrize('row', ['here', 'child'])\n"
        "def test_row(row, where):\n"
        "    assert (where == PARENT) == (row != 'child')\n")
    (tmp_path / "conftest.py").write_text(CONFTEST + "\n\ndef pytest_collection_modifyitems(items):\n"
                                          "    import pytest\n    for i in items:\n"
                                          "        if i.name.endswith('[child]'):\n"
                                          "            i.add_marker(pytest.mark.in_child)\n")
    (tmp_path / "test_next.py").write_text("def test_next():\n    pass\n")
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "--rootdir",
                           str(tmp_path), str(tmp_path)], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0 and "3 passed" in out, out


RECORDING = """
import os

import pytest

pytestmark = pytest.mark.in_child


@pytest.mark.parametrize("k", range(2))
def test_records(k, request):
    with open(os.path.join(os.environ["MARKS"], request.node.nodeid.replace("/", "_")), "a") as f:
        f.write(f"{os.getpid()}\\n")
"""


def test_under_xdist_each_marked_test_runs_once_in_one_child(tmp_path):
    """pytest-xdist: every worker collects the whole session, but runs only what it is given;
    marked tests of two files on two workers (``--dist loadfile``, what this suite's ``-n`` means:
    a file each) each run once, each file's tests in one child sharing its module fixtures."""
    shutil.copy(HERE / "in_child.py", tmp_path / "in_child.py")
    (tmp_path / "conftest.py").write_text(CONFTEST)
    for name in ("test_a.py", "test_b.py"):
        (tmp_path / name).write_text(RECORDING)
    marks = tmp_path / "marks"
    marks.mkdir()
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-n", "2", "--dist",
                           "loadfile", "--rootdir", str(tmp_path), str(tmp_path)], cwd=tmp_path, capture_output=True,
                          text=True, timeout=120, env={**os.environ, "MARKS": str(marks)})
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0 and "4 passed" in out, out
    runs = {p.name: p.read_text().split() for p in marks.iterdir()}
    assert len(runs) == 4 and all(len(pids) == 1 for pids in runs.values()), runs
    children = {name: {pids[0] for test, pids in runs.items() if test.startswith(name)}
                for name in ("test_a.py", "test_b.py")}
    assert all(len(pids) == 1 for pids in children.values()) and len(set.union(*children.values())) == 2, children


def test_under_another_xdist_dist_a_worker_runs_each_marked_test_in_a_child_of_its_own():
    """``--dist load`` (or any but loadfile) gives a worker single tests: its child runs the test
    it was given, never the file's others (another worker may have them)."""
    from types import SimpleNamespace

    from . import in_child

    class Item:
        def __init__(self, nodeid, session, dist):
            self.nodeid, self.session, self.path = nodeid, session, Path(nodeid.split("::")[0])
            self.config = SimpleNamespace(workerinput={in_child.DIST: dist})

        def get_closest_marker(self, name):
            return name == in_child.MARK

    for dist, expect in (("load", [["a.py::t0"], ["a.py::t1"]]), ("loadfile", [["a.py::t0", "a.py::t1"]] * 2)):
        session = SimpleNamespace(items=[])
        session.items += [Item(f"a.py::t{k}", session, dist) for k in range(2)] + [Item("b.py::t0", session, dist)]
        assert [[i.nodeid for i in in_child._group(item).items] for item in session.items[:2]] == expect, dist
