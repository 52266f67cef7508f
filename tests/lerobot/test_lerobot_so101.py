"""LeRobot's own scripts drive a simulated SO-101 pair through the plugin and two daemons (issue 21,
"Tests (CI)"): ``lerobot-record`` of 2 episodes teleoperated by the leader's daemon, then
``lerobot-replay`` of the first, then ``lerobot-teleoperate`` until the follower's daemon faults.

Both arms are ``crtk-sim feetech`` buses holding one LeRobot calibration (rig.CalibratedArm),
each served by its daemon with the calibration imported: so LeRobot's documented conversion of
the simulator's registers (rig.lerobot_reading) says, independently of the plugin, what the
dataset must hold. A hand moves the leader (torque off, as a person does); the follower is
compared with its simulator's registers. No hub, no cameras: a local dataset, HF_HUB_OFFLINE=1.
The module's tests run in order on one pair (record, then replay of what was recorded, then the
fault, which ends the follower's daemon's usefulness).
"""

from __future__ import annotations

import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest

from ..conftest import wait_until
from .rig import (ARM, KEYS, MOTORS, SO101, SO101_LEADER, CalibratedArm, Sampler, finish, lerobot_reading, on_the_way,
                  one_tick, polyline_distance, pose_at, read_dataset, run_lerobot, tail)

#: "crtk": LeRobot through the plugin and the daemons (what CI runs); "direct": LeRobot's own
#: so101_follower / so101_leader on the same simulated buses (CRTK_LEROBOT_TEST_MODE=direct), the
#: reference the harness was checked against
MODE = os.environ.get("CRTK_LEROBOT_TEST_MODE", "crtk")
REPO = "local/crtk_test"
FPS = 30
EPISODE_S = 4
#: the leader's poses: at rest at A, moved to B during episode 0 and to C during episode 1
A, B, C = pose_at(0.35), pose_at(0.6), pose_at(0.45)
HAND_SPEED = 900.0  # ticks/s: under one second for each move, then held
HOLD_S = 0.8  # s: the leader held still at the start of each episode (a replay starts there)
EPISODES = ((A, B), (B, C))


def robot_args(arm: CalibratedArm, prefix: str = "robot", units: str | None = None) -> list[str]:
    if MODE == "direct":
        kind = "so101_follower" if prefix == "robot" else "so101_leader"
        return [f"--{prefix}.type={kind}", f"--{prefix}.port={arm.port}", f"--{prefix}.id={arm.name}",
                f"--{prefix}.calibration_dir={arm.calibration_dir}"]
    return [f"--{prefix}.type=crtk", f"--{prefix}.socket={arm.socket}"] + \
        ([f"--{prefix}.units={units}"] if units else [])


def lerobot_reading_of(pose: dict[str, int]) -> np.ndarray:
    return np.array([lerobot_reading(m, pose[m]) for m in MOTORS])


TICKS = np.array([one_tick(m) for m in MOTORS])


class Pair:
    def __init__(self, venv: Path, plugin: Path | None, tmp: Path):
        self.venv, self.plugin, self.tmp = venv, plugin, tmp
        self.follower = CalibratedArm(SO101, tmp, "follower", pose=A)
        self.leader = CalibratedArm(SO101_LEADER, tmp, "leader", pose=A)
        if MODE != "direct":
            self.follower.start_daemon()
            self.leader.start_daemon()
        self.root = tmp / "dataset"
        self.recorded: dict | None = None

    def close(self) -> None:
        for arm in (self.follower, self.leader):
            arm.close()


@pytest.fixture(scope="module")
def pair(lerobot_venv, lerobot_launcher, lerobot_reader, request):
    plugin = request.getfixturevalue("lerobot_plugin") if MODE != "direct" else None
    tmp = Path(tempfile.mkdtemp(prefix="crtk-lr-"))
    p = Pair(lerobot_venv, plugin, tmp)
    p.reader, p.launcher = lerobot_reader, lerobot_launcher
    yield p
    p.close()
    shutil.rmtree(tmp, ignore_errors=True)


def test_record_two_episodes_teleoperated_by_the_leader(pair):
    log = pair.tmp / "record.log"
    proc = run_lerobot(pair.launcher, "lerobot-record", [
        *robot_args(pair.follower), *robot_args(pair.leader, "teleop"),
        f"--dataset.repo_id={REPO}", f"--dataset.root={pair.root}", "--dataset.num_episodes=2",
        f"--dataset.fps={FPS}", f"--dataset.episode_time_s={EPISODE_S}", "--dataset.reset_time_s=1",
        "--dataset.single_task=crtk-bridge test", "--dataset.push_to_hub=false", "--dataset.video=false",
        "--play_sounds=false", "--display_data=false"], log)
    try:
        for k, (_start, end) in enumerate(EPISODES):  # a hand moves the leader once each episode began
            wait_until(lambda: f"Recording episode {k}" in log.read_text(errors="replace") or proc.poll() is not None,
                       240, what=f"lerobot-record's episode {k}")
            time.sleep(HOLD_S)  # the person holds the leader still a moment, then moves it
            pair.leader.hand(end, HAND_SPEED)
        rc = finish(proc, log)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert rc == 0, tail(log)

    data = read_dataset(pair.reader, pair.root, REPO)
    assert data["num_episodes"] == 2, data["num_episodes"]
    assert data["action_names"] == list(KEYS) and data["state_names"] == list(KEYS), data
    episodes = np.array(data["episode_index"])
    actions, states = np.array(data["action"]), np.array(data["observation.state"])
    for k, (start, end) in enumerate(EPISODES):
        act, obs = actions[episodes == k], states[episodes == k]
        s, e = lerobot_reading_of(start), lerobot_reading_of(end)
        assert len(act) >= FPS * EPISODE_S // 3, (k, len(act))  # a loaded host may run slow, never empty
        # the actions are the leader's positions in LeRobot's units: on its way from start to end,
        # every joint one way only, and the end it was held at, to the tick
        assert np.all(on_the_way(act, s, e, TICKS)), (k, act[~on_the_way(act, s, e, TICKS)][:3], s, e)
        steps = np.diff(act, axis=0) * np.sign(e - s)
        assert np.all(steps >= -TICKS), (k, "the leader's readings went back", steps.min(axis=0))
        assert np.all(np.abs(act[-1] - e) <= 1.01 * TICKS), (k, "last action", act[-1], e)
        assert np.linalg.norm(act[0] - s) < np.linalg.norm(act[0] - e), (k, act[0], s, e)
        # the observations are the follower's positions: on the same way, and at the end where the
        # leader was (the follower follows)
        tol = 1.0 + TICKS  # the follower's interpolation and servo settle within a degree / percent
        assert np.all(on_the_way(obs, s, e, tol)), (k, obs[~on_the_way(obs, s, e, tol)][:3], s, e)
        assert np.all(np.abs(obs[-1] - e) <= tol), (k, "last observation", obs[-1], e)
    # and the last one is what the follower's servos hold now, in LeRobot's units
    now = pair.follower.reading()
    now = np.array([now[k] for k in KEYS])
    assert np.all(np.abs(states[-1] - now) <= 2 * TICKS + 0.3), (states[-1], now)
    pair.recorded = data


