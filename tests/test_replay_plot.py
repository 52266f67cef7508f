"""Replay and plots of a recording (docs/recording.md): ``crtk-ctl replay`` moves the SO-101
simulator along a recording within the daemon's tracking tolerance, refuses another robot's or
other joints' recording naming the difference, asks before the first move and holds on Ctrl-C;
``crtk-ctl plot`` writes a PNG / SVG / HTML (the HTML rendered by headless Chromium without
console errors), and says which extra to install when matplotlib is absent."""

from __future__ import annotations

import io
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest
import yaml

from crtk_bridge.client import bagfile, connect, replay
from crtk_bridge.client.cli import main as ctl_main

from .conftest import ROOT, DaemonProcess, so101_data

ARM = ["shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll"]
POSES = ([0.4, -0.3, 0.3, 0.2, -0.3], [-0.3, 0.2, -0.2, -0.2, 0.4])
ELSEWHERE = [0.1, 0.1, 0.1, 0.1, 0.1]


@pytest.fixture(scope="module")
def daemon():
    tmp = Path(tempfile.mkdtemp(prefix="crtk-rp-"))  # short: the socket path
    data = so101_data()
    data["recording"] = {"blackbox_s": 0}
    (tmp / "so101.yaml").write_text(yaml.safe_dump(data))
    d = DaemonProcess(["--profile", str(tmp / "so101.yaml"), "--sim"], tmp / "so101.sock", tmp / "daemon.log")
    d.tmp = tmp
    d.tolerance = data["safety"]["tracking_error_max"]
    try:
        yield d
    finally:
        d.print_tail()
        d.stop()
        shutil.rmtree(tmp, ignore_errors=True)


@pytest.fixture(scope="module")
def recorded(daemon) -> Path:
    """A recording of two moves on the simulator (the robot left elsewhere after it), with a
    warning event in it."""
    with connect(socket=str(daemon.socket_path), timeout=10.0) as robot:
        arm = robot.device("so101")
        robot.enable()
        started = robot.record(str(daemon.tmp / "orig.mcap"))
        for goal in POSES:
            assert arm.move_jp(goal).wait(timeout=20)
        result = robot.record_stop(started["recording"], timeout=20)
        assert arm.move_jp(ELSEWHERE).wait(timeout=20)
    return Path(result["path"])


def _stream_window(t, q, ref_t, ref_q):
    """The largest joint error of the trajectory (t, q) against (ref_t, ref_q) at the best time
    offset (the replay's start, unknown to the test), and that offset."""
    best = (np.inf, 0.0)
    span = ref_t[-1]
    grid = np.linspace(0.0, span, 200)
    ref = np.stack([np.interp(grid, ref_t, ref_q[:, j]) for j in range(ref_q.shape[1])], axis=1)
    for start in np.arange(t[0], t[-1] - span, 0.005):
        got = np.stack([np.interp(start + grid, t, q[:, j]) for j in range(q.shape[1])], axis=1)
        err = float(np.abs(got - ref).max())
        if err < best[0]:
            best = (err, start)
    return best


