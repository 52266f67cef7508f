#!/usr/bin/env python3
"""A Robotiq 2F-85 on a UR5e's tool flange (profiles/ur5e_robotiq.yaml): the gripper bus's
achieved cycle rate beside its wire's limit at 115200 baud, and the UR's cycle rate with and
without the gripper in the robot, same run.

* **Wire limit**: the bytes of one Modbus RTU cycle of the backend, built with pymodbus's RTU
  framer as the backend builds them: a function 4 read of the three input words (request and
  reply) and a function 16 write of the three output words (request and reply), 11 bits a
  character (Modbus RTU: start, 8 data, parity or a second stop, stop) and the 3.5 characters of
  silence that end each frame. The backend writes only when the request changed, so a cycle that
  only reads is also given.
* **Achieved rates**: the robot built as ``--sim`` builds it (``daemon._simulate_buses``: the UR
  controller simulator, the gripper's simulator on a pty behind the UR simulator's tool port
  54321), run in this process by the cycle runner around the controller, as the control
  process does (SCHED_FIFO where permitted), ENABLED, for ``--seconds``: the gripper following a
  servo_jp stream (a sine of 2 cm at 1 Hz: a write nearly every cycle of its bus) while the arm
  holds. Figures: the loop's cycles per second, the RTDE packages the UR backend missed
  (``missed_packets``) and the loop's overruns; the gripper bus's own cycles per second
  (served at its own rate: ``CompositeActuator.own_rate_cycles``). Then the UR alone
  (profiles/ur5e.yaml, its own simulator) the same way, in ``--rounds`` alternating rounds.

Figures only; nothing is asserted. Usage:

    python bench/bench_robotiq.py [--seconds 5] [--rounds 2]
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from pymodbus.framer import FramerRTU  # noqa: E402
from pymodbus.pdu import DecodePDU  # noqa: E402
from pymodbus.pdu.register_message import (ReadInputRegistersRequest,  # noqa: E402
                                           WriteMultipleRegistersRequest)

from crtk_bridge import daemon  # noqa: E402
from crtk_bridge.backends import backend_class, create_backend  # noqa: E402
from crtk_bridge.backends.robotiq import tables as T  # noqa: E402
from crtk_bridge.core.actuator import effective_period_s  # noqa: E402
from crtk_bridge.core.control import Controller  # noqa: E402
from crtk_bridge.core.cycle import CycleRunner  # noqa: E402
from crtk_bridge.profile import load_profile  # noqa: E402
from crtk_bridge.sim.control import control_request  # noqa: E402

UR_ROBOTIQ = ROOT / "profiles" / "ur5e_robotiq.yaml"
UR_ALONE = ROOT / "profiles" / "ur5e.yaml"
QUICK = {"cmd": "timings", "power_on_s": 0.1, "brake_release_s": 0.1, "unlock_delay_s": 0.3}
BITS = 11  # a Modbus RTU character on the wire
GAP = 3.5  # characters of silence after each frame


def wire_limit(baud: int) -> dict:
    framer = FramerRTU(DecodePDU(False))
    read = len(framer.buildFrame(ReadInputRegistersRequest(address=T.INPUT_ADDRESS, count=T.WORDS, dev_id=9)))
    read_reply = 3 + 2 * T.WORDS + 2  # id, fc, byte count, the words, CRC
    write = len(framer.buildFrame(WriteMultipleRegistersRequest(address=T.OUTPUT_ADDRESS, registers=[0] * T.WORDS,
                                                                dev_id=9)))
    write_reply = 8  # id, fc, address, count, CRC
    full = read + read_reply + write + write_reply
    full_s = (full + 4 * GAP) * BITS / baud
    read_s = (read + read_reply + 2 * GAP) * BITS / baud
    return {"read": (read, read_reply), "write": (write, write_reply), "bytes": full, "full_s": full_s,
            "read_only_s": read_s}


def realtime() -> str:
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(40))
        return "SCHED_FIFO 40"
    except (OSError, AttributeError) as exc:
        return f"not real-time ({exc})"


def build(path: Path, workdir: str, sims: list):
    """The robot of ``path`` on its simulators, wired as --sim wires it."""
    profile = load_profile(path)
    if profile.backends is not None:
        profile = daemon._simulate_buses(profile, str(path), workdir, sims, False)
    else:
        sim = daemon.SimulatorProcess(str(path), "ur", workdir, host_ports=(30004, 29999, 30003))
        sims.append(sim)
        profile = backend_class("ur").sim_profile(profile, sim.link)
    for sim in sims:
        if sim.link.startswith("127."):
            assert control_request(sim.control, QUICK).get("ok")
    act = create_backend(profile)
    act.open()
    act.configure()
    return profile, act


def run(path: Path, seconds: float) -> dict:
    sims: list = []
    workdir = tempfile.mkdtemp(prefix="bench-robotiq-")
    try:
        profile, act = build(path, workdir, sims)
        try:
            period = effective_period_s(profile, act)
            ctl = Controller(profile, act, time.time, period)
            runner = CycleRunner(act, period)
            runner.cycle(ctl)
            ctl.handle({"id": 1, "cmd": "enable"})
            end = time.monotonic() + 30
            while ctl.state.value != "ENABLED":
                runner.cycle(ctl)
                if time.monotonic() > end:
                    raise SystemExit(f"bench: {path.name} did not enable: {ctl.outbox[-3:]}")
            ur = act.parts[0] if hasattr(act, "parts") else act
            gripper = "ur5e/gripper" if "ur5e/gripper" in ctl.namespaces else None
            for _ in range(200):  # settle
                runner.cycle(ctl)
            missed0, over0 = ur.missed_packets, runner.overruns
            own0 = act.own_rate_cycles() if gripper else {}
            t0 = time.perf_counter()
            cycles = rid = 0
            while time.perf_counter() - t0 < seconds:
                if gripper and cycles % 5 == 0:
                    rid += 1
                    x = 0.05 + 0.02 * math.sin(2 * math.pi * (time.perf_counter() - t0))
                    ctl.handle({"id": 100 + rid, "cmd": "servo_jp", "ns": gripper, "data": {"position": [x]}})
                runner.cycle(ctl)
                cycles += 1
                if len(ctl.outbox) > 1000:
                    ctl.outbox.clear()
            dt = time.perf_counter() - t0
            out = {"rate": cycles / dt, "missed": ur.missed_packets - missed0, "overruns": runner.overruns - over0,
                   "cycles": cycles}
            if gripper:
                own1 = act.own_rate_cycles()
                out["gripper_rate"] = (own1["hand"] - own0["hand"]) / dt
            ctl.handle({"id": 2, "cmd": "disable"})
            end = time.monotonic() + 15
            while ctl.state.value != "DISABLED" and time.monotonic() < end:
                runner.cycle(ctl)
            return out
        finally:
            act.close()
    finally:
        for sim in sims:
            sim.stop()
        daemon._remove_dir(workdir)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--rounds", type=int, default=2)
    args = ap.parse_args()
    baud = int(load_profile(UR_ROBOTIQ).backends["hand"]["baudrate"])
    w = wire_limit(baud)
    print(f"wire at {baud} baud ({BITS} bits a character, {GAP} characters of silence a frame): "
          f"FC4 read {w['read'][0]} + {w['read'][1]} bytes, FC16 write {w['write'][0]} + {w['write'][1]} bytes "
          f"= {w['bytes']} bytes: {w['full_s'] * 1e3:.2f} ms a read + write cycle -> {1 / w['full_s']:.0f} Hz "
          f"at most ({1 / w['read_only_s']:.0f} Hz for a cycle that only reads)")
    print(f"loop: {realtime()}")
    rows: dict[str, list[dict]] = {"ur5e + robotiq": [], "ur5e alone": []}
    for _ in range(args.rounds):
        rows["ur5e + robotiq"].append(run(UR_ROBOTIQ, args.seconds))
        rows["ur5e alone"].append(run(UR_ALONE, args.seconds))
    for name, rs in rows.items():
        rate = statistics.median(r["rate"] for r in rs)
        line = (f"{name:15s}: UR cycle rate median {rate:.1f} Hz over {args.rounds} x {args.seconds:g} s; "
                f"missed RTDE packages {[r['missed'] for r in rs]}, overruns {[r['overruns'] for r in rs]}")
        if "gripper_rate" in rs[0]:
            g = statistics.median(r["gripper_rate"] for r in rs)
            line += (f"; gripper bus (own rate) {g:.1f} Hz = {g * w['full_s'] * 100:.0f} % of the read + write "
                     f"wire limit")
        print(line)
    both, alone = (statistics.median(r["rate"] for r in rows[k]) for k in rows)
    print(f"UR cycle rate with the gripper / without: {both / alone:.3f}")


if __name__ == "__main__":
    main()
