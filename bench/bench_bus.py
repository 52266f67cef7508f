#!/usr/bin/env python3
"""Bus cost per cycle on the simulated serial-servo buses, at an emulated baud rate.

For each bus -- Feetech STS3215 (SO-101 profile), Dynamixel X with Fast Sync Read and with plain
Sync Read (Koch v1.1 profile) -- runs the backend's real-time cycle (one ``read`` + one
``write`` of position goals) back to back against the simulator started with ``emulate_baud``
(each reply leaves no earlier than the request and reply would take on a real wire), and
reports:

* bytes per cycle, counted at the client's port (written + read), split read / write;
* the wire-time limit: baud / (10 bits x bytes per cycle), the rate the byte count allows
  (servo turnaround excluded: both backends configure Return_Delay_Time = 0);
* the achieved cycle rate and its ratio to that limit (docs/architecture.md, "Performance targets": >= 90 % at 1 Mbps).

Figures only; nothing is asserted. Usage:

    python bench/bench_bus.py [--cycles 2000] [--baud 1000000]
"""

from __future__ import annotations

import argparse
import copy
import sys
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from crtk_bridge.backends import create_backend  # noqa: E402
from crtk_bridge.core.actuator import CommandMode  # noqa: E402
from crtk_bridge.profile import parse_profile  # noqa: E402


def _count_bytes(port, counter: dict) -> None:
    """Wrap a port handler's readPort / writePort to count the bytes that cross it."""
    read, write = port.readPort, port.writePort

    def counted_read(n):
        data = read(n)
        counter[counter["phase"] + "_rx"] += len(data)
        return data

    def counted_write(pkt):
        sent = write(pkt)
        counter[counter["phase"] + "_tx"] += sent
        return sent

    port.readPort, port.writePort = counted_read, counted_write


def run(label: str, profile_file: str, sim_cls, backend_keys: dict, cycles: int, baud: int) -> dict:
    data = yaml.safe_load((ROOT / "profiles" / profile_file).read_text())
    data = copy.deepcopy(data)
    data["backend"]["baudrate"] = baud
    data["backend"].update(backend_keys)
    sim = sim_cls.from_profile(parse_profile(data), emulate_baud=True)
    sim.start()
    try:
        data["backend"]["port"] = sim.port
        b = create_backend(parse_profile(data))
        b.open()
        b.configure()
        fb, cmd = b.new_feedback(), b.new_command()
        b.enable(fb)
        cmd.mode[:] = CommandMode.POSITION
        counter = {"phase": "read", "read_rx": 0, "read_tx": 0, "write_rx": 0, "write_tx": 0}
        _count_bytes(b._port, counter)
        for _ in range(50):  # warm up
            b.read(fb)
            b.write(cmd)
        for k in counter:
            if k != "phase":
                counter[k] = 0
        faults = 0
        t0 = time.perf_counter()
        for k in range(cycles):
            counter["phase"] = "read"
            faults += b.read(fb) is not None
            counter["phase"] = "write"
            cmd.position[:] = 0.05 * ((k // 100) % 2)  # goals change: the writes are real
            faults += b.write(cmd) is not None
        elapsed = time.perf_counter() - t0
        b.close()
    finally:
        sim.stop()
    read_b = (counter["read_rx"] + counter["read_tx"]) / cycles
    write_b = (counter["write_rx"] + counter["write_tx"]) / cycles
    total = read_b + write_b
    limit = baud / (10 * total)
    rate = cycles / elapsed
    return {"label": label, "read": read_b, "write": write_b, "total": total, "limit": limit,
            "rate": rate, "ratio": rate / limit, "faults": faults}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cycles", type=int, default=2000)
    ap.add_argument("--baud", type=int, default=1_000_000)
    args = ap.parse_args(argv)
    from crtk_bridge.sim.dynamixel import DynamixelSimulator
    from crtk_bridge.sim.feetech import FeetechSimulator

    rows = [
        run("feetech sts3215 x6 (sync read 56..70)", "so101.yaml", FeetechSimulator, {}, args.cycles, args.baud),
        run("dynamixel x6 fast sync read 126..135", "koch.yaml", DynamixelSimulator,
            {"fast_sync_read": "on"}, args.cycles, args.baud),
        run("dynamixel x6 sync read 126..135", "koch.yaml", DynamixelSimulator,
            {"fast_sync_read": "off"}, args.cycles, args.baud),
    ]
    print(f"emulated baud {args.baud}, {args.cycles} cycles of read + write (position goals)")
    print(f"{'bus':40s} {'read B':>7s} {'write B':>7s} {'B/cycle':>7s} {'limit Hz':>9s} "
          f"{'achieved Hz':>11s} {'ratio':>6s} {'faults':>6s}")
    for r in rows:
        print(f"{r['label']:40s} {r['read']:7.1f} {r['write']:7.1f} {r['total']:7.1f} {r['limit']:9.0f} "
              f"{r['rate']:11.0f} {r['ratio']:6.1%} {r['faults']:6d}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