def test_replay_moves_the_simulator_along_the_recording(daemon, recorded, capsys):
    sock = str(daemon.socket_path)
    orig = bagfile.read(recorded)
    sp = orig.series("so101", "setpoint_js")
    ok = np.isfinite(sp.position).all(axis=1)
    ref_t, ref_q = sp.t[ok] - sp.t[ok][0], sp.position[ok]
    assert np.ptp(ref_q, axis=0).max() > 0.5  # the recording moves
    om = orig.series("so101", "measured_js")  # what the simulator did then, over the same window
    inside = (om.t >= sp.t[ok][0]) & (om.t <= sp.t[ok][-1])
    ref_mt, ref_mq = om.t[inside] - sp.t[ok][0], om.position[inside]

    with connect(socket=sock, timeout=10.0) as robot:
        started = robot.record(str(daemon.tmp / "replayed.mcap"))
        assert ctl_main(["--socket", sock, "replay", str(recorded), "--yes"]) == 0
        result = robot.record_stop(started["recording"], timeout=20)
    out = capsys.readouterr().out
    assert "first a move_jp to its first position" in out and "replayed" in out
    again = bagfile.read(result["path"])
    m = again.series("so101", "measured_js")
    s = again.series("so101", "setpoint_js")
    valid = np.isfinite(s.position).all(axis=1)
    # the simulator's measured positions follow the recorded ones, at their timing (one time
    # offset for the whole replay), within the daemon's tracking tolerance; so do the setpoints
    err_m, _ = _stream_window(m.t, m.position, ref_mt, ref_mq)
    err_s, _ = _stream_window(s.t[valid], s.position[valid], ref_t, ref_q)
    print(f"replay: largest joint error {err_m:.4f} rad measured, {err_s:.4f} rad setpoint")
    assert err_m < daemon.tolerance and err_s < daemon.tolerance, (err_m, err_s)
    # the first position was reached by a move_jp, then interpolate_jp samples, nothing else
    commands = [c for _, c in _commands(result["path"])]
    assert commands[0]["cmd"] == "move_jp"
    np.testing.assert_allclose(commands[0]["data"]["position"], ref_q[0], atol=1e-9)
    assert {c["cmd"] for c in commands[1:]} == {"interpolate_jp"} and len(commands) > 20


def _commands(path):
    import json

    from rosbags.rosbag2 import Reader

    from crtk_bridge.transport.ros.types import TYPESTORE
    with Reader(path) as bag:
        conns = [c for c in bag.connections if c.topic == "/so101/commands"]
        return [(t, json.loads(TYPESTORE.deserialize_cdr(d, c.msgtype).string)) for c, t, d in bag.messages(conns)]


def test_replay_of_another_robot_or_other_joints_is_refused_naming_the_difference(recorded):
    rec = bagfile.read(recorded)
    with pytest.raises(bagfile.BagError, match="recorded on robot 'so101', this is 'koch': replay refused"):
        replay.plan(rec, "koch", "so101", "setpoint_js", ARM)
    with pytest.raises(bagfile.BagError, match=r"recorded only: wrist_roll; not recorded: wrist_twist"):
        replay.plan(rec, "so101", "so101", "setpoint_js", ARM[:4] + ["wrist_twist"])
    with pytest.raises(bagfile.BagError, match="the order differs"):
        replay.plan(rec, "so101", "so101", "setpoint_js", list(reversed(ARM)))
    rec.namespaces = ["so101/gripper"]
    with pytest.raises(bagfile.BagError, match="namespace so101 is not in this recording"):
        replay.plan(rec, "so101", "so101", "setpoint_js", ARM)


class _FakeArm:
    """What replay.stream sends, on a clock it drives (no daemon)."""

    def __init__(self, refuse_at: int | None = None):
        self.now = 0.0
        self.sent: list[tuple[float, list]] = []
        self.held = False
        self.refuse_at = refuse_at

    def interpolate_jp(self, q):
        from crtk_bridge.errors import CommandError
        if self.refuse_at is not None and len(self.sent) == self.refuse_at:
            raise CommandError("step_too_large", "so101: interpolate_jp: too far")
        self.sent.append((self.now, q))

    def hold(self):
        self.held = True

    def sleep(self, s):
        self.now += s


def test_replay_keeps_the_recorded_timing_scaled_by_speed_and_holds_on_a_refused_sample():
    t = np.linspace(0.0, 2.0, 2001)  # 2 s at 1 kHz: joint 0 ramps 0 -> 1 rad
    p = replay.Plan("so101", "setpoint_js", ["a", "b"], t, np.stack([t / 2.0, np.zeros_like(t)], axis=1))
    for speed in (1.0, 2.0, 0.5):
        arm = _FakeArm()
        report = replay.stream(arm, p, speed, 50.0, clock=lambda: arm.now, sleep=arm.sleep)
        assert report.samples == len(arm.sent) == round(2.0 / speed * 50) + 1
        for when, q in arm.sent:  # each sample: the recorded position at (wall time x speed)
            assert q[0] == pytest.approx(min(1.0, when * speed / 2.0), abs=1e-9) and q[1] == 0.0
        assert arm.sent[-1][1][0] == pytest.approx(1.0) and arm.sent[-1][0] == pytest.approx(2.0 / speed)
        assert not arm.held
    arm = _FakeArm(refuse_at=5)
    with pytest.raises(Exception, match="too far"):
        replay.stream(arm, p, 1.0, 50.0, clock=lambda: arm.now, sleep=arm.sleep)
    assert arm.held and len(arm.sent) == 5


