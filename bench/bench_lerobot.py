"""LeRobot's own SO101Follower against LeRobot through the plugin and the daemon (issue 21, Bench).

One simulated SO-101 bus (``crtk-sim feetech``, holding a LeRobot calibration as
``lerobot-calibrate`` leaves it), one run: the same 30 Hz action stream (an episode as a leader
arm records it: smooth hand motion read in whole ticks, LeRobot's units) is replayed as
``lerobot-replay`` replays (``get_observation()`` then ``send_action()`` each tick)

  (a) by LeRobot's own ``so101_follower`` writing the goals to the bus itself, then
  (b) by ``--robot.type=crtk`` through the daemon on the same bus (calibration imported from the
      same file, so the same numbers are the same ticks; ``command=interpolate``), once per
      ``loop.interpolation`` mode asked for (``--interpolation``, default all: linear, smooth,
      predict), each on a daemon of its own.

Meanwhile the simulator's registers are sampled (``dump`` on its control socket, every
``--sample-ms``) and reported per mode, all modes side by side: RMS jerk of the follower's motion (deg/s^3, on a 10 ms
grid of the positions averaged over 10 ms), both of the horn's simulated position
(``present_position_exact``: the motion itself) and of the Present_Position register (what an
encoder reads: its whole ticks alone read as about 80,000 deg/s^3 of jerk on that grid, whatever
the motion, so that figure cannot show a ratio above about 2), the largest step of the measured position and of the goal
register between two samples (one daemon bus cycle at the default 5 ms), the tracking lag (the
time shift that best aligns the measured trajectory with the actions as sent), and the time from
``send_action`` to the servo's Goal_Position register changing (a separate probe: single steps,
the register read in a tight loop). Then, per daemon mode, the smoothness gain (a)/(b) and the
extra lag (b)-(a). Medians over ``--runs`` runs; the load average is printed beside them.

Needs the LeRobot venv (tests/lerobot/venv.py builds it: ``python -m tests.lerobot.venv``) and
this checkout's plugin (installed into a temporary folder here). Run from the repository:

    python bench/bench_lerobot.py [--seconds 10] [--runs 3] [--interpolation linear smooth predict]
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import socket
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from tests.conftest import DaemonProcess  # noqa: E402
from tests.lerobot import venv as lrvenv  # noqa: E402
from tests.lerobot.conftest import LeRobotDriver  # noqa: E402
from tests.lerobot.rig import CALIBRATION, MOTORS, SO101, CalibratedArm, lerobot_reading  # noqa: E402

FPS = 30
MODES = ("linear", "smooth", "predict")  # loop.interpolation
JERK_S = 0.01  # s: the grid (and smoothing window) of the jerk figure
IDS = {m: c["id"] for m, c in CALIBRATION.items()}


def episode(seconds: float, seed: int = 7) -> list[dict[str, float]]:
    """A 30 Hz episode as a leader records it: each joint a smooth hand motion (two sines),
    read in whole servo ticks and converted as LeRobot converts them."""
    rng = np.random.default_rng(seed)
    n = int(seconds * FPS)
    t = np.arange(n) / FPS
    out = [dict() for _ in range(n)]
    for m, c in CALIBRATION.items():
        lo, hi = c["range_min"], c["range_max"]
        mid, span = (lo + hi) / 2, hi - lo
        amp = 0.12 * min(span, 2600)  # ticks: about 25 degrees on the arm, 12 % on the gripper
        f1, f2 = rng.uniform(0.2, 0.45), rng.uniform(0.5, 0.8)
        p1, p2 = rng.uniform(0, 2 * math.pi, 2)
        ticks = np.rint(mid + amp * (0.75 * np.sin(2 * math.pi * f1 * t + p1) + 0.25 * np.sin(2 * math.pi * f2 * t + p2)))
        for i, v in enumerate(ticks):
            out[i][f"{m}.pos"] = lerobot_reading(m, int(v))
    return out


class Control:
    """The simulator's control socket, one connection (one JSON line per request)."""

    def __init__(self, path: str):
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.sock.connect(path)
        self.f = self.sock.makefile("rwb")

    def __call__(self, **req) -> dict:
        self.f.write((json.dumps(req) + "\n").encode())
        self.f.flush()
        return json.loads(self.f.readline())

    def close(self) -> None:
        self.sock.close()


