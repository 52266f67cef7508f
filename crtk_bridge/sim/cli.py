"""``crtk-sim``: run a simulated device in the foreground until SIGTERM / SIGINT.

    crtk-sim feetech --profile profiles/so101.yaml --link /tmp/ttySIM [--control /tmp/sim.sock]
                     [--emulate-baud] [--torque-delay S] [--log-level info]
    crtk-sim dynamixel --profile profiles/koch.yaml --link /tmp/ttySIM [...same options]
    crtk-sim feetech --profile profiles/bimanual_so101.yaml --bus left --link /tmp/ttyLEFT
    crtk-sim canopen --profile profiles/canopen_2axis.yaml --link /tmp/ttyCAN [--control C]
                     [--interface slcan|socketcan --channel vcan0] [--enable-delay S]
    crtk-sim ur --profile profiles/ur5e.yaml --host 127.0.0.2 [--control /tmp/ur.ctl]
                [--series e-series|cb3] [--power-on-s S] [--brake-release-s S] [--unlock-delay-s S]
                [--tool-link /tmp/ttyGRIPPER [--tool-baud 115200]]

Day-one buses (what `crtk-bridge setup-servos` and `check --scan --all-bauds` meet on a new arm):

    crtk-sim feetech --profile P --empty --factory-servo    one unconfigured servo (id 1, factory rate)
    crtk-sim feetech --profile P --servo-baud 115200        the servos at another rate than the profile
    crtk-sim feetech --profile P --model 3=sts3250          servo 3 of another model

Prints one line once the port (and control socket) exist, then serves until signalled; exits 0
after removing the link and the control socket. Exit 2: bad arguments or profile; 1: the
simulator could not start (e.g. the link path is a regular file) or died.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys

from .. import __version__
from ..errors import CrtkBridgeError, ProfileError
from ..profile import load_profile, resolve_profile_arg
from . import simulator_class

_SIGNALS = {signal.SIGTERM, signal.SIGINT}
_HEALTH_CHECK_S = 0.5
#: --parent-pid: the simulator stops once it is no longer this process's child (its spawner died,
#: however: SIGKILL, or before PR_SET_PDEATHSIG took effect, or a spawner that never set it)
_parent_pid: int | None = None
#: --workdir: the spawner's folder for this simulator's link and control socket, removed (once
#: empty: several simulators may share it) when the simulator ends, so that a spawner killed
#: outright (SIGKILL: no clean-up of its own) leaves no folder behind
_workdir: str | None = None


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="crtk-sim", description="Run a wire-level device simulator.")
    p.add_argument("--version", action="version", version=f"crtk-sim {__version__}")
    sub = p.add_subparsers(dest="device", required=True, metavar="DEVICE")
    for device, what in (("feetech", "Feetech STS3215 servo bus on a pseudo-terminal"),
                         ("dynamixel", "Dynamixel X-series (Protocol 2.0) bus on a pseudo-terminal")):
        d = sub.add_parser(device, help=what)
        d.add_argument("--profile", required=True, help="robot profile (YAML); one servo per joint id")
        d.add_argument("--link", help="create this symlink to the pty (default: print the pty path)")
        d.add_argument("--emulate-baud", action="store_true",
                       help="delay replies by the wire time at the profile's baud rate")
        d.add_argument("--torque-delay", type=float, default=0.0, metavar="S",
                       help="a torque-on takes S seconds to take effect (a slow device; default 0)")
        d.add_argument("--empty", action="store_true",
                       help="start with no servo on the bus (add them with --factory-servo or the "
                            "control socket's add_servo)")
        d.add_argument("--factory-servo", action="append", nargs="?", const="", metavar="MODEL",
                       help="add a factory-fresh servo (id 1 at the factory baud rate; default model: "
                            "the vendor's usual); repeatable")
        d.add_argument("--servo-baud", type=int, metavar="BAUD",
                       help="the profile's servos sit at this rate instead of the profile's (a baud "
                            "rate mismatch)")
        d.add_argument("--model", action="append", default=[], metavar="ID=MODEL",
                       help="the servo with this id is of another model; repeatable")
    d = sub.add_parser("canopen", help="CiA 402 drives behind a simulated SLCAN USB-CAN adapter (pty)")
    d.add_argument("--profile", required=True, help="robot profile (YAML); one drive per joint node_id")
    d.add_argument("--link", help="create this symlink to the adapter's pty (default: print the pty path)")
    d.add_argument("--interface", default="slcan", choices=["slcan", "socketcan"],
                   help="slcan (default): a simulated USB-CAN adapter on a pty; socketcan: join --channel")
    d.add_argument("--channel", help="with --interface socketcan: the kernel CAN interface (e.g. vcan0)")
    d.add_argument("--enable-delay", type=float, default=0.0, metavar="S",
                   help="enable operation takes S seconds (a brake releasing; default 0)")
    u = sub.add_parser("ur", help="Universal Robots controller (UR5e): RTDE 30004, dashboard 29999, "
                                  "script 30003 on a loopback address")
    u.add_argument("--profile", required=True, help="robot profile (YAML): six joints, their limits and home")
    u.add_argument("--host", required=True,
                   help="address to serve on, e.g. 127.0.0.2 (the ports are fixed; 'auto': a free 127.0.0.N)")
    u.add_argument("--series", choices=["e-series", "cb3"],
                   help="controller generation: e-series (500 Hz) or cb3 (125 Hz); default: the "
                        "profile's backend.series, else e-series")
    u.add_argument("--power-on-s", type=float, default=0.3, metavar="S", help="power on -> IDLE (default 0.3)")
    u.add_argument("--brake-release-s", type=float, default=0.5, metavar="S",
                   help="brake release -> RUNNING (default 0.5)")
    u.add_argument("--unlock-delay-s", type=float, default=5.0, metavar="S",
                   help="a protective stop may be unlocked this long after it (default 5, as UR)")
    u.add_argument("--tool-link", metavar="PATH",
                   help="serve the tool flange's RS-485 on TCP 54321 (UR's tool communication), relayed "
                        "to the serial device PATH (e.g. a Robotiq gripper simulator's pty)")
    u.add_argument("--tool-baud", type=int, default=115200, metavar="BAUD",
                   help="the tool's serial rate (default 115200)")
    from ..registry import devices

    for device, backend in devices().items():  # another distribution's (crtk_bridge/registry.py)
        if device in sub.choices:
            continue
        d = sub.add_parser(device, help=f"the simulator registered for backend {backend!r}")
        d.add_argument("--profile", required=True, help="robot profile (YAML)")
        where = d.add_mutually_exclusive_group()
        where.add_argument("--link", help="create this symlink to its pty (a serial device)")
        where.add_argument("--host", help="serve on this loopback address (a device on TCP ports)")
    for d in sub.choices.values():  # every device's
        d.add_argument("--control", help="serve the JSON-lines control socket at this path")
        d.add_argument("--bus", help="with a several-bus profile (backends:), the bus to simulate")
        d.add_argument("--log-level", default="warning",
                       choices=["debug", "info", "warning", "error"], help="default: warning")
        d.add_argument("--parent-pid", type=int, metavar="PID",
                       help="stop when the process PID (the spawner, our parent) is gone")
        d.add_argument("--workdir", metavar="DIR",
                       help="the spawner's folder for the link and control socket: removed at exit once empty")
    return p


def _serve(sim, ready_line: str) -> int:
    """Print ``ready_line``, then wait for SIGTERM / SIGINT (signals already blocked) while
    ``sim.running``; stop it either way."""
    try:
        print(ready_line, flush=True)
        while True:
            if signal.sigtimedwait(_SIGNALS, _HEALTH_CHECK_S) is not None:
                return 0
            if not sim.running:
                print("crtk-sim: the simulator thread died (see the log above)", file=sys.stderr)
                return 1
            if _parent_pid is not None and os.getppid() != _parent_pid:
                print(f"crtk-sim: the process that started it (pid {_parent_pid}) is gone; stopping", file=sys.stderr)
                return 0
    finally:
        sim.stop()  # removes the link and the control socket
        if _workdir is not None:
            try:
                os.rmdir(_workdir)  # only once empty: another simulator's files keep it
            except OSError:
                pass


def _start_and_serve(build, ready_line) -> int:
    """``build()`` makes and starts the simulator; then :func:`_serve` it, announced by
    ``ready_line(sim)``. A failure to start is one line on stderr and the exit code (2: the
    profile or an option; 1: the simulator could not start)."""
    try:
        sim = build()
    except CrtkBridgeError as exc:
        print(f"crtk-sim: {exc}", file=sys.stderr)
        return 2 if isinstance(exc, ProfileError) else 1
    except OSError as exc:
        print(f"crtk-sim: cannot start the simulator: {exc}", file=sys.stderr)
        return 1
    return _serve(sim, ready_line(sim))


#: the devices with options of their own above; any other registered one gets the common options
_BUILTIN_DEVICES = ("feetech", "dynamixel", "canopen", "ur")


def _main_registered(Simulator, args, profile) -> int:
    """A simulator registered by another distribution (docs/architecture.md, "Adding a
    backend"): ``Simulator.from_profile(profile, link=... | host=..., control=...)``, then
    ``start()``; it has ``running``, ``port`` (its endpoint) and ``stop()``."""
    where = {"host": args.host} if args.host else {"link": args.link}

    def build():
        sim = Simulator.from_profile(profile, control=args.control, **where)
        sim.start()
        return sim

    return _start_and_serve(build, lambda sim: f"crtk-sim: {args.device} ready: port={sim.port} "
                                               f"control={sim.control_path or '-'}")


def _main_ur(args, profile) -> int:
    import numpy as np

    from .loopback import free_loopback_host
    from .ur import PORTS, URController, profile_options
    from .ur_robot import Limits, Timings

    def build():
        opts = profile_options(profile)
        host = free_loopback_host(PORTS.values()) if args.host == "auto" else args.host
        sim = URController(host, q0=opts["q0"], limits=Limits(np.array(opts["lower"]), np.array(opts["upper"])),
                           series=args.series or opts["series"], control=args.control,
                           timings=Timings(args.power_on_s, args.brake_release_s, args.unlock_delay_s),
                           tool_link=args.tool_link, tool_baud=args.tool_baud)
        sim.start()
        return sim

    return _start_and_serve(build, lambda sim: (
        f"crtk-sim: ur controller ready: host={sim.host} rtde=30004 dashboard=29999 "
        f"script=30003{' tool=54321' if sim.tool_link else ''} series={sim.series} "
        f"rate={sim.rate_hz:g}Hz control={sim.control_path or '-'}"))


def _day_one(sim, args) -> None:
    """Apply --empty, --model, --servo-baud, --factory-servo (in that order). Raises
    SimulatorError or ProfileError."""
    for sid in sim.ids if args.empty else ():
        sim.remove_servo(sid)
    for spec in args.model:
        sid, sep, model = spec.partition("=")
        if not sep or not sid.strip().isdigit():
            raise ProfileError(f"--model {spec!r}: expected ID=MODEL, e.g. 3=sts3250")
        sim.replace_model(int(sid), model.strip())
    if args.servo_baud is not None:
        code = sim.BAUD_CODES.get(args.servo_baud)
        if code is None:
            raise ProfileError(f"--servo-baud {args.servo_baud}: not a {sim.vendor} servo baud rate; "
                               f"valid: {', '.join(map(str, sorted(sim.BAUD_CODES)))}")
        for sid in sim.ids:
            sim.servo(sid).write("Baud_Rate", code)
    for model in args.factory_servo or ():
        sim.add_servo(model=model or None)


def main(argv: list[str] | None = None) -> int:
    global _parent_pid, _workdir
    args = _parser().parse_args(argv)
    _parent_pid, _workdir = args.parent_pid, args.workdir
    logging.basicConfig(level=args.log_level.upper(), format="crtk-sim: %(levelname)s %(message)s")
    try:
        args.profile = str(resolve_profile_arg(args.profile))  # a file, or a shipped profile's name
        profile = load_profile(args.profile)
    except ProfileError as exc:
        print(f"crtk-sim: {exc}", file=sys.stderr)
        return 2
    if profile.backends is not None or args.bus is not None:
        if args.bus not in profile.bus_names:
            print(f"crtk-sim: {args.profile}: --bus must name one of the profile's buses "
                  f"({', '.join(profile.bus_names) or 'it has one backend: leave --bus out'})", file=sys.stderr)
            return 2
        profile = profile.bus_profile(args.bus)  # one simulator per bus (a UR arm beside a gripper too)
    if args.device == "ur":  # signals blocked before any thread exists, as below
        signal.pthread_sigmask(signal.SIG_BLOCK, _SIGNALS)
        return _main_ur(args, profile)

    try:
        Simulator = simulator_class(args.device)
    except CrtkBridgeError as exc:
        print(f"crtk-sim: {exc}", file=sys.stderr)
        return 1

    # Block the signals before any thread exists, so every thread inherits the mask and only
    # sigtimedwait() below receives them: a clean, race-free shutdown path.
    signal.pthread_sigmask(signal.SIG_BLOCK, _SIGNALS)
    if args.device not in _BUILTIN_DEVICES:
        return _main_registered(Simulator, args, profile)
    if args.device == "canopen" and args.interface == "socketcan" and not args.channel:
        print("crtk-sim: --interface socketcan needs --channel (e.g. vcan0)", file=sys.stderr)
        return 2

    def build():
        if args.device == "canopen":
            sim = Simulator.from_profile(profile, link=args.link, control=args.control,
                                         interface=args.interface, channel=args.channel)
            sim.set_torque_delay(args.enable_delay)
        else:
            sim = Simulator.from_profile(
                profile, link=args.link, control=args.control, emulate_baud=args.emulate_baud)
            sim.set_torque_delay(args.torque_delay)
            _day_one(sim, args)
        sim.start()
        return sim

    if args.device == "canopen":
        return _start_and_serve(build, lambda sim: (
            f"crtk-sim: canopen bus ready: interface={sim.interface} channel={sim.port} "
            f"pty={sim.pty_path or '-'} control={sim.control_path or '-'} "
            f"nodes={','.join(map(str, sim.ids))} bitrate={sim.bitrate}"))
    return _start_and_serve(build, lambda sim: (
        f"crtk-sim: {args.device} bus ready: port={sim.port} pty={sim.pty_path} "
        f"control={sim.control_path or '-'} ids={','.join(map(str, sim.ids))} "
        f"baud={sim.baudrate}{' (emulated)' if sim.emulate_baud else ''}"))


if __name__ == "__main__":
    sys.exit(main())