def test_replay_asks_first_and_holds_on_ctrl_c(daemon, recorded, capsys, monkeypatch):
    sock = str(daemon.socket_path)
    with connect(socket=sock, timeout=10.0) as robot:  # then released: crtk-ctl's session takes control
        robot.enable()
        assert robot.device("so101").move_jp(ELSEWHERE).wait(timeout=20)
    with connect(socket=sock, timeout=10.0) as robot:
        arm = robot.device("so101")
        # stdin not a terminal, no --yes: refused before anything moves
        monkeypatch.setattr(sys, "stdin", io.StringIO("y\n"))
        assert ctl_main(["--socket", sock, "replay", str(recorded)]) == 2
        assert "give --yes" in capsys.readouterr().err
        # a terminal answering no: nothing moves
        tty = io.StringIO("n\n")
        tty.isatty = lambda: True
        monkeypatch.setattr(sys, "stdin", tty)
        assert ctl_main(["--socket", sock, "replay", str(recorded)]) == 1
        assert "replay not started" in capsys.readouterr().err
        np.testing.assert_allclose(arm.measured_jp()[0], ELSEWHERE, atol=0.02)

        # Ctrl-C during the stream: hold, said, exit 130
        def interrupted(dev, p, speed, rate):
            dev.interpolate_jp(p.at(0.05).tolist())
            raise KeyboardInterrupt
        monkeypatch.setattr(replay, "stream", interrupted)
        assert ctl_main(["--socket", sock, "replay", str(recorded), "--yes"]) == 130
        err = capsys.readouterr().err
        assert "interrupted: so101 replay stopped with hold" in err
        state = arm.operating_state_full()
        assert state["state"] == "ENABLED" and not state["is_busy"]


# ---------------------------------------------------------------- plots
def test_plot_png_one_line_per_joint(recorded, tmp_path, capsys):
    pytest.importorskip("matplotlib")  # in the test extra: CI has it
    from matplotlib.image import imread
    from matplotlib.colors import to_rgb

    from crtk_bridge.client import plot

    rec = bagfile.read(recorded)
    fig = plot.figure(rec, "so101")
    axes = fig.axes
    assert len(axes) >= 2 * len(ARM)  # position and velocity, a row per joint
    position = [ax for ax in axes if "position" in ax.get_ylabel()]
    assert [ax.get_ylabel().split("\n")[0] for ax in position] == ARM
    for j, ax in enumerate(position):  # measured and setpoint of that joint, in its colour
        labels = sorted(line.get_label() for line in ax.get_lines() if not line.get_label().startswith("_"))
        assert labels == [f"{ARM[j]} measured", f"{ARM[j]} setpoint"]
        assert {line.get_color() for line in ax.get_lines() if not line.get_label().startswith("_")} == {f"C{j}"}
        assert max(len(line.get_xdata()) for line in ax.get_lines()) > 100
    out = tmp_path / "run.png"
    assert ctl_main(["plot", str(recorded), "-o", str(out)]) == 0
    assert f"wrote {out}" in capsys.readouterr().out
    img = imread(out)[:, :, :3]
    assert img.shape[0] > 500 and img.shape[1] > 500 and img.std() > 0.05  # not blank
    pixels = img.reshape(-1, 3)
    for j in range(len(ARM)):  # every joint's colour is drawn
        near = np.abs(pixels - np.array(to_rgb(f"C{j}"))).max(axis=1) < 0.02
        assert near.sum() > 200, f"joint {ARM[j]}'s colour C{j} barely in the image"
    # --joints, --from/--to and --ns select
    fig = plot.figure(rec, "so101", joints=["elbow_flex"], t_from=0.5, t_to=1.0)
    lines = [ln for ax in fig.axes for ln in ax.get_lines() if not ln.get_label().startswith("_")]
    assert lines and all(0.5 <= min(ln.get_xdata()) and max(ln.get_xdata()) <= 1.0 for ln in lines)
    assert {ax.get_ylabel().split("\n")[0] for ax in fig.axes} == {"elbow_flex"}
    # each joint in its unit: the SO-101's are all revolute; one the metadata says is prismatic in m
    assert rec.custom["prismatic_joints"] == "" and "position (rad)" in position[0].get_ylabel()
    rec.custom["prismatic_joints"] = "elbow_flex"
    labels = [ax.get_ylabel() for ax in plot.figure(rec, "so101").axes]
    assert "elbow_flex\nposition (m)" in labels and "elbow_flex\nvelocity (m/s)" in labels
    assert "wrist_flex\nposition (rad)" in labels and "wrist_flex\nvelocity (rad/s)" in labels
    assert ctl_main(["plot", str(recorded), "-o", str(tmp_path / "g.svg"), "--ns", "so101/gripper"]) == 0
    assert "<svg" in (tmp_path / "g.svg").read_text()[:2000]
    assert ctl_main(["plot", str(recorded), "-o", str(tmp_path / "x.png"), "--joints", "nope"]) == 1
    assert "so101 has no joint nope" in capsys.readouterr().err


