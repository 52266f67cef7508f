#!/usr/bin/env python3
"""CPU per cycle of the daemon's processes on each shipped profile's simulator, beside a bare loop
doing the same bus transactions with the vendor library alone, same run (issue 23, item 1).

For each profile, ``crtk-bridge --profile <profile> --sim`` runs through four windows of
``--window`` s: DISABLED idle, DISABLED streaming (one client subscribed to ``measured_js`` at the
loop rate), ENABLED idle (holding), ENABLED streaming (the subscription, and ``servo_jp`` at
``--servo-rate`` Hz of a target moving about the held position: STREAM_AMPLITUDE at STREAM_HZ). Each process's CPU (its threads' run time from /proc/<pid>/task/*/schedstat, in ns, over
the window: robust to a loaded host, unlike wall time) is printed apart: the control process, the
front (socket server), the UR backend's ur_rtde worker, the simulator; as a share of one core and
as microseconds per cycle of the profile's loop rate.

The bare loop, in a process of its own against a standalone simulator of the same kind, paced at
the profile's rate by sleeping to an absolute tick:

* canopen402: python-can's ``slcan`` and canopen, used as their documentation shows (defaults):
  per cycle one SYNC and RPDO1 (controlword, target position, mode) per drive; TPDO1 + TPDO2
  (statusword, position, mode display; velocity, torque) per drive answer every SYNC, decoded by
  canopen's notifier thread -- the backend's traffic;
* feetech (so101): the servo SDK's GroupSyncRead of the block the backend reads, and when ENABLED
  a GroupSyncWrite of Goal_Position;
* ur5e: ur_rtde's RTDEReceiveInterface read every controller package (500 Hz), as the backend's
  worker does; servo commands are not part of it (DISABLED and ENABLED alike);
* dynamixel (koch, openmanipulator_x): no bare loop (``-``).

``--old DIR`` runs another checkout (``git worktree add /tmp/old <commit>``) the same way, its
daemon alternating with this one's profile by profile, for a before/after from one run.
Figures only; nothing is asserted. Usage:

    python bench/bench_cpu.py [--profiles so101 canopen_2axis ur5e] [--window 4] [--old /tmp/old] [--repeat 3]
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parent.parent
TCK = os.sysconf("SC_CLK_TCK")
PHASES = ("DISABLED idle", "DISABLED streaming", "ENABLED idle", "ENABLED streaming")
ROLES = ("control", "front", "ur worker", "simulator")
BARE_KINDS = {"canopen402": "canopen", "feetech": "feetech", "ur": "ur"}


# -- /proc --------------------------------------------------------------------------------------

def cpu_s(pid: int) -> float:
    """CPU time of ``pid``'s threads (s), 0 when it is gone: the scheduler's run time in ns
    (/proc/<pid>/task/*/schedstat; utime + stime count whole clock ticks, 10 ms, too coarse for a
    few seconds' window of a process using a few per cent), else utime + stime."""
    try:
        total = 0
        for tid in os.listdir(f"/proc/{pid}/task"):
            try:
                total += int(Path(f"/proc/{pid}/task/{tid}/schedstat").read_text().split()[0])
            except (OSError, IndexError, ValueError):
                continue  # a thread that ended meanwhile
        if total:
            return total / 1e9
    except OSError:
        pass
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / TCK


def children() -> dict[int, list[int]]:
    kids: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                ppid = int(Path(f"/proc/{entry}/stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            kids.setdefault(ppid, []).append(int(entry))
    return kids


def cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
    except OSError:
        return ""


def roles(front: int) -> dict[str, list[int]]:
    """The daemon's processes by role: the front is ``front``; the simulator and the UR worker are
    known by their module; the multiprocessing resource tracker is left out; the rest of the
    front's children is the control process."""
    kids = children()
    out: dict[str, list[int]] = {r: [] for r in ROLES}
    out["front"].append(front)
    todo = list(kids.get(front, []))
    while todo:
        pid = todo.pop()
        todo += kids.get(pid, [])
        cmd = cmdline(pid)
        if "crtk_bridge.sim.cli" in cmd:
            out["simulator"].append(pid)
        elif "backends.ur.worker" in cmd:
            out["ur worker"].append(pid)
        elif "resource_tracker" in cmd:
            continue
        else:
            out["control"].append(pid)
    return out


def window(groups: dict[str, list[int]], seconds: float) -> dict[str, float]:
    """CPU share of one core per group over ``seconds``."""
    before = {g: sum(cpu_s(p) for p in pids) for g, pids in groups.items()}
    t0 = time.monotonic()
    time.sleep(seconds)
    dt = time.monotonic() - t0
    return {g: (sum(cpu_s(p) for p in pids) - before[g]) / dt for g, pids in groups.items()}


# -- the daemon ---------------------------------------------------------------------------------

def start_daemon(tree: Path, profile: str, tmp: Path) -> tuple[subprocess.Popen, Path]:
    sock = tmp / f"{profile}.sock"
    env = dict(os.environ, PYTHONPATH=str(tree))
    proc = subprocess.Popen([sys.executable, "-m", "crtk_bridge.cli", "--profile", str(tree / "profiles" / f"{profile}.yaml"),
                             "--sim", "--socket", str(sock), "--log-level", "ERROR"],
                            cwd=tree, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 60
    while not sock.exists():
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            raise RuntimeError(f"{tree}: {profile}: the daemon did not start")
        time.sleep(0.05)
    return proc, sock


def measure_daemon(tree: Path, profile: str, rate: float, args, tmp: Path) -> dict[str, dict[str, float]]:
    from crtk_bridge.client import connect

    proc, sock = start_daemon(tree, profile, tmp)
    out: dict[str, dict[str, float]] = {}
    try:
        time.sleep(args.settle)
        groups = roles(proc.pid)
        with connect(socket=str(sock), timeout=10.0) as robot:
            dev = robot.device()
            for phase in PHASES:
                if phase.startswith("ENABLED") and dev.operating_state() != "ENABLED":
                    if not dev.enable(20.0):
                        raise RuntimeError(f"{profile}: not ENABLED")
                    time.sleep(args.settle)
                stop = threading.Event()
                threads = []
                sub = None
                if phase.endswith("streaming"):
                    sub = dev.subscribe("measured_js", rate)
                    threads.append(threading.Thread(target=drain, args=(sub, stop), daemon=True))
                    if phase.startswith("ENABLED"):
                        threads.append(threading.Thread(target=servo, args=(dev, args.servo_rate, stop), daemon=True))
                    for t in threads:
                        t.start()
                    time.sleep(0.5)
                out[phase] = window(groups, args.window)
                stop.set()
                for t in threads:
                    t.join(5)
                if sub is not None:
                    sub.close()
            dev.disable(10.0)
    finally:
        proc.terminate()
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return out


def drain(sub, stop: threading.Event) -> None:
    while not stop.is_set():
        try:
            sub.get(timeout=0.2)
        except Exception:
            pass


#: the streamed motion: every joint STREAM_AMPLITUDE (rad, or m) about where it was held, at
#: STREAM_HZ: a target that changes every command (a held one is cheaper on backends that send
#: only a change, e.g. the UR's hold)
STREAM_AMPLITUDE = 0.01
STREAM_HZ = 0.5


def servo(dev, rate: float, stop: threading.Event) -> None:
    p0 = [float(x) for x in dev.measured_js()[0]]
    period = 1.0 / rate
    t0 = tick = time.monotonic()
    while not stop.is_set():
        offset = STREAM_AMPLITUDE * math.sin(2.0 * math.pi * STREAM_HZ * (tick - t0))
        dev.servo_jp([x + offset for x in p0])
        tick += period
        time.sleep(max(0.0, tick - time.monotonic()))


# -- the bare loops -----------------------------------------------------------------------------

def start_sim(kind: str, profile: Path, tmp: Path) -> tuple[subprocess.Popen, str]:
    control = tmp / f"bare-{kind}.ctl"
    if kind == "ur":
        where = ["--host", "auto"]
    else:
        link = tmp / f"bare-{kind}.tty"
        where = ["--link", str(link)]
    proc = subprocess.Popen([sys.executable, "-m", "crtk_bridge.sim.cli", kind, "--profile", str(profile), *where,
                             "--control", str(control)], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                            text=True)
    line = proc.stdout.readline()  # "crtk-sim: ... ready: ..."
    if "ready" not in line:
        proc.kill()
        raise RuntimeError(f"bare {kind}: the simulator did not start: {line!r}")
    if kind == "ur":
        host = next(w.split("=", 1)[1] for w in line.split() if w.startswith("host="))
        return proc, host
    return proc, str(link)


def measure_bare(kind: str, profile: Path, rate: float, args, tmp: Path) -> dict[str, float]:
    sim, where = start_sim(kind, profile, tmp)
    out = {}
    try:
        if kind == "ur":
            power_on(sim, where, tmp)
        for state in ("DISABLED", "ENABLED"):
            loop = subprocess.Popen([sys.executable, __file__, "--bare", kind, "--where", where, "--profile-file",
                                     str(profile), "--rate", str(rate), "--state", state], cwd=ROOT,
                                    stdout=subprocess.PIPE, text=True)
            if loop.stdout.readline().strip() != "ready":
                loop.kill()
                raise RuntimeError(f"bare {kind}: the loop did not start")
            time.sleep(args.settle)
            out[state] = window({"bare": [loop.pid], "simulator": [sim.pid]}, args.window)
            loop.terminate()
            loop.wait(10)
    finally:
        sim.terminate()
        sim.wait(10)
    return out


def power_on(sim, host: str, tmp: Path) -> None:
    import dashboard_client

    dash = dashboard_client.DashboardClient(host)
    dash.connect()
    dash.powerOn()
    time.sleep(1.0)
    dash.brakeRelease()
    time.sleep(1.0)
    dash.disconnect()


def bare_loop(kind: str, where: str, profile_file: str, rate: float, enabled: bool) -> None:
    """The bare loop itself (a child process): prints ``ready``, then runs until SIGTERM."""
    data = yaml.safe_load(Path(profile_file).read_text())
    period = 1.0 / rate
    if kind == "canopen":
        import canopen

        from crtk_bridge.sim.canopen402 import make_object_dictionary

        ids = [int(j["node_id"]) for j in data["joints"]]
        net = canopen.Network()
        net.connect(interface="slcan", channel=where, bitrate=data["backend"].get("bitrate", 1000000),
                    sleep_after_open=0)
        nodes = []
        for nid in ids:
            node = canopen.RemoteNode(nid, make_object_dictionary(nid))
            net.add_node(node)
            node.tpdo.read()
            node.rpdo.read()
            for pdo, objs in ((node.tpdo[1], (0x6041, 0x6064, 0x6061)), (node.tpdo[2], (0x606C, 0x6077)),
                              (node.rpdo[1], (0x6040, 0x607A, 0x6060))):
                pdo.clear()
                for o in objs:
                    pdo.add_variable(o)
                pdo.trans_type = 1
                pdo.enabled = True
            node.tpdo.save()
            node.rpdo.save()
            node.nmt.state = "OPERATIONAL"
            nodes.append(node)
        print("ready", flush=True)
        tick = time.perf_counter()
        cw = 0x0F if enabled else 0x06
        while True:
            tick += period
            time.sleep(max(0.0, tick - time.perf_counter()))
            net.sync.transmit()
            for node in nodes:
                rp = node.rpdo[1]
                rp.map[0].raw = cw
                rp.map[1].raw = node.tpdo[1].map[1].raw
                rp.map[2].raw = 8
                rp.transmit()
    elif kind == "feetech":
        from scservo_sdk import GroupSyncRead, GroupSyncWrite, PacketHandler, PortHandler

        from crtk_bridge.backends.feetech import tables

        ids = [int(j["id"]) for j in data["joints"]]
        port = PortHandler(where)
        port.openPort()
        port.setBaudRate(int(data["backend"]["baudrate"]))
        ph = PacketHandler(0)
        gsr = GroupSyncRead(port, ph, tables.PRESENT_BLOCK_START, tables.PRESENT_BLOCK_LEN)
        goal = tables.STS_CONTROL_TABLE["Goal_Position"].address
        gsw = GroupSyncWrite(port, ph, goal, 2)
        for sid in ids:
            gsr.addParam(sid)
            gsw.addParam(sid, [0, 8])
        print("ready", flush=True)
        tick = time.perf_counter()
        while True:
            tick += period
            time.sleep(max(0.0, tick - time.perf_counter()))
            gsr.txRxPacket()
            pos = [gsr.getData(sid, tables.PRESENT_BLOCK_START, 2) for sid in ids]
            if enabled:
                for sid, p in zip(ids, pos):
                    gsw.changeParam(sid, [p & 0xFF, p >> 8])
                gsw.txPacket()
    elif kind == "ur":
        import rtde_receive

        r = rtde_receive.RTDEReceiveInterface(where, 500.0)
        print("ready", flush=True)
        last = r.getTimestamp()
        while True:  # as the backend's worker: each new package, polled (ur_rtde has no wait)
            ts = r.getTimestamp()
            if ts != last:
                last = ts
                r.getActualQ(), r.getActualQd(), r.getActualTCPPose()
            else:
                time.sleep(0.0001)


# -- main ---------------------------------------------------------------------------------------

def backend_kind(profile_path: Path) -> tuple[str, float]:
    data = yaml.safe_load(profile_path.read_text())
    rate = float((data.get("loop") or {}).get("rate_hz") or 0)
    if data["backend"]["type"] == "ur" and not rate:
        rate = 500.0
    return data["backend"]["type"], rate


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--profiles", nargs="+", default=["so101", "koch", "canopen_2axis", "ur5e"])
    ap.add_argument("--window", type=float, default=4.0, help="seconds per figure (default 4)")
    ap.add_argument("--settle", type=float, default=1.0)
    ap.add_argument("--servo-rate", type=float, default=100.0)
    ap.add_argument("--old", type=Path, help="another checkout, measured the same way in the same run")
    ap.add_argument("--repeat", type=int, default=1,
                    help="daemon runs per profile and tree, alternating; each figure is their median (default 1)")
    ap.add_argument("--no-bare", action="store_true")
    ap.add_argument("--bare", help=argparse.SUPPRESS)
    ap.add_argument("--where", help=argparse.SUPPRESS)
    ap.add_argument("--profile-file", help=argparse.SUPPRESS)
    ap.add_argument("--rate", type=float, help=argparse.SUPPRESS)
    ap.add_argument("--state", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.bare:
        bare_loop(args.bare, args.where, args.profile_file, args.rate, args.state == "ENABLED")
        return 0
    sys.path.insert(0, str(ROOT))
    trees = [("new", ROOT)] + ([("old", args.old.resolve())] if args.old else [])
    load = [os.getloadavg()[0]]
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-cpu-") as tmp:
        for profile in args.profiles:
            kind, rate = backend_kind(ROOT / "profiles" / f"{profile}.yaml")
            runs: dict[str, list] = {name: [] for name, _ in trees}
            for k in range(args.repeat):
                for name, tree in trees if (len(rows) + k) % 2 == 0 else list(reversed(trees)):
                    runs[name].append(measure_daemon(tree, profile, rate, args, Path(tmp)))
                    load.append(os.getloadavg()[0])
            for name, _ in trees:
                for phase in PHASES:
                    med = {g: statistics.median(r[phase][g] for r in runs[name]) for g in ROLES}
                    rows.append((profile, rate, name, phase, med, os.getloadavg()[0]))
            bare = BARE_KINDS.get(kind)
            if bare and not args.no_bare:
                res = measure_bare(bare, ROOT / "profiles" / f"{profile}.yaml", rate, args, Path(tmp))
                for state, r in res.items():
                    rows.append((profile, rate, "bare", f"{state} (vendor library alone)",
                                 {"control": r["bare"], "simulator": r["simulator"]}, os.getloadavg()[0]))
    print(f"CPU per cycle, share of one core (us per cycle at the loop rate); window {args.window:g} s"
          + (f", median of {args.repeat} daemon runs" if args.repeat > 1 else ""))
    head = f"{'profile':<14} {'tree':<5} {'phase':<36}" + "".join(f"{r:>22}" for r in ROLES) + "  load"
    print(head)
    for profile, rate, name, phase, r, ld in rows:
        cells = "".join(f"{r[g] * 100:8.1f}% ({r[g] / rate * 1e6:6.0f}us)" if g in r and (r[g] or name != "bare")
                        else f"{'-':>22}" for g in ROLES)
        print(f"{profile + f' {rate:g}Hz':<14} {name:<5} {phase:<36}{cells}  {ld:.1f}")
    print(f"load average (1 min) from {min(load):.2f} to {max(load):.2f} on {os.cpu_count()} cores; "
          "target: control <= 10 % of one core, and <= 1.5x the bare loop")
    return 0


if __name__ == "__main__":
    sys.exit(main())