def test_replay_moves_the_follower_along_the_recorded_positions(pair):
    if pair.recorded is None:
        pytest.fail("test_record_two_episodes_teleoperated_by_the_leader did not record (it failed first)")
    data = pair.recorded
    episodes = np.array(data["episode_index"])
    path = np.array(data["action"])[episodes == 0]
    log = pair.tmp / "replay.log"
    sampler = Sampler(pair.follower, 0.02)
    proc = run_lerobot(pair.launcher, "lerobot-replay", [
        *robot_args(pair.follower), f"--dataset.repo_id={REPO}", f"--dataset.root={pair.root}",
        "--dataset.episode=0", "--play_sounds=false"], log)
    try:
        rc = finish(proc, log)
        # the follower ends where the episode ended (the daemon holds the last action)
        end = dict(zip(MOTORS, path[-1]))
        wait_until(lambda: all(abs(pair.follower.reading()[f"{m}.pos"] - end[m]) <= 1.0 + one_tick(m) for m in MOTORS),
                   10, what="the follower at the episode's last action")
    finally:
        samples = sampler.stop()
        if proc.poll() is None:
            proc.kill()
    assert rc == 0, tail(log)
    readings = np.array([[lerobot_reading(m, s[m]) for m in MOTORS] for _, s in samples])
    assert len(readings) > 20, len(readings)
    # it went from where it was to the episode's first action, then along the recorded actions to
    # their end: every sample from then on lies on the recorded path, within a degree / percent
    near_start = np.abs((readings - path[0]) / TICKS).max(axis=1)
    first = int(np.argmax(near_start <= 12))
    assert near_start[first] <= 12, ("never at the episode's first action", near_start.min(), readings[-1], path[0])
    along = readings[first:]
    d = polyline_distance(along, path, TICKS)
    assert d.max() <= 1.0 / TICKS.min() + 2, (d.max(), along[d.argmax()])
    near_end = np.abs((along - path[-1]) / TICKS).max(axis=1)
    assert near_end.min() <= 12, ("never at the episode's last action", near_end.min())
    # and it travelled: by the action half-way along the path (not a jump from start to end)
    arc = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(path / TICKS, axis=0), axis=1))])
    mid = path[int(np.argmin(np.abs(arc - arc[-1] / 2)))]
    assert np.abs((along - mid) / TICKS).max(axis=1).min() <= 1.0 / TICKS.min() + 2


def test_teleoperate_then_the_follower_daemon_faults(pair):
    log = pair.tmp / "teleoperate.log"
    d = pose_at(0.52)
    proc = run_lerobot(pair.launcher, "lerobot-teleoperate", [
        *robot_args(pair.follower), *robot_args(pair.leader, "teleop"), "--fps=30", "--display_data=false"],
        log)
    try:
        wait_until(lambda: "teleop" in log.read_text(errors="replace").lower() and
                   pair.follower.read("shoulder_pan", "Torque_Enable") == 1 or proc.poll() is not None,
                   240, what="lerobot-teleoperate connected")
        assert proc.poll() is None, tail(log)
        pair.leader.hand(d, HAND_SPEED)  # the follower follows the leader...
        pair.follower.wait_at({m: d[m] for m in ARM}, 20, tol=12)
        pair.follower.fault("elbow_flex", "silent")  # ... until its bus goes silent: the daemon faults
        rc = finish(proc, log, 60)
    finally:
        if proc.poll() is None:
            proc.kill()
    out = log.read_text(errors="replace")
    assert rc != 0, tail(log)
    # a clear error: the plugin's, with the daemon's one-line reason (the joint whose servo fell silent)
    error = [ln for ln in out.splitlines() if "CrtkFaultError" in ln]
    assert error and "so101 is in FAULT (" in error[-1] and "elbow_flex" in error[-1], tail(log)
    # the follower stopped: the leader moves on, the follower's goals stay where they were
    goals = {m: pair.follower.read(m, "Goal_Position") for m in ("shoulder_pan", "shoulder_lift", "wrist_flex")}
    pair.leader.hand(pose_at(0.4), HAND_SPEED)
    deadline = time.monotonic() + 1.0
    while time.monotonic() < deadline:
        assert {m: pair.follower.read(m, "Goal_Position") for m in goals} == goals
        time.sleep(0.05)