class Sampler(threading.Thread):
    """Every ``period`` s: (monotonic t, Present_Position by motor, Goal_Position by motor, the
    horn's unrounded position by motor) from one dump."""

    def __init__(self, control_path: str, period: float):
        super().__init__(daemon=True)
        self.control, self.period = Control(control_path), period
        self.rows: list[tuple[float, list[int], list[int]]] = []
        self.stop_event = threading.Event()

    def run(self) -> None:
        nxt = time.monotonic()
        while not self.stop_event.is_set():
            d = self.control(cmd="dump")
            t = d["clock"]  # when the simulator's physics were at these values (time.monotonic)
            servos = d["servos"]
            self.rows.append((t, [servos[str(IDS[m])]["present_position"] for m in MOTORS],
                              [servos[str(IDS[m])]["goal_position"] for m in MOTORS],
                              [servos[str(IDS[m])]["present_position_exact"] for m in MOTORS]))
            nxt += self.period
            self.stop_event.wait(max(0.0, nxt - time.monotonic()))

    def stop(self):
        self.stop_event.set()
        self.join(5)
        self.control.close()
        return self.rows


def to_units(ticks_rows: np.ndarray) -> np.ndarray:
    """Rows of ticks (by MOTORS) in LeRobot's units: degrees (arm), percent (gripper)."""
    return np.array([[lerobot_reading(m, v) for m, v in zip(MOTORS, row)] for row in ticks_rows])


def rms_jerk(pos: np.ndarray, period: float) -> float:
    """RMS jerk of the arm's joints (deg/s^3) on a JERK_S grid of the positions (sampled every
    ``period``) averaged over JERK_S."""
    k = max(1, round(JERK_S / period))
    smooth = np.stack([np.convolve(pos[:, j], np.ones(k) / k, mode="valid") for j in range(5)], axis=1)[::k]
    jerk = np.diff(smooth, n=3, axis=0) / (k * period) ** 3
    return float(np.sqrt(np.mean(jerk ** 2)))


def analyse(rows, sends: list[tuple[float, dict]], period: float) -> dict:
    t = np.array([r[0] for r in rows])
    present = to_units(np.array([r[1] for r in rows]))
    goal = to_units(np.array([r[2] for r in rows]))
    horn = to_units(np.array([r[3] for r in rows]))
    t0, t1 = sends[0][0], sends[-1][0]
    grid = np.arange(t0, t1, period)
    pos = np.stack([np.interp(grid, t, present[:, j]) for j in range(len(MOTORS))], axis=1)
    horn_pos = np.stack([np.interp(grid, t, horn[:, j]) for j in range(len(MOTORS))], axis=1)
    arm = slice(0, 5)
    steps = np.abs(np.diff(pos[:, arm], axis=0)).max()
    inwin = (t >= t0) & (t <= t1)
    goal_steps = np.abs(np.diff(goal[inwin][:, arm], axis=0)).max()
    # tracking lag: the shift of the sent actions (held until the next) that best matches the motion
    st = np.array([s[0] for s in sends])
    acts = np.array([[s[1][f"{m}.pos"] for m in MOTORS] for s in sends])
    best = (math.inf, 0.0)
    for lag_ms in range(0, 301):
        lag = lag_ms / 1000
        idx = np.searchsorted(st, grid - lag, side="right") - 1
        ok = idx >= 0
        err = np.sqrt(np.mean((pos[ok][:, arm] - acts[idx[ok]][:, arm]) ** 2))
        if err < best[0]:
            best = (err, lag)
    return {"rms_jerk": rms_jerk(horn_pos, period), "rms_jerk_register": rms_jerk(pos, period), "max_step": float(steps), "max_goal_step": float(goal_steps),
            "lag_ms": best[1] * 1000, "rms_error_at_lag": best[0]}


