#!/usr/bin/env python3
"""The CANopen CiA 402 backend's bus cycle, against a bare python-can baseline in the same run.

Two simulated drives (profiles/canopen_2axis.yaml, crtk_bridge.sim.canopen402) on a python-can
``virtual`` channel, in this process; a passive listener on the same channel timestamps every
frame (the virtual bus stamps a frame when it is sent). Reports:

* SYNC period jitter, |period - nominal| p50 / p99, of the backend driven by the real controller
  with core/loop.py's schedule (ENABLED, holding; the SYNC sent at the tick by the backend's
  ``wait_cycle``, then read -> step -> write), beside a
  bare ``bus.send_periodic`` of the same SYNC frame at the same rate on the same interface
  (python-can's own periodic thread). Alternated, ``--rounds`` times each; ratio = backend / bare.
* CAN frames per cycle in steady state, beside the minimum: 1 SYNC + RPDOs + TPDOs (heartbeats,
  the drives' and the master's own, counted apart: they are not cycle traffic).
* The highest loop rate (of a doubling sweep) with no missed TPDO over ``--seconds``.

Figures only; nothing is asserted. Usage:

    python bench/bench_canopen.py [--rate 250] [--seconds 3] [--rounds 2]
"""

from __future__ import annotations

import argparse
import os
import sys
import threading
import time
from pathlib import Path

import can
import msgspec
import numpy as np
import yaml

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from crtk_bridge.backends.canopen402.backend import Canopen402Backend  # noqa: E402
from crtk_bridge.core.control import Controller  # noqa: E402
from crtk_bridge.core.cycle import CycleRunner  # noqa: E402
from crtk_bridge.profile import parse_profile  # noqa: E402
from crtk_bridge.sim.canopen402 import CanopenSimulator  # noqa: E402

PROFILE = ROOT / "profiles" / "canopen_2axis.yaml"
SYNC = 0x80


class Tap(can.Listener):
    """Every frame on the channel: (time, id)."""

    def __init__(self):
        self.frames: list[tuple[float, int]] = []
        self.lock = threading.Lock()

    def on_message_received(self, msg: can.Message) -> None:
        with self.lock:
            self.frames.append((msg.timestamp, msg.arbitration_id))

    def take(self) -> list[tuple[float, int]]:
        with self.lock:
            out, self.frames = self.frames, []
        return out


def jitter(frames, period: float) -> np.ndarray:
    t = np.array([ts for ts, cid in frames if cid == SYNC])
    return np.abs(np.diff(t) - period) if len(t) > 2 else np.array([np.nan])


def rig(rate: float):
    data = yaml.safe_load(PROFILE.read_text())
    data["loop"]["rate_hz"] = rate
    profile = parse_profile(data, str(PROFILE))
    sim = CanopenSimulator.from_profile(profile, interface="virtual")
    sim.start()
    profile = msgspec.structs.replace(profile, backend={
        **profile.backend, "interface": "virtual", "channel": sim.port, "options": {}})
    backend = Canopen402Backend(profile)
    backend.open()
    backend.configure()
    c = Controller(profile, backend, time.time, 1.0 / rate)
    runner = CycleRunner(backend, 1.0 / rate)
    return sim, backend, c, runner, profile


def run_loop(c, backend, runner, period: float, seconds: float) -> None:
    """core/loop.py's cycle (core/cycle.py): the SYNC at the tick of the loop's schedule
    (``wait_cycle``), then read -> step -> write."""
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        runner.cycle(c)
        c.outbox.clear()