def _chromium() -> str:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        if shutil.which(name):
            return shutil.which(name)
    pytest.fail("headless Chromium is needed (.ci/run installs Debian's chromium package)")


def _render(page: Path, tmp: Path) -> tuple[list[str], Path]:
    """Headless Chromium renders ``page``: (its console messages, a screenshot)."""
    shot = tmp / f"{page.stem}.shot.png"
    proc = subprocess.run(
        [_chromium(), "--headless", "--no-sandbox", "--disable-gpu", "--enable-logging=stderr", "--v=0",
         "--window-size=1200,1600", f"--screenshot={shot}", page.as_uri()],
        capture_output=True, text=True, timeout=120, env={**os.environ, "HOME": str(tmp)})
    assert proc.returncode == 0 and shot.exists(), proc.stderr[-2000:]
    return [line for line in proc.stderr.splitlines() if ":CONSOLE" in line], shot


def test_plot_html_renders_in_headless_chromium_without_console_errors(recorded, tmp_path):
    pytest.importorskip("matplotlib")
    from matplotlib.image import imread

    out = tmp_path / "run.html"
    assert ctl_main(["plot", str(recorded), "-o", str(out)]) == 0
    console, shot = _render(out, tmp_path)
    assert console == []
    assert imread(shot)[:, :, :3].std() > 0.05  # the page drew something
    page = subprocess.run([_chromium(), "--headless", "--no-sandbox", "--disable-gpu", "--dump-dom", out.as_uri()],
                          capture_output=True, text=True, timeout=120, env={**os.environ, "HOME": str(tmp_path)})
    assert "<svg" in page.stdout and "so101" in page.stdout
    # the check sees console errors: a page with one is caught
    bad = tmp_path / "bad.html"
    bad.write_text("<!DOCTYPE html><html><head><title>x</title></head><body><script>undefinedFn();</script></body></html>")
    console, _ = _render(bad, tmp_path)
    assert any("undefinedFn is not defined" in line for line in console), console


def test_plot_without_matplotlib_names_the_extra(recorded, tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib raises ImportError
    assert ctl_main(["plot", str(recorded), "-o", str(tmp_path / "x.png")]) == 1
    err = capsys.readouterr().err.strip()
    assert err == "crtk-ctl: plot needs matplotlib, an optional extra: pip install 'crtk-bridge[plot]'"
    assert not (tmp_path / "x.png").exists()


def test_the_client_does_not_import_matplotlib_unless_plotting():
    code = ("import sys; from crtk_bridge.client import cli; cli.main(['replay', '--help']) if False else None; "
            "cli.build_parser(); print('matplotlib' in sys.modules, 'rosbags' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert out.stdout.split() == ["False", "False"], out.stderr
