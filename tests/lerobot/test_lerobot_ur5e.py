"""``lerobot-record`` and ``lerobot-replay`` on the UR5e profile in ``si`` units (issue 21, "Tests
(CI)"): the follower a simulated UR5e (``crtk-bridge --sim``: ``crtk-sim ur`` on a free
127.0.0.N), teleoperated by a second one in freedrive (teach mode) that a hand pushes, as
docs/lerobot.md describes. Keys ``<joint>.pos`` in radians; the simulators' joint positions
(``state``) are the reference.
"""

from __future__ import annotations

import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from crtk_bridge.client import connect
from crtk_bridge.sim.control import control_request

from ..conftest import DaemonProcess, wait_until
from .rig import UR5E, Sampler, finish, on_the_way, polyline_distance, read_dataset, run_lerobot, tail

JOINTS = ("shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint", "wrist_3_joint")
KEYS = [f"{j}.pos" for j in JOINTS]
HOME = np.array([0.0, -1.5708, 0.0, -1.5708, 0.0, 0.0])  # profiles/ur5e.yaml's home, where both start
#: where the hand pushes the leader during episode 0, then episode 1
B = HOME + np.array([0.25, 0.15, -0.2, 0.1, 0.0, 0.3])
C = HOME + np.array([0.1, 0.05, -0.05, 0.05, 0.1, 0.1])
EPISODES = ((HOME, B), (B, C))
HAND = 0.5  # rad/s
HOLD_S = 0.8  # s: the leader held still at the start of each episode (a replay starts there)
EPISODE_S = 3
REPO = "local/crtk_ur5e"


class URArm:
    """A simulated UR5e under its daemon (``--sim``); ``q()``: the simulator's joint positions.
    ``series``: the controller's (the leader runs as a CB3, RTDE at 125 Hz: a quarter of the CPU an
    e-Series takes, on a host that runs both)."""

    def __init__(self, tmp: Path, name: str, series: str | None = None):
        self.tmp = tmp / name
        self.tmp.mkdir()
        self.socket = self.tmp / "d.sock"
        profile = UR5E
        if series is not None:
            data = yaml.safe_load(UR5E.read_text())
            data["backend"]["series"] = series
            profile = self.tmp / "ur5e.yaml"
            profile.write_text(yaml.safe_dump(data))
        self.daemon = DaemonProcess(["--profile", str(profile), "--sim"], self.socket, self.tmp / "daemon.log")
        self.sim = self.daemon.sim_control_path()

    def state(self) -> dict:
        reply = control_request(self.sim, {"cmd": "state"})
        assert reply["ok"], reply
        return reply

    def q(self) -> np.ndarray:
        return np.array(self.state()["q"])

    def ticks(self, register=None) -> dict:  # for rig.Sampler
        return dict(zip(JOINTS, self.q()))

    def close(self) -> None:
        self.daemon.stop()


@pytest.fixture(scope="module")
def urs(lerobot_venv, lerobot_plugin, lerobot_launcher, lerobot_reader):
    tmp = Path(tempfile.mkdtemp(prefix="crtk-lrur-"))
    arms = []
    try:
        follower = URArm(tmp, "follower")
        arms.append(follower)
        leader = URArm(tmp, "leader", series="cb3")
        arms.append(leader)
        client = connect(socket=str(leader.socket))  # freedrive: enabled, then free (you do this)
        arm = client.device("ur5e")
        assert arm.enable(20.0)
        arm.free()
        wait_until(lambda: leader.state()["teach_mode"], 5, what="the leader in teach mode")
        yield {"venv": lerobot_venv, "plugin": lerobot_plugin, "tmp": tmp, "follower": follower, "leader": leader,
               "root": tmp / "dataset", "recorded": None, "client": client, "reader": lerobot_reader,
               "launcher": lerobot_launcher}
        client.close()
    finally:
        for a in arms:
            a.close()
        shutil.rmtree(tmp, ignore_errors=True)


def args(urs) -> list[str]:
    return ["--robot.type=crtk", f"--robot.socket={urs['follower'].socket}", "--robot.units=si"]