def goal_latency(driver: LeRobotDriver, control_path: str, base: dict[str, float], n: int) -> list[float]:
    """send_action -> Goal_Position: single steps of shoulder_pan (+-2 deg), the register read in a
    tight loop from the moment the request is written until it changes."""
    ctl = Control(control_path)
    out = []
    try:
        for k in range(n):
            action = dict(base)
            action["shoulder_pan.pos"] = base["shoulder_pan.pos"] + (2.0 if k % 2 == 0 else -2.0)
            before = ctl(cmd="read", id=IDS["shoulder_pan"], register="Goal_Position")["value"]
            driver.proc.stdin.write(json.dumps({"op": "act", "action": action}) + "\n")
            driver.proc.stdin.flush()
            deadline = time.monotonic() + 1.0
            changed = None
            while time.monotonic() < deadline:
                v = ctl(cmd="read", id=IDS["shoulder_pan"], register="Goal_Position")["value"]
                if v != before:
                    changed = time.monotonic()
                    break
                # not a busy loop: each read takes the simulator's lock, and on a loaded host a
                # tight loop of them starved its bus replies until the daemon faulted
                time.sleep(0.0005)
            reply = json.loads(driver.proc.stdout.readline())
            if not reply["ok"]:  # the probes end here; the figures so far stand
                print(f"bench_lerobot: send_action failed during the latency probes: {reply['error']}",
                      file=sys.stderr)
                break
            if changed is not None:
                out.append((changed - reply["t"]) * 1000)
            time.sleep(0.3)  # the arm settles on the new goal
    finally:
        ctl.close()
    return out


def replay(driver: LeRobotDriver, control_path: str, stream: list[dict], sample_s: float):
    driver("act", action=stream[0])  # to the episode's start, then let it settle
    time.sleep(2.0)
    sampler = Sampler(control_path, sample_s)
    sampler.start()
    time.sleep(0.2)
    sends, failed = [], 0
    nxt = time.monotonic()
    for action in stream:  # lerobot-replay's loop: observe, act, sleep out the period
        reply = driver.request("step", action=action)
        if not reply["ok"]:  # LeRobot's own bus read gave up (it would end lerobot-replay): counted
            failed += 1
            reply = driver("act", action=action)
        sends.append((reply["t"], reply["sent"]))
        nxt += 1 / FPS
        time.sleep(max(0.0, nxt - time.monotonic()))
    time.sleep(0.5)
    return sampler.stop(), sends, failed


