#!/usr/bin/env python3
"""Kinematics cost per call on the SO-101 arm (crtk_bridge.core.kinematics), for the cycle budget.

Times FK (``fk``, ``fk_matrix``), the Jacobian (spatial, body), ``twist``, and IK warm-started
from a nearby q (as ``servo_cp`` from the last setpoint: the target is FK of q + a small step)
and cold (from q = 0, random valid targets over the inner 80 % of each range). Prints the median
and p99 per call and each as a fraction of a 1 ms (1 kHz) and a 5 ms (200 Hz, the SO-101
profile's rate) cycle, plus IK iteration counts and success rates. Also the per-cycle cost of a
``servo_cv`` stream in the control process (core/twist.py: the twist mapped to joint velocities
at the setpoint, bounded, every cycle), as a fraction of the profile's cycle period. Figures only; nothing is
asserted (docs/architecture.md, "Performance targets": IK per cycle as a fraction of the cycle period, goal under 10 %). Usage:

    python bench/bench_kinematics.py [--calls 20000] [--ik-calls 3000]
"""

from __future__ import annotations

import argparse
import gc
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from crtk_bridge.core.actuator import Capabilities  # noqa: E402
from crtk_bridge.core.kinematics import Kinematics  # noqa: E402
from crtk_bridge.core.motion import NamespaceMotion  # noqa: E402
from crtk_bridge.core.twist import build_twist_motions  # noqa: E402
from crtk_bridge.profile import load_profile  # noqa: E402

URDF = ROOT / "profiles" / "urdf" / "so101.urdf"
ARM = ["shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll"]


def time_calls(fn, args_list) -> np.ndarray:
    """Per-call wall time (s) of fn(*args) for each args in args_list."""
    out = np.empty(len(args_list))
    clock = time.perf_counter
    for i, args in enumerate(args_list):
        t0 = clock()
        fn(*args)
        out[i] = clock() - t0
    return out


def row(name: str, t: np.ndarray, extra: str = "") -> None:
    med, p99 = np.median(t), np.percentile(t, 99)
    print(
        f"{name:<28} {med * 1e6:9.1f} {p99 * 1e6:9.1f}   "
        f"{med / 1e-3:7.1%} {p99 / 1e-3:7.1%}   {med / 5e-3:7.2%} {p99 / 5e-3:7.2%}  {extra}"
    )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--calls", type=int, default=20000, help="FK / Jacobian calls per figure")
    ap.add_argument("--ik-calls", type=int, default=3000, help="IK calls per figure")
    args = ap.parse_args(argv)

    kin = Kinematics(URDF, "base_link", "gripper_frame_link", ARM)
    rng = np.random.default_rng(0)
    lo, hi = kin.lower * 0.8, kin.upper * 0.8
    qs = [rng.uniform(lo, hi) for _ in range(args.calls)]
    qds = [rng.normal(size=5) for _ in range(args.calls)]

    # warm IK: from q toward FK(q + step), a step of a fast servo_cp stream (~1 rad/s at 1 kHz
    # would be 1 mrad; use 0.01 rad per joint, ten times that)
    warm = []
    for _ in range(args.ik_calls):
        q = rng.uniform(lo, hi)
        p, quat = kin.fk(np.clip(q + rng.normal(0, 0.01, 5), kin.lower, kin.upper))
        warm.append((p, quat, q))
    cold = []
    for _ in range(args.ik_calls):
        p, quat = kin.fk(rng.uniform(lo, hi))
        cold.append((p, quat, np.zeros(5)))

    gc.collect()
    gc.freeze()
    print(f"pinocchio kinematics, SO-101 arm (5 joints), {args.calls} FK/J calls, {args.ik_calls} IK calls")
    print(f"{'call':<28} {'med us':>9} {'p99 us':>9}   {'med/1ms':>7} {'p99/1ms':>7}   {'med/5ms':>7} {'p99/5ms':>7}")
    row("fk(q) -> pos, quat", time_calls(kin.fk, [(q,) for q in qs]))
    row("fk_matrix(q)", time_calls(kin.fk_matrix, [(q,) for q in qs]))
    row("jacobian(q, 'spatial')", time_calls(kin.jacobian, [(q, "spatial") for q in qs]))
    row("jacobian(q, 'body')", time_calls(kin.jacobian, [(q, "body") for q in qs]))
    row("twist(q, qd)", time_calls(kin.twist, [(q, qd) for q, qd in zip(qs, qds)]))
    row("wrench_from_efforts(q, tau)", time_calls(kin.wrench_from_efforts, [(q, qd) for q, qd in zip(qs, qds)]))
    twists = [np.concatenate([rng.normal(0, 0.05, 3), rng.normal(0, 0.2, 3)]) for _ in range(args.calls)]
    row("joint_velocity(q, twist)", time_calls(kin.joint_velocity, list(zip(qs, twists))))
    cycle_cost = bench_twist_cycle(args.calls, rng)

    for name, cases, restarts in (
        ("ik warm (restarts=0)", warm, 0),
        ("ik cold from 0 (restarts=4)", cold, 4),
    ):
        iters, oks = [], 0

        def call(p, quat, q, _r=restarts):
            nonlocal oks
            oks += kin.ik(p, quat, q, restarts=_r)[1]
            iters.append(kin.last_iterations)

        t = time_calls(call, cases)
        it = np.array(iters)
        row(name, t, f"ok {oks / len(cases):.1%}, iterations med {np.median(it):.0f} p99 {np.percentile(it, 99):.0f}")
    far = [(p + np.array([1.0, 0.0, 0.0]), quat, q) for p, quat, q in warm[:300]]
    row("ik unreachable (1 m away)", time_calls(kin.ik, far))
    profile_rate, t = cycle_cost
    period = 1.0 / profile_rate
    print(f"per-cycle servo_cv mapping (TwistMotion.update + motion step) at profiles/so101.yaml's "
          f"{profile_rate:g} Hz: median {np.median(t) * 1e6:.1f} us = {np.median(t) / period:.2%} of the "
          f"{period * 1e3:g} ms period, p99 {np.percentile(t, 99) * 1e6:.1f} us = "
          f"{np.percentile(t, 99) / period:.2%}; at 1 kHz: median {np.median(t) / 1e-3:.1%}")
    return 0


def bench_twist_cycle(calls: int, rng) -> tuple[float, np.ndarray]:
    """One servo_cv stream on the so101 arm as the controller runs it: every cycle the twist is
    re-mapped at the setpoint and integrated (the motion step). Returns (profile rate, times)."""
    profile = load_profile(ROOT / "profiles" / "so101.yaml")
    spec = profile.namespace("so101")
    dt = 1.0 / profile.loop.rate_hz
    m = NamespaceMotion("so101", [profile.joint_index(j) for j in spec.joints], profile, dt, Capabilities())
    tm = build_twist_motions(profile, {"so101": m})["so101"]
    out = np.empty(calls)
    clock = time.perf_counter
    now = 1000.0
    for i in range(calls):
        if i % 200 == 0:  # a fresh start pose and twist now and then, inside the workspace
            m.reset(rng.uniform(m.pos_min * 0.5, m.pos_max * 0.5))
            tm.servo(np.concatenate([rng.normal(0, 0.03, 3), rng.normal(0, 0.1, 3)]), "spatial", now)
        now += dt
        m.last_cmd_time = now  # the stream keeps arriving (no watchdog stop mid-bench)
        t0 = clock()
        tm.update()
        m.step(now, m.setpoint_p)
        out[i] = clock() - t0
    return profile.loop.rate_hz, out


if __name__ == "__main__":
    sys.exit(main())