def enable(c, backend, runner, period: float) -> None:
    c.handle({"id": 1, "cmd": "enable"})
    deadline = time.monotonic() + 5
    while c.state.value != "ENABLED":
        assert time.monotonic() < deadline, "enable did not finish"
        run_loop(c, backend, runner, period, period)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rate", type=float, default=250.0)
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--sweep-from", type=float, default=125.0, help="first rate of the doubling sweep")
    args = ap.parse_args(argv)
    period = 1.0 / args.rate
    print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")

    sim, backend, c, runner, profile = rig(args.rate)
    tap_bus = can.Bus(interface="virtual", channel=sim.port)  # hears everyone but itself
    sender = can.Bus(interface="virtual", channel=sim.port)  # the bare periodic baseline
    tap = Tap()
    notifier = can.Notifier(tap_bus, [tap], timeout=0.05)
    sync_msg = can.Message(arbitration_id=SYNC, data=b"", is_extended_id=False)
    master_cob = 0x700 + backend.config.master_node_id
    # the bare master produces its heartbeat too (the drives watch it: 0x1016), on its own thread
    master_hb = can.Message(arbitration_id=master_cob, data=b"\x05", is_extended_id=False)
    try:
        enable(c, backend, runner, period)
        loop_j, bare_j, loop_frames = [], [], []
        for _ in range(args.rounds):  # alternate: loop, bare, loop, bare...
            tap.take()
            run_loop(c, backend, runner, period, args.seconds)
            frames = tap.take()
            loop_j.append(jitter(frames, period))
            loop_frames.append(frames)
            # the bare baseline: python-can's periodic SYNC (the drives answer it too; the
            # backend's loop is idle meanwhile, as a free-running master would be)
            task = sender.send_periodic(sync_msg, period)
            hb_task = sender.send_periodic(master_hb, backend.config.master_heartbeat_ms / 1000.0)
            time.sleep(args.seconds)
            task.stop()
            hb_task.stop()
            bare_j.append(jitter(tap.take(), period))
        lj, bj = np.concatenate(loop_j) * 1e3, np.concatenate(bare_j) * 1e3
        print(f"\nSYNC period jitter at {args.rate:g} Hz (|period - {period * 1e3:g} ms|), alternating "
              f"{args.rounds} x {args.seconds:g} s each:")
        print(f"  backend loop      p50 {np.nanpercentile(lj, 50):.3f} ms   p99 {np.nanpercentile(lj, 99):.3f} ms   "
              f"(n={len(lj)})")
        print(f"  bare send_periodic p50 {np.nanpercentile(bj, 50):.3f} ms   p99 {np.nanpercentile(bj, 99):.3f} ms   "
              f"(n={len(bj)})")
        print(f"  ratio backend / bare: p50 {np.nanpercentile(lj, 50) / max(np.nanpercentile(bj, 50), 1e-9):.2f}   "
              f"p99 {np.nanpercentile(lj, 99) / max(np.nanpercentile(bj, 99), 1e-9):.2f}")

        frames = [f for fs in loop_frames for f in fs]
        syncs = sum(1 for _, cid in frames if cid == SYNC)
        heartbeats = sum(1 for _, cid in frames if 0x700 <= cid < 0x780 and cid != master_cob)
        master = sum(1 for _, cid in frames if cid == master_cob)
        cycle = len(frames) - heartbeats - master
        rpdos = sum(2 if d.rpdo2 is not None else 1 for d in backend.drives)
        tpdos = 2 * backend.n
        minimum = 1 + rpdos + tpdos
        print(f"\nCAN frames per cycle (ENABLED, holding): {cycle / syncs:.2f}  "
              f"minimum {minimum} (1 SYNC + {rpdos} RPDOs + {tpdos} TPDOs)   "
              f"+ heartbeats: the drives' {heartbeats / syncs:.3f}, the master's {master / syncs:.3f} per cycle")
    finally:
        notifier.stop()
        tap_bus.shutdown()
        sender.shutdown()
        backend.close()
        sim.stop()

    print(f"\nhighest loop rate with no missed TPDO ({args.seconds:g} s each):")
    best = None
    rate = args.sweep_from
    while rate <= 8000:
        sim, backend, c, runner, _ = rig(rate)
        try:
            enable(c, backend, runner, 1.0 / rate)
            missed0, reads0 = backend.stats["tpdos_missed"], backend.stats["reads"]
            t0 = time.perf_counter()
            run_loop(c, backend, runner, 1.0 / rate, args.seconds)
            took = time.perf_counter() - t0
            missed = backend.stats["tpdos_missed"] - missed0
            reads = backend.stats["reads"] - reads0
            print(f"  {rate:6g} Hz: {reads / took:7.1f} cycles/s achieved, {missed} missed TPDO reads of {reads}")
            if missed == 0 and reads / took > 0.95 * rate:
                best = rate
            else:
                break
        finally:
            backend.close()
            sim.stop()
        rate *= 2
    print(f"  -> {best:g} Hz" if best else "  -> none of the rates tried")
    return 0


if __name__ == "__main__":
    sys.exit(main())
