"""``crtk-bridge``: run the daemon, or check a profile.

    crtk-bridge --profile FILE [--sim] [--socket PATH] [--log-level L] [--no-realtime]
                [--zenoh-connect ENDPOINT] [--zenoh-listen ENDPOINT] [--ros-domain-id N]
    crtk-bridge check --profile FILE [--scan [--all-bauds]] [--json]
    crtk-bridge find-port [--replug]
    crtk-bridge setup-servos --profile FILE [--yes] [--json] [--joint NAME]
    crtk-bridge init-profile NAME FILE [--force]

``--profile`` takes a file, or a shipped profile by name (``so101``, or ``profiles/so101.yaml`` as
README writes it from the clone's root, from any folder once installed: profile.resolve_profile_arg).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys

from . import __version__
from .argparsing import ArgumentParser
from .errors import CrtkBridgeError


def _run_parser() -> argparse.ArgumentParser:
    p = ArgumentParser(
        prog="crtk-bridge",
        usage="%(prog)s --profile FILE [--sim] [--socket PATH] [options]\n"
              "       %(prog)s check --profile FILE [--scan [--all-bauds]] [--json]\n"
              "       %(prog)s find-port [--replug]\n"
              "       %(prog)s setup-servos --profile FILE [--yes] [--json] [--joint NAME]\n"
              "       %(prog)s init-profile NAME FILE [--force]",
        description="Serve the CRTK robot API for the robot a profile describes.",
        epilog="commands:\n"
               "  check --profile FILE  validate a profile without opening the bus: every key, the\n"
               "                        backend section, and the kinematics where it names a URDF\n"
               "                        (frames and joints); exit 0 if valid. --scan also pings\n"
               "                        every id on the bus: model, firmware, torque of each\n"
               "                        servo; missing and extra ids; EEPROM settings that differ\n"
               "                        (register named); --all-bauds also the servos at other\n"
               "                        baud rates (exit 1 on a mismatch); --json: the findings as\n"
               "                        one JSON document (docs/check.md)\n"
               "  find-port [--replug]  list serial ports with their /dev/serial/by-id names and USB\n"
               "                        vendor / product / serial number; --replug names the one\n"
               "                        you unplug and plug back\n"
               "  setup-servos --profile FILE  one servo at a time, give each joint's servo its id\n"
               "                        and the profile's baud rate (see setup-servos --help)\n"
               "  init-profile NAME FILE  write FILE from the shipped profile NAME (so101, koch...),\n"
               "                        to edit for your arm (see init-profile --help)",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--profile", required=True,
                   help="robot profile (YAML), e.g. my_arm.yaml, or a shipped one by name: so101, "
                        "profiles/so101.yaml (crtk-bridge init-profile --help lists them)")
    p.add_argument("--sim", action="store_true", help="run on the built-in simulator instead of hardware")
    p.add_argument("--socket", help="Unix socket path (default: $XDG_RUNTIME_DIR/crtk-bridge/<robot>.sock)")
    z = p.add_argument_group("Zenoh transport (off unless an endpoint is given here or in the profile's "
                             "transport.zenoh; docs/zenoh.md)")
    z.add_argument("--zenoh-connect", metavar="ENDPOINT", action="append",
                   help="join the Zenoh router or peer at ENDPOINT, e.g. tcp/127.0.0.1:7447 (repeatable; "
                        "replaces transport.zenoh.connect)")
    z.add_argument("--zenoh-listen", metavar="ENDPOINT", action="append",
                   help="accept Zenoh peers and clients on ENDPOINT, e.g. tcp/127.0.0.1:7448 (repeatable; "
                        "replaces transport.zenoh.listen). Beyond loopback only as tls/ with "
                        "transport.zenoh.tls and transport.zenoh.access_control")
    z.add_argument("--ros-domain-id", metavar="N", type=int,
                   help="ROS_DOMAIN_ID of the ROS 2 graph (default: transport.zenoh.ros_domain_id, else 0)")
    p.add_argument("--record", metavar="DIR",
                   help="record every control cycle from start-up into rosbag2 MCAP bags in DIR, a new bag "
                        "every recording.rotate_s seconds (default 300), until the daemon stops; replaces "
                        "the profile's recording.dir (docs/recording.md)")
    p.add_argument("--foxglove-listen", metavar="HOST:PORT",
                   help="serve a read-only live view to Foxglove (WebSocket, the ROS 2 graph's topics and the "
                        "URDF), e.g. 127.0.0.1:8765; off by default. Beyond loopback only with transport.zenoh.tls "
                        "and transport.zenoh.access_control, as Zenoh; needs pip install 'crtk-bridge[foxglove]' "
                        "(docs/recording.md)")
    p.add_argument("--log-level", default="INFO", choices=["DEBUG", "INFO", "WARNING", "ERROR"])
    p.add_argument("--no-realtime", action="store_true", help="do not ask for SCHED_FIFO / mlockall")
    p.add_argument("--version", action="version", version=f"crtk-bridge {__version__}")
    return p


def _check(argv: list[str]) -> int:
    p = ArgumentParser(prog="crtk-bridge check", description="Validate a robot profile; exit 0 if valid.")
    p.add_argument("--profile", required=True)
    p.add_argument("--scan", action="store_true",
                   help="also open each bus (the daemon must not be running) and ping every id at "
                        "the profile's baud rate: report each servo's model, firmware and torque "
                        "state, the joints whose id did not answer, the ids no joint has, and the "
                        "EEPROM settings that differ from the profile and the backend (register "
                        "named: Homing_Offset, position limits, Return_Delay_Time, operating mode, "
                        "direction bits); exit 1 on any mismatch. Writes nothing to the servos")
    p.add_argument("--all-bauds", action="store_true",
                   help="with --scan: also ping at every other baud rate the servos support and "
                        "report the servos found there (exit 1; crtk-bridge setup-servos moves them)")
    p.add_argument("--json", action="store_true",
                   help="print the findings as one JSON document on stdout (and nothing else; keys in "
                        "docs/check.md); the exit status is the same")
    args = p.parse_args(argv)
    if args.all_bauds and not args.scan:
        p.error("--all-bauds needs --scan")
    from .backends import create_backend
    from .core.kinematics_check import check_kinematics
    from .profile import load_profile, resolve_profile_arg
    from .transport.zenoh_session import check_exposure, zenoh_config

    doc: dict = {"check_format": CHECK_FORMAT, "profile": args.profile, "ok": False, "valid": False, "error": None,
                 "robot": None, "backend": None, "joints": [], "namespaces": [], "kinematics": [],
                 "scan": None, "problems": []}
    try:
        profile = load_profile(resolve_profile_arg(args.profile))
        backend = create_backend(profile, source=args.profile)
        cartesian = check_kinematics(profile, args.profile)
        zenoh = zenoh_config(profile)
        if zenoh is not None:  # loopback, or TLS + access control (transport/zenoh_session.py)
            check_exposure(zenoh, profile.name)
    except CrtkBridgeError as exc:
        doc["error"] = str(exc)
        doc["problems"].append(str(exc))
        return _check_end(doc, args.json, 1)
    doc.update(valid=True, robot=profile.name, backend=profile.backend_type, joints=list(profile.joint_names),
               namespaces=[ns.name for ns in profile.namespaces], kinematics=list(cartesian or []))
    if not args.json:
        print(f"{args.profile}: valid profile for robot {profile.name!r} ({profile.backend_type}, "
              f"{len(profile.joints)} joints, namespaces {', '.join(ns.name for ns in profile.namespaces)}"
              f"{'; kinematics ' + ', '.join(cartesian) if cartesian else ''})")
    failed = False
    if args.scan:
        buses = _scan(profile, backend, args.profile, args.all_bauds, args.json)
        doc["scan"] = {"all_bauds": args.all_bauds, "buses": buses}
        doc["problems"] += [problem for bus in buses for problem in bus["problems"]]
        failed = any(not bus["ok"] for bus in buses)
    doc["ok"] = not failed
    return _check_end(doc, args.json, 1 if failed else 0)


#: ``check --json``'s document format; raised when a key changes meaning or goes (docs/check.md)
CHECK_FORMAT = 1


def _check_end(doc: dict, as_json: bool, status: int) -> int:
    """End ``check``: the JSON document (``--json``), else the profile error if any (the
    scan's lines are printed as it goes). Returns ``status``."""
    if as_json:
        print(json.dumps(doc, indent=2))
    elif doc["error"] is not None:
        print(f"crtk-bridge: {doc['error']}", file=sys.stderr)
    return status


def _scan(profile, backend, source: str, all_bauds: bool, quiet: bool = False) -> list[dict]:
    """``check --scan``: each bus's servos against the profile, one record each (``check
    --json``'s ``scan.buses``; ``ok`` false on any mismatch). Prints the report unless ``quiet``."""
    from .backends.optional import BusScanner, require

    if profile.backends is not None:
        buses = {bus: (part, str(profile.backends[bus]["type"])) for bus, part in zip(backend.bus_names, backend.parts)}
    else:
        buses = {"": (backend, profile.backend_type)}
    out = []

    def fail(rec: dict, message: str) -> None:
        rec.update(ok=False, error=message)
        rec["problems"].append(message)
        if not quiet:
            print(f"crtk-bridge: {message}", file=sys.stderr)

    for bus, (part, backend_type) in buses.items():
        where = f"backends.{bus}" if bus else "backend"
        rec = {"bus": bus or None, "where": where, "vendor": backend_type, "port": None,
               "baudrate": None, "ok": True, "error": None, "servos_answered": 0, "joints": [], "extra": [],
               "other_rates": [], "problems": []}
        out.append(rec)
        try:
            scanner = require(part, BusScanner, robot=profile.name, where=where, backend_type=backend_type)
        except CrtkBridgeError as exc:
            fail(rec, str(exc))
            continue
        baudrate, plan = scanner.scan_plan(all_bauds)
        rec.update(baudrate=baudrate, port=scanner.port_name)
        if not quiet:
            print(f"scanning {where} ({backend_type}) {plan}...", flush=True)
        try:
            found = scanner.scan(all_bauds=all_bauds)
        except CrtkBridgeError as exc:
            fail(rec, str(exc))
            continue
        bus_opt = f" --bus {bus}" if bus else ""
        lines, problems, findings = scanner.scan_report(
            found, f": run crtk-bridge setup-servos --profile {source}{bus_opt} with only that servo connected")
        rec.update(findings, port=scanner.port_name, ok=not problems, problems=problems)
        n = rec["servos_answered"]
        if quiet:
            continue
        print(f"{where}: {part.port_name}: {n} servo{'s' if n != 1 else ''} answered")
        for line in lines:
            print("  " + line)
        if problems:
            print(f"crtk-bridge: {profile.name}: {where} ({part.port_name}) does not match the profile: "
                  + "; ".join(problems), file=sys.stderr)
    return out


def _find_port(argv: list[str]) -> int:
    p = ArgumentParser(
        prog="crtk-bridge find-port",
        description="List serial ports: device, /dev/serial/by-id names, USB vendor:product, serial "
                    "number. Put a by-id path or {serial_number: ...} in the profile's backend.port "
                    "so that two arms never swap.")
    p.add_argument("--replug", action="store_true",
                   help="ask you to unplug the arm's adapter and plug it back, then name its port "
                        "(and its stable names)")
    args = p.parse_args(argv)
    from .backends.ports import find_replugged, list_serial_ports

    lister = list_serial_ports
    if args.replug:
        return 0 if find_replugged(lister, input, sys.stdout) is not None else 1
    ports = lister()
    if not ports:
        print("no serial ports found")
    for port in ports:
        print(port.describe())
    return 0


def _setup_servos(argv: list[str]) -> int:
    p = ArgumentParser(
        prog="crtk-bridge setup-servos",
        description="Give each joint's servo its id and the profile's baud rate, one servo at a time "
                    "(as lerobot-setup-motors): for each joint, in reverse profile order, connect ONLY "
                    "that joint's servo; it is found at any id and baud rate, its model checked, then "
                    "its ID, Return_Delay_Time and Baud_Rate written (persisted) and verified. The daemon "
                    "must not be running.",
        epilog="exit status: 0 every servo set up and verified; 1 error (profile, port, a write or its "
               "verification); 2 bad arguments; 3 refused: the servo found is of another model than "
               "the joint's; 4 --yes: no single new servo appeared within --timeout (none, several, "
               "or only the previous one); 130 interrupted",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--profile", required=True)
    p.add_argument("--bus", help="with a several-bus profile (backends:), the bus to set up")
    p.add_argument("--joint", action="append", default=[], metavar="NAME",
                   help="set up only this joint's servo (e.g. a replaced one); repeatable")
    p.add_argument("--yes", action="store_true",
                   help="no prompts (scripts): for each joint wait until exactly one new servo answers, "
                        "up to --timeout")
    p.add_argument("--timeout", type=float, default=60.0, metavar="S",
                   help="with --yes: seconds to wait for each joint's servo (default 60)")
    p.add_argument("--json", action="store_true",
                   help="one JSON object per line for each step, then a summary object")
    args = p.parse_args(argv)
    from .backends import create_backend
    from .backends.optional import DeviceSetup, require
    from .backends.servo_setup import EXIT_ERROR
    from .profile import load_profile, resolve_profile_arg

    def emit(event: dict) -> None:
        if args.json:
            print(json.dumps(event), flush=True)
        else:
            _print_setup_event(event, args.profile)

    try:
        profile = load_profile(resolve_profile_arg(args.profile, hardware=True))  # it writes EEPROM
        backend = create_backend(profile, source=args.profile)
        where, backend_type = "backend", profile.backend_type
        if profile.backends is not None:
            if args.bus not in profile.bus_names:
                p.error(f"--bus must name one of the profile's buses ({', '.join(profile.bus_names)})")
            backend = backend.parts[backend.bus_names.index(args.bus)]
            where, backend_type = f"backends.{args.bus}", str(profile.backends[args.bus]["type"])
        elif args.bus is not None:
            p.error("--bus: the profile has one backend; leave --bus out")
        backend = require(backend, DeviceSetup, robot=profile.name, where=where, backend_type=backend_type)
        unknown = [n for n in args.joint if n not in backend.joint_names]
        if unknown:
            p.error(f"--joint {unknown[0]}: not a joint of this bus ({', '.join(backend.joint_names)})")
    except CrtkBridgeError as exc:
        if args.json:
            emit({"event": "summary", "ok": False, "exit_code": EXIT_ERROR, "error": str(exc)})
        else:
            print(f"crtk-bridge: {exc}", file=sys.stderr)
        return EXIT_ERROR
    joints = [i for i, n in enumerate(backend.joint_names) if not args.joint or n in args.joint][::-1]
    ask = None if args.yes else (lambda prompt: input(prompt))
    return backend.setup_devices(joints, emit, ask, args.timeout)


def _print_setup_event(e: dict, source: str) -> None:
    kind = e["event"]
    if kind == "connect":
        print(f"[{e['index']}/{e['of']}] {e['joint']}: connect ONLY its servo ({e['model']}); it gets id "
              f"{e['id']} at {e['baudrate']} baud" + ("" if e["interactive"] else ". Waiting for it..."),
              flush=True)
    elif kind == "waiting":
        print(f"  waiting: {e['message']}", flush=True)
    elif kind == "found":
        print(f"  found {e['model'] or 'model number ' + str(e['model_number'])} at id {e['id']}, "
              f"{e['baudrate']} baud", flush=True)
    elif kind == "configured":
        ids = f"id {e['from_id']} -> {e['id']}" if e["from_id"] != e["id"] else f"id {e['id']} (kept)"
        rate = (f"{e['from_baudrate']} -> {e['baudrate']} baud" if e["from_baudrate"] != e["baudrate"]
                else f"{e['baudrate']} baud (kept)")
        print(f"  set up: {ids}, {rate} (wrote {', '.join(e['written'])}); verified", flush=True)
    elif kind == "summary":
        done = ", ".join(f"{r['joint']} id {r['id']}" for r in e.get("joints", []))
        if e["ok"]:
            print(f"{e['set_up']} of {e['of']} servos set up ({done}). Connect them all and check the bus: "
                  f"crtk-bridge check --profile {source} --scan", flush=True)
        else:
            if e.get("error"):
                print(f"crtk-bridge: {e['error']}", file=sys.stderr, flush=True)
            print(f"{e.get('set_up', 0)} of {e.get('of', '?')} servos set up{' (' + done + ')' if done else ''}; "
                  f"stopped (exit {e['exit_code']})", flush=True)


def _init_profile(argv: list[str]) -> int:
    from .profile import shipped_profile_names, shipped_profiles_dir

    names = shipped_profile_names()
    p = ArgumentParser(
        prog="crtk-bridge init-profile",
        description="Write a new profile FILE from a shipped one, comments included, to edit for your "
                    "arm (backend.port, calibration...). Its URDF stays the shipped one (a profile's "
                    "relative paths are looked up beside the profile file, then among the shipped "
                    "profiles).",
        epilog=f"shipped profiles: {', '.join(names)} (in {shipped_profiles_dir()})")
    p.add_argument("name", metavar="NAME", help="a shipped profile: " + ", ".join(names))
    p.add_argument("file", metavar="FILE", help="the profile to write, e.g. my_arm.yaml")
    p.add_argument("--force", action="store_true", help="overwrite FILE if it exists")
    args = p.parse_args(argv)
    name = args.name[:-5] if args.name.endswith(".yaml") else args.name
    if name not in names:
        p.error(f"NAME: no shipped profile {args.name!r} (shipped: {', '.join(names)})")
    from pathlib import Path

    target = Path(args.file).expanduser()
    if target.exists() and not args.force:
        print(f"crtk-bridge: {target} exists: give another FILE, or --force to overwrite it", file=sys.stderr)
        return 1
    text = (shipped_profiles_dir() / f"{name}.yaml").read_text()
    try:
        target.write_text(f"# Written by `crtk-bridge init-profile {name}` from the shipped profile {name} "
                          f"(crtk-bridge {__version__}).\n{text}")
    except OSError as exc:
        print(f"crtk-bridge: cannot write {target}: {exc.strerror or exc}", file=sys.stderr)
        return 1
    print(f"wrote {target} from the shipped profile {name}: set {_where_the_robot_is(text)}, then "
          f"crtk-bridge check --profile {args.file}")
    return 0


#: the backend keys that say where a robot of each backend type is found (default: ``port``)
_WHERE = {"ur": ("host",), "canopen402": ("interface", "channel")}


def _where_the_robot_is(text: str) -> str:
    """The keys to set in a profile written from the shipped ``text``: a serial bus's port, a UR's
    host, a CAN bus's interface and channel; each bus's own of a several-bus profile."""
    import yaml

    data = yaml.safe_load(text) or {}
    buses = data.get("backends")
    sections = ({f"backends.{bus}": section for bus, section in buses.items()} if isinstance(buses, dict) and buses
                else {"backend": data.get("backend") or {}})
    keys = [f"{where}.{key}" for where, section in sections.items()
            for key in _WHERE.get((section or {}).get("type"), ("port",))]
    serial = any((section or {}).get("type") not in _WHERE for section in sections.values())
    return " and ".join(keys) + (" (crtk-bridge find-port)" if serial and len(sections) == 1 else "")


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "init-profile":
        return _init_profile(argv[1:])
    if argv and argv[0] == "find-port":
        return _find_port(argv[1:])
    if argv and argv[0] == "check":
        return _check(argv[1:])
    if argv and argv[0] == "setup-servos":
        return _setup_servos(argv[1:])
    args = _run_parser().parse_args(argv)
    logging.basicConfig(level=args.log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    from .daemon import run
    from .profile import resolve_profile_arg

    try:
        profile = resolve_profile_arg(args.profile, hardware=not args.sim)
    except CrtkBridgeError as exc:
        print(f"crtk-bridge: {exc}", file=sys.stderr)
        return 1
    if str(profile) != args.profile:
        print(f"crtk-bridge: --profile {args.profile}: using the shipped profile {profile}", file=sys.stderr)
    try:
        return run(str(profile), sim=args.sim, socket_path=args.socket, realtime=not args.no_realtime,
                   zenoh_connect=args.zenoh_connect, zenoh_listen=args.zenoh_listen,
                   ros_domain_id=args.ros_domain_id, record_dir=args.record,
                   foxglove_listen=args.foxglove_listen)
    except CrtkBridgeError as exc:
        print(f"crtk-bridge: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 0


if __name__ == "__main__":
    sys.exit(main())