def run_mode(mode: str, arm: CalibratedArm, venv: Path, plugin: Path | None, stream, args, log: Path,
             sock: Path | None = None) -> dict:
    driver = LeRobotDriver(venv, log, plugin)
    try:
        if mode == "direct":
            driver("connect", type="so101_follower", config={"port": arm.port, "id": arm.name,
                                                             "calibration_dir": str(arm.calibration_dir)})
        else:
            driver("connect", type="crtk", config={"socket": str(sock), "units": "lerobot"})
        rows, sends, failed = replay(driver, arm.sim, stream, args.sample_ms / 1000)
        figures = analyse(rows, sends, args.sample_ms / 1000)
        figures["failed_ticks"] = failed
        lat = goal_latency(driver, arm.sim, stream[-1], args.probes)
        figures["goal_ms"] = statistics.median(lat) if lat else math.nan
        figures["goal_ms_p90"] = float(np.percentile(lat, 90)) if lat else math.nan
        driver("disconnect")
        return figures
    finally:
        driver.close()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=10.0, help="episode length (s, at 30 Hz)")
    ap.add_argument("--runs", type=int, default=3, help="runs of each mode (medians reported)")
    ap.add_argument("--sample-ms", type=float, default=5.0, help="register sampling period (ms)")
    ap.add_argument("--probes", type=int, default=20, help="send_action -> goal register probes per run")
    ap.add_argument("--direct-only", action="store_true", help="only (a): LeRobot's own follower")
    ap.add_argument("--interpolation", nargs="+", choices=MODES, default=list(MODES),
                    help="the daemon profile's loop.interpolation modes to run, each on its own daemon "
                         "(default: all)")
    args = ap.parse_args()

    venv = lrvenv.ensure_venv()
    tmp = Path(tempfile.mkdtemp(prefix="crtk-bench-lr-"))
    try:
        plugin = None if args.direct_only else lrvenv.install_plugin(venv, tmp / "plugin")
        stream = episode(args.seconds)
        modes = [] if args.direct_only else list(dict.fromkeys(args.interpolation))
        results: dict[str, list[dict]] = {"direct": [], **{m: [] for m in modes}}
        loads = []
        for run in range(args.runs):
            arm = CalibratedArm(SO101, tmp, f"run{run}")
            try:
                loads.append(Path("/proc/loadavg").read_text().split()[0])
                results["direct"].append(run_mode("direct", arm, venv, None, stream, args, tmp / f"direct{run}.log"))
                for mode in modes:
                    data = yaml.safe_load(arm.imported_profile().read_text())
                    data.setdefault("loop", {})["interpolation"] = mode
                    profile = arm.tmp / f"imported-{mode}.yaml"
                    profile.write_text(yaml.safe_dump(data))
                    sock = arm.tmp / f"{mode}.sock"
                    arm.daemon = DaemonProcess(["--profile", str(profile)], sock, arm.tmp / f"daemon-{mode}.log")
                    try:
                        results[mode].append(run_mode("crtk", arm, venv, plugin, stream, args,
                                                      tmp / f"{mode}{run}.log", sock))
                    finally:
                        arm.daemon.stop()
                        arm.daemon = None
            finally:
                arm.close()
        loads.append(Path("/proc/loadavg").read_text().split()[0])
        keys = [("rms_jerk", "RMS jerk of the motion (horn, deg/s^3)"),
                ("rms_jerk_register", "RMS jerk of Present_Position (ticks, deg/s^3)"),
                ("max_step", "largest measured step per sample (deg)"),
                ("max_goal_step", "largest goal register step per sample (deg)"),
                ("lag_ms", "tracking lag (ms)"), ("rms_error_at_lag", "RMS error at that lag (deg)"),
                ("goal_ms", "send_action -> goal register, median (ms)"),
                ("goal_ms_p90", "send_action -> goal register, p90 (ms)"),
                ("failed_ticks", "ticks whose bus read failed (LeRobot would stop)")]
        med = {mode: {k: statistics.median(r[k] for r in rs) for k, _ in keys} for mode, rs in results.items()}
        print(f"bench_lerobot: {args.runs} run(s) x {args.seconds:g} s at {FPS} Hz, samples every {args.sample_ms:g} ms "
              f"(medians); load average (1 min) at each run's start and at the end: {' '.join(loads)}")
        cols = ["direct", *modes]
        print(f"{'':48s}" + "".join(f"{('(a) direct' if m == 'direct' else '(b) ' + m):>14s}" for m in cols))
        for k, label in keys:
            print(f"{label:48s}" + "".join(f"{med[m][k]:14.3f}" for m in cols))
        a = med["direct"]
        for m in modes:
            b = med[m]
            print(f"{m:8s}: smoothness (RMS jerk of the motion) gain (a)/(b) {a['rms_jerk'] / b['rms_jerk']:.1f}x "
                  f"(of Present_Position: {a['rms_jerk_register'] / b['rms_jerk_register']:.1f}x); "
                  f"extra lag (b)-(a): {b['lag_ms'] - a['lag_ms']:+.0f} ms; "
                  f"largest measured step {b['max_step']:.2f} deg (direct {a['max_step']:.2f})")
        print(f"(LeRobot's loop period: {1000 / FPS:.0f} ms; the daemon's loop period: 5 ms)")
        return 0
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