def test_record_on_the_ur5e_in_si_units(urs):
    log = urs["tmp"] / "record.log"
    proc = run_lerobot(urs["launcher"], "lerobot-record", [
        *args(urs), "--teleop.type=crtk", f"--teleop.socket={urs['leader'].socket}", "--teleop.units=si",
        f"--dataset.repo_id={REPO}", f"--dataset.root={urs['root']}", "--dataset.num_episodes=2", "--dataset.fps=30",
        f"--dataset.episode_time_s={EPISODE_S}", "--dataset.reset_time_s=1", "--dataset.single_task=reach",
        "--dataset.push_to_hub=false", "--dataset.video=false", "--play_sounds=false", "--display_data=false"], log)
    try:
        for k, (_start, end) in enumerate(EPISODES):
            wait_until(lambda: f"Recording episode {k}" in log.read_text(errors="replace") or proc.poll() is not None,
                       240, what=f"lerobot-record's episode {k}")
            time.sleep(HOLD_S)  # the person holds the leader still a moment, then moves it
            reply = control_request(urs["leader"].sim, {"cmd": "hand", "q": list(end), "speed": HAND})
            assert reply["ok"], reply
        rc = finish(proc, log)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert rc == 0, tail(log)
    data = read_dataset(urs["reader"], urs["root"], REPO)
    assert data["action_names"] == KEYS and data["state_names"] == KEYS, data
    episodes = np.array(data["episode_index"])
    actions, states = np.array(data["action"]), np.array(data["observation.state"])
    tol = np.full(6, 2e-3)  # rad: the controller's reported positions, within its tracking
    for k, (s, e) in enumerate(EPISODES):
        act, obs = actions[episodes == k], states[episodes == k]
        assert len(act) >= 30, (k, len(act))
        assert np.all(on_the_way(act, s, e, tol)), (k, act[~on_the_way(act, s, e, tol)][:3])
        np.testing.assert_allclose(act[-1], e, atol=2e-3, err_msg=f"episode {k}: the leader's last position")
        assert np.all(on_the_way(obs, s, e, tol + 0.02)), (k, obs[~on_the_way(obs, s, e, tol + 0.02)][:3])
        np.testing.assert_allclose(obs[-1], e, atol=0.01, err_msg=f"episode {k}: the follower's last position")
    np.testing.assert_allclose(states[-1], urs["follower"].q(), atol=0.01)  # what the controller says now
    urs["recorded"] = data


def test_replay_on_the_ur5e_moves_it_along_the_recorded_positions(urs):
    if urs["recorded"] is None:
        pytest.fail("test_record_on_the_ur5e_in_si_units did not record (it failed first)")
    data = urs["recorded"]
    path = np.array(data["action"])[np.array(data["episode_index"]) == 0]
    start = urs["follower"].q()
    log = urs["tmp"] / "replay.log"
    sampler = Sampler(urs["follower"], 0.02)
    proc = run_lerobot(urs["launcher"], "lerobot-replay", [
        *args(urs), f"--dataset.repo_id={REPO}", f"--dataset.root={urs['root']}", "--dataset.episode=0",
        "--play_sounds=false"], log)
    try:
        rc = finish(proc, log)
        wait_until(lambda: np.allclose(urs["follower"].q(), path[-1], atol=5e-3), 10,
                   what="the follower at the episode's last action")
    finally:
        samples = sampler.stop()
        if proc.poll() is None:
            proc.kill()
    assert rc == 0, tail(log)
    q = np.array([[s[j] for j in JOINTS] for _, s in samples])
    d = polyline_distance(q, np.vstack([start, path]), np.ones(6))
    assert d.max() <= 0.02, (d.max(), q[d.argmax()])  # rad
    near_start = np.abs(q - path[0]).max(axis=1)
    first = int(np.argmax(near_start <= 5e-3))
    assert near_start[first] <= 5e-3, ("never at the episode's first action", near_start.min())
    assert np.abs(q[first:] - path[-1]).max(axis=1).min() <= 5e-3
