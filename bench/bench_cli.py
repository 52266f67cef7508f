#!/usr/bin/env python3
"""How fast ``crtk-ctl`` answers (issue 23, item 4: ``state``, ``get measured_js`` and ``enable``
on the SO-101 ``--sim`` each within 0.15 s wall time), beside a bare ``python -c pass`` in the
same run.

Each command runs in a fresh interpreter as the installed ``crtk-ctl`` script runs it (``from
crtk_bridge.client.cli import main``) against one ``crtk-bridge --profile so101.yaml --sim``;
the commands take turns (pass, --version, state, get measured_js, enable, disable, ...), N
rounds. Printed per command: the median and the worst wall time, and the median CPU (user + sys
of the child, from wait4: robust to a loaded host, where wall time is not). ``--old DIR`` times
another checkout's crtk-ctl (e.g. ``git worktree add /tmp/old <commit>``) against the same
daemon, in the same rounds, for a before/after from one run.

Bytecode is compiled first and the children may use it, as an installed package does (``pip
install`` compiles it): a host that sets PYTHONDONTWRITEBYTECODE and has no ``__pycache__``
compiles every module at every start instead. Figures only; nothing is asserted. Usage:

    python bench/bench_cli.py [--rounds 15] [--old /tmp/old]
"""

from __future__ import annotations

import argparse
import compileall
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import sim_daemon  # noqa: E402  (bench/, beside this script)

#: what the crtk-ctl console script does
CTL = "import sys; from crtk_bridge.client.cli import main; sys.exit(main())"


def run(argv: list[str], env: dict, cwd: Path) -> tuple[float, float, int]:
    """Run ``argv``; returns (wall s, child CPU s, exit status)."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(argv, env=env, cwd=cwd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        sys.stderr.write(f"{' '.join(argv[-3:])}: exit {proc.returncode}: {proc.stderr.read().decode()[:200]}\n")
    proc.stderr.close()
    return wall, usage.ru_utime + usage.ru_stime, proc.returncode


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=15)
    ap.add_argument("--old", type=Path, help="another checkout whose crtk-ctl is timed beside this one")
    args = ap.parse_args()

    trees = {"new": ROOT} | ({"old": args.old.resolve()} if args.old else {})
    for tree in trees.values():
        compileall.compile_dir(str(tree / "crtk_bridge"), quiet=1)
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    rate = yaml.safe_load((ROOT / "profiles" / "so101.yaml").read_text())["loop"]["rate_hz"]
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="bench-cli-") as tmp:
        daemon, sock = sim_daemon.start(rate, Path(tmp))
        try:
            cases = [("python -c pass", None, ["-c", "pass"])]
            for name, tree in trees.items():
                for cmd in (["--version"], ["state"], ["get", "measured_js"], ["enable"], ["disable"]):
                    label = f"crtk-ctl {' '.join(cmd)}" + (f" ({name})" if len(trees) > 1 else "")
                    cases.append((label, tree, ["-c", CTL, "--socket", str(sock), *cmd]))
            walls: dict[str, list[float]] = {c[0]: [] for c in cases}
            cpus: dict[str, list[float]] = {c[0]: [] for c in cases}
            for r in range(args.rounds + 1):  # round 0 warms the page cache and is not counted
                for label, tree, argv in cases:
                    e = dict(env, PYTHONPATH=str(tree)) if tree else env
                    wall, cpu, _ = run([sys.executable, *argv], e, tree or ROOT)
                    if r:
                        walls[label].append(wall)
                        cpus[label].append(cpu)
        finally:
            daemon.terminate()
            daemon.wait(timeout=30)
    base = statistics.median(walls["python -c pass"])
    print(f"crtk-ctl on the SO-101 --sim ({rate:g} Hz), {args.rounds} rounds, commands taking turns")
    print(f"{'command':<34} {'wall p50':>9} {'wall max':>9} {'cpu p50':>9} {'p50 - bare':>11}")
    for label, _, _ in cases:
        w, c = walls[label], cpus[label]
        print(f"{label:<34} {statistics.median(w) * 1e3:7.0f}ms {max(w) * 1e3:7.0f}ms "
              f"{statistics.median(c) * 1e3:7.0f}ms {(statistics.median(w) - base) * 1e3:9.0f}ms")
    print(f"load average (1 min) at start {load_before:.2f}, at end {os.getloadavg()[0]:.2f} on "
          f"{os.cpu_count()} cores; target: state, get measured_js, enable each <= 150 ms wall")
    return 0


if __name__ == "__main__":
    sys.exit(main())
