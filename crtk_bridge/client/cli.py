"""``crtk-ctl``: command the crtk-bridge daemon from a shell.

    crtk-ctl state                      crtk-ctl enable            crtk-ctl home
    crtk-ctl get measured_js            crtk-ctl echo measured_js --rate 50 --count 10
    crtk-ctl move_jp 0 0.5 -0.5 0 0 --wait        crtk-ctl --robot so101 --ns so101/gripper list
    crtk-ctl servo_jv 0.1 0 0 0 0 --duration 1      crtk-ctl interpolate_jp 0 0.5 -0.5 0 0
    crtk-ctl servo_jr 0.05 0 0 0 0 --duration 0.5   (moves by 0.05 rad in total)
    crtk-ctl hold                       crtk-ctl free              crtk-ctl events --count 5
    crtk-ctl get measured_cp            crtk-ctl get measured_cv --frame body
    crtk-ctl move_cp 0.3 0 0.2 0 0.7071 0 0.7071 --wait      crtk-ctl move_cr 0 0 0.02 --wait
    crtk-ctl servo_cv 0 0 0.02 0 0 0 --frame body --duration 1
    crtk-ctl fk 0 0.5 -0.5 0 0          crtk-ctl ik 0.3 0 0.2 0 0.7071 0 0.7071 --seed 0 0 0 0 0
    crtk-ctl calibrate --profile my_arm.yaml           (by hand, robot DISABLED; docs/calibration.md)
    crtk-ctl calibrate --profile my_arm.yaml --import ~/.cache/huggingface/lerobot/calibration/robots/so_follower/arm.json
    crtk-ctl teleop --leader so101_leader --follower so101   (follower ENABLED first; docs/teleop.md)
    crtk-ctl record run1.mcap --duration 2      crtk-ctl replay run1.mcap --yes      (docs/recording.md)
    crtk-ctl plot run1.mcap -o run1.png         (pip install 'crtk-bridge[plot]')

Cartesian poses are X Y Z (m) then the unit quaternion QX QY QZ QW, the tip frame in the base
frame; relative commands (_cr) take DX DY DZ [QX QY QZ QW] in the base frame (no quaternion: no
rotation). Twists are VX VY VZ (m/s) WX WY WZ (rad/s), wrenches FX FY FZ (N) TX TY TZ (N·m), in
the spatial frame (base axes) or, with --frame body, the tip frame's axes.

When crtk-ctl leaves, a move or position goal it sent runs to its end; a velocity or effort
command has no end and stops, so it needs --duration (docs/protocol.md, Client loss). A
--duration stream ends at its duration on the wall clock whatever --rate (capped at the loop
rate), a velocity or effort stream with hold; a relative command (_jr, _cr) is split over the
samples: it moves by the offset given.

Exit status: 0 on success; 1 when the daemon refuses a command (one line on stderr with the
error code and the daemon's message), a wait times out or a state is not reached; 2 when no
daemon answers (the line names the socket path, or the Zenoh endpoint with --zenoh-connect) or
the arguments are wrong; 130 on Ctrl-C (a move waited on, a home or a stream is stopped with
hold first, said in one line).

Across machines: `crtk-ctl --zenoh-connect tcp/127.0.0.1:7447 --robot so101 state` reaches the
daemon through a Zenoh router (docs/zenoh.md); `crtk-ctl --zenoh-connect ENDPOINT robots` lists
the robots served there.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import re
import sys
import time
from typing import Sequence

from crtk_bridge import __version__, vocabulary
from crtk_bridge.argparsing import ArgumentParser

from crtk_bridge.client import teleop
from crtk_bridge.client.connection import DaemonConnectionError
from crtk_bridge.client.device import (
    CARTESIAN_TOPICS, CF_TOPICS, CV_TOPICS, ENDLESS_COMMANDS, FRAMES, JS_TOPICS, Device, Robot,
    connect, encode_pose, list_robots)
from crtk_bridge.client.paths import SYSTEM_SOCKET_DIR, default_socket_dir
from crtk_bridge.errors import CommandError, CrtkBridgeError, fmt_number
from crtk_bridge.zenoh_lease import ZENOH_LEASE_MS_DEFAULT, ZENOH_LEASE_MS_MAX, ZENOH_LEASE_MS_MIN, zenoh_lease_problem

PROG = "crtk-ctl"
GET_TOPICS = tuple(str(t) for t in (*JS_TOPICS, *CARTESIAN_TOPICS, *vocabulary.ROBOT_TOPICS))
#: Default wait (s) per state command when --timeout is not given.
WAIT_DEFAULTS = {"enable": 5.0, "disable": 5.0, "pause": 5.0, "resume": 5.0,
                 "home": 30.0, "unhome": 5.0}
TARGETS = {"enable": "ENABLED", "disable": "DISABLED", "pause": "PAUSED", "resume": "ENABLED",
           "home": "homed", "unhome": "not homed"}
MOVE_WAIT_DEFAULT = 30.0
#: one-shot stream commands: name -> (help, metavar of the vector)
STREAM_COMMANDS = {
    "servo_jp": ("set the joint position setpoint P (rad)", "P"),
    "servo_jr": ("move the joint position setpoint by P (rad)", "P"),
    "servo_jv": ("set the joint velocity setpoint V (rad/s); the stream holds after the "
                 "profile's servo timeout", "V"),
    "servo_jf": ("set the joint effort setpoint F (N·m); needs effort control", "F"),
    "interpolate_jp": ("set the interpolated joint position goal P (rad)", "P"),
    "interpolate_jr": ("move the interpolated joint position goal by P (rad)", "P"),
    "interpolate_jv": ("set the interpolated joint velocity goal V (rad/s)", "V"),
    "interpolate_jf": ("set the interpolated joint effort goal F (N·m); needs effort control", "F"),
}

#: cartesian one-shot stream commands: name -> (help, payload kind)
CART_STREAM_COMMANDS = {
    "servo_cp": ("set the cartesian position setpoint: X Y Z (m) QX QY QZ QW", "pose"),
    "servo_cr": ("move the cartesian setpoint by DX DY DZ (m) [QX QY QZ QW] (base frame)", "delta"),
    "interpolate_cp": ("set the interpolated cartesian goal X Y Z (m) QX QY QZ QW", "pose"),
    "interpolate_cr": ("move the interpolated cartesian goal by DX DY DZ [QX QY QZ QW]", "delta"),
    "servo_cv": ("set the cartesian velocity setpoint VX VY VZ (m/s) WX WY WZ (rad/s)", "twist"),
    "interpolate_cv": ("set the interpolated cartesian velocity goal VX VY VZ WX WY WZ", "twist"),
    "servo_cf": ("set the wrench setpoint FX FY FZ (N) TX TY TZ (N·m); needs effort control",
                 "wrench"),
    "interpolate_cf": ("set the interpolated wrench goal FX FY FZ TX TY TZ; needs effort control",
                       "wrench"),
}

# ENDLESS_COMMANDS (velocity, effort: no end) need --duration: sent once, the daemon would stop
# them as crtk-ctl disconnects (client loss); with it their stream ends with hold. A stream of
# RELATIVE_COMMANDS (_jr, _cr) moves by the offset given, in total (Device.stream).
_DURATION_HELP = ("send the command at --rate for S seconds on the wall clock (default: send once); the "
                  "stream ends at S whatever the rate. A relative command (_jr, _cr) moves by the given "
                  "offset in total; a velocity or effort command needs it (it has no end) and stops "
                  "with hold at S")
_RATE_HELP = ("samples per second with --duration (default 50; above the daemon's loop rate: capped to "
              "it, said on stderr)")


class Failure(CrtkBridgeError):
    """A command ran but did not achieve its aim (exit 1, one line on stderr)."""


class UsageError(CrtkBridgeError):
    """The arguments cannot do what was asked (exit 2, one line on stderr)."""


class Interrupted(CrtkBridgeError):
    """Ctrl-C during a command that moves the robot: what it started was stopped, or not (exit
    130, one line on stderr saying which)."""


#: help of every joint-vector argument: how many values, in which order
JOINT_VECTOR_HELP = ("one value per joint of the namespace (--ns; default: the first), in the order "
                     "`crtk-ctl list` prints its joints, e.g. on the SO-101 arm: shoulder_pan "
                     "shoulder_lift elbow_flex wrist_flex wrist_roll; each in its joint's unit: rad "
                     "(rad/s, N·m), or m (m/s, N) for a prismatic joint such as a gripper's opening "
                     "(`unit: m` in the profile)")


class Parser(ArgumentParser):
    """argparse with usage errors on one line (``crtk-ctl get: error: argument TOPIC: ...``),
    as one JSON object when ``--json`` is on the command line; an unknown argument is named before
    a missing required option (crtk_bridge/argparsing.py). Subparsers are made of the same class,
    so this holds for every subcommand."""

    json_errors = False

    def error(self, message: str):
        if self._probing:
            super().error(message)  # raises: probing for unknown arguments
        message = _one_line(self.unknown_first(message))
        if Parser.json_errors:
            _emit_json_error("usage", message)
            self.exit(2)
        self.exit(2, f"{self.prog}: error: {message}\n")


def _positive_float(text: str) -> float:
    """argparse type: a finite number > 0 (a timeout, a rate, a duration)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not (value > 0 and math.isfinite(value)):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text}")
    return value


def _checked(problem, kind=float):
    """argparse type: a number (``kind``: float or int) that ``problem(value)`` finds nothing
    wrong with (it says why otherwise)."""
    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"expected {'an integer' if kind is int else 'a number'}, got {text!r}") from None
        why = problem(value)
        if why:
            raise argparse.ArgumentTypeError(why)
        return value
    return parse


def _add_globals(p: argparse.ArgumentParser, suppress: bool) -> None:
    # The same options on the main parser and on every subparser, so that they are accepted
    # before or after the subcommand; SUPPRESS on the subparsers keeps a value given before.
    d = (lambda v: argparse.SUPPRESS) if suppress else (lambda v: v)
    g = p.add_argument_group("connection and output")
    g.add_argument("--socket", metavar="PATH", default=d(None),
                   help="daemon socket path (default: from --robot, else the only socket)")
    g.add_argument("--robot", metavar="NAME", default=d(None),
                   help="robot name: use its default socket path (with --zenoh-connect: the robot "
                        "on the Zenoh network)")
    g.add_argument("--zenoh-connect", metavar="ENDPOINT", action="append", default=d(None),
                   help="reach the daemon over Zenoh, through the router or peer at ENDPOINT "
                        "(e.g. tcp/127.0.0.1:7447; repeatable) instead of the socket (docs/zenoh.md)")
    g.add_argument("--zenoh-config", metavar="FILE", default=d(None),
                   help="with --zenoh-connect: a Zenoh configuration file (JSON5) for what the endpoint "
                        "needs, e.g. transport/link/tls/root_ca_certificate for a tls/ router")
    g.add_argument("--zenoh-lease-ms", metavar="MS", type=_checked(zenoh_lease_problem, int), default=d(None),
                   help=f"with --zenoh-connect: this client's Zenoh link lease, {ZENOH_LEASE_MS_MIN}-"
                        f"{ZENOH_LEASE_MS_MAX} (default {ZENOH_LEASE_MS_DEFAULT}): the daemon releases a "
                        "frozen client's control after it (docs/zenoh.md, 'Lease')")
    g.add_argument("--ns", metavar="NAMESPACE", default=d(None),
                   help="CRTK namespace, e.g. so101/gripper (default: the first one)")
    g.add_argument("--json", action="store_true", default=d(False),
                   help="print one JSON object per line")
    g.add_argument("--timeout", metavar="S", type=_positive_float, default=d(None),
                   help="reply timeout, and wait timeout of enable/home/move --wait (s)")


#: what argparse takes for a negative number rather than an option: its own pattern misses the
#: exponent form (``-9.5e-06``, as ``--json`` output prints small floats)
_NEGATIVE_NUMBER = re.compile(r"^-(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$")


def _numbers_not_options(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    if hasattr(p, "_negative_number_matcher"):  # argparse internals: keep working without it
        p._negative_number_matcher = _NEGATIVE_NUMBER
    return p


def build_parser() -> argparse.ArgumentParser:
    parser = _numbers_not_options(Parser(
        prog=PROG, description="Command a robot served by the crtk-bridge daemon (CRTK API)."))
    parser.add_argument("--version", action="version", version=f"{PROG} {__version__}")
    _add_globals(parser, suppress=False)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    def add(name, help_):
        p = _numbers_not_options(sub.add_parser(name, help=help_, description=help_))
        _add_globals(p, suppress=True)
        return p

    add("state", "print the operating state, is_homed and is_busy")
    add("enable", "enable (power) the robot and wait for ENABLED")
    add("disable", "disable the robot and wait for DISABLED")
    add("home", "home the robot and wait until homed and not busy")
    add("unhome", "clear is_homed")
    add("pause", "pause (ENABLED -> PAUSED)")
    add("resume", "resume (PAUSED -> ENABLED)")
    add("list", "print namespaces, joints and commands")
    add("robots", "print the names of the robots reachable: those with a socket in the default "
                  "directory, or with --zenoh-connect, those served on the Zenoh network (none: exit 2, "
                  "saying where it looked)")
    def add_frame(p):
        p.add_argument("--frame", choices=FRAMES, default="spatial",
                       help="twists and wrenches: spatial (base axes, default) or body (tip axes)")

    p = add("get", "print one sample of a topic")
    p.add_argument("topic", choices=GET_TOPICS, metavar="TOPIC", help=", ".join(GET_TOPICS))
    add_frame(p)
    p = add("echo", "stream a topic until Ctrl-C or --count frames")
    p.add_argument("topic", choices=GET_TOPICS, metavar="TOPIC", help=", ".join(GET_TOPICS))
    p.add_argument("--rate", metavar="HZ", type=_positive_float, default=10.0, help="frames/s (default 10)")
    p.add_argument("--count", metavar="N", type=int, default=None, help="stop after N frames")
    add_frame(p)
    for name, what in (("move_jp", "move to joint positions P (rad)"),
                       ("move_jr", "move by joint offsets P (rad)")):
        p = add(name, what)
        p.add_argument("position", nargs="+", type=float, metavar="P", help=JOINT_VECTOR_HELP)
        p.add_argument("--wait", action="store_true", help="wait until the move has ended")
    for name, (what, meta) in STREAM_COMMANDS.items():
        p = add(name, what)
        p.add_argument("values", nargs="+", type=float, metavar=meta, help=JOINT_VECTOR_HELP)
        p.add_argument("--duration", metavar="S", type=_positive_float, default=None, help=_DURATION_HELP)
        p.add_argument("--rate", metavar="HZ", type=_positive_float, default=50.0, help=_RATE_HELP)
    p = add("move_cp", "move the tip to the pose X Y Z (m) QX QY QZ QW (IK, then a joint "
                       "trajectory)")
    p.add_argument("values", nargs="+", type=float, metavar="POSE",
                       help="X Y Z (m) QX QY QZ QW: the tip frame in the base frame")
    p.add_argument("--wait", action="store_true", help="wait until the move has ended")
    p = add("move_cr", "move the tip by DX DY DZ (m) [QX QY QZ QW] in the base frame")
    p.add_argument("values", nargs="+", type=float, metavar="DELTA",
                   help="DX DY DZ (m) [QX QY QZ QW], in the base frame")
    p.add_argument("--wait", action="store_true", help="wait until the move has ended")
    for name, (what, kind) in CART_STREAM_COMMANDS.items():
        p = add(name, what)
        if kind == "pose":
            p.add_argument("values", nargs="+", type=float, metavar="POSE",
                       help="X Y Z (m) QX QY QZ QW: the tip frame in the base frame")
        else:
            meta, helptext = {
                "delta": ("DELTA", "DX DY DZ (m) [QX QY QZ QW], in the base frame"),
                "twist": ("TWIST", "VX VY VZ (m/s) WX WY WZ (rad/s)"),
                "wrench": ("WRENCH", "FX FY FZ (N) TX TY TZ (N·m)")}[kind]
            p.add_argument("values", nargs="+", type=float, metavar=meta, help=helptext)
        if kind in ("twist", "wrench"):
            add_frame(p)
        p.add_argument("--duration", metavar="S", type=_positive_float, default=None, help=_DURATION_HELP)
        p.add_argument("--rate", metavar="HZ", type=_positive_float, default=50.0, help=_RATE_HELP)
    p = add("fk", "forward kinematics: print the tip pose for joint positions J (rad)")
    p.add_argument("values", nargs="+", type=float, metavar="J", help=JOINT_VECTOR_HELP)
    p = add("ik", "inverse kinematics: print the joint positions for the pose X Y Z QX QY QZ QW "
                  "(exit 1 with ik_failed when not reachable)")
    p.add_argument("values", nargs="+", type=float, metavar="POSE",
                       help="X Y Z (m) QX QY QZ QW: the tip frame in the base frame")
    p.add_argument("--seed", nargs="+", type=float, metavar="J",
                   help="joint positions to start from (rad; default: the measured ones); "
                        + JOINT_VECTOR_HELP)
    add("hold", "stop a move (decelerating) or a stream and hold the position")
    add("free", "torque off on the namespace's joints; the robot stays ENABLED")
    p = add("calibrate", "calibrate the joints by hand (robot DISABLED: middle pose, then sweep every "
                         "joint, live range bars) or --import a LeRobot calibration file; writes the "
                         "joints' calibration into --profile, keeping its comments (docs/calibration.md)")
    p.add_argument("--profile", required=True, metavar="FILE",
                   help="the daemon's profile, where the calibration is written (into its calibration_file "
                        "if it names one); the daemon uses it after a restart")
    p.add_argument("--gripper", action="append", metavar="JOINT",
                   help="a joint with closed / open ends (repeatable; default: the joints of the "
                        "namespaces named .../gripper)")
    p.add_argument("--import", dest="import_path", metavar="JSON",
                   help="convert this LeRobot calibration file of the same arm instead of sweeping")
    p = add("teleop", "joint-space teleoperation: the follower robot follows the leader robot's "
                      "measured positions (interpolate_jp), once the operator aligned them; the "
                      "follower must be ENABLED; Ctrl-C ends it, the follower holding (docs/teleop.md)")
    p.add_argument("--leader", required=True, metavar="ROBOT|SOCKET",
                   help="the leader: a robot name (its default socket, or on the Zenoh network with "
                        "--zenoh-connect) or a socket path")
    p.add_argument("--follower", required=True, metavar="ROBOT|SOCKET", help="the follower, as --leader")
    p.add_argument("--pair", action="append", metavar="LEADER_NS=FOLLOWER_NS",
                   help="which namespace follows which (repeatable; default: by position)")
    p.add_argument("--rate", metavar="HZ", type=_checked(teleop.rate_problem), default=None,
                   help=f"interpolate_jp samples per second, {teleop.RATE_MIN_HZ:g} up to the lower loop rate of "
                        f"the two daemons (default {teleop.RATE_DEFAULT_HZ:g}, or that loop rate if lower)")
    p.add_argument("--tolerance", metavar="RAD", type=_checked(teleop.tolerance_problem), default=0.1,
                   help=f"alignment: every leader joint this close to the follower's, {teleop.TOLERANCE_MIN:g} "
                        f"to {teleop.TOLERANCE_MAX:g} rad (default 0.1)")
    p.add_argument("--align", choices=("wait", "move"), default="wait",
                   help="wait: the operator brings the leader to the follower (default); move: the "
                        "follower moves to the leader first (move_jp)")
    p.add_argument("--duration", metavar="S", type=_positive_float, default=None,
                   help="end after S seconds (default: until Ctrl-C)")
    p = add("events", "print status/warning/error events as they arrive, until Ctrl-C or "
                      "--count events")
    p.add_argument("--count", metavar="N", type=int, default=None, help="stop after N events")
    p.add_argument("--kind", choices=("status", "warning", "error"), action="append",
                   help="only events of this kind (repeatable; default: all)")
    p = add("record", "record every control cycle (joint states, poses, state, events, commands) into the "
                      "rosbag2 MCAP bag OUT (OUT.mcap or OUT: the folder OUT/ holding OUT/OUT.mcap), written "
                      "by the daemon, until Ctrl-C or --duration (docs/recording.md)")
    p.add_argument("out", metavar="OUT.mcap", help="the bag to write (must not exist)")
    p.add_argument("--duration", metavar="S", type=_positive_float, default=None,
                   help="record S seconds of cycles, then print the result (default: until Ctrl-C)")
    ns_option = getattr(p, "_option_string_actions", {}).get("--ns")  # argparse internals: --ns takes
    if ns_option is not None:                                         # several namespaces here
        ns_option.nargs, ns_option.metavar = "+", "NS"
        ns_option.help = "record these namespaces only (default: every namespace)"
    p = add("blackbox", "write the black box (the last recording.blackbox_s seconds of every cycle, kept "
                        "by the daemon) into the rosbag2 MCAP bag OUT (docs/recording.md)")
    p.add_argument("out", metavar="OUT.mcap", help="the bag to write (must not exist)")
    p = add("replay", "play a recording's joint positions back on the robot it was made on: a move_jp to its "
                      "first position (confirmed, or --yes), then the positions at their recorded timing as an "
                      "interpolate_jp stream; Ctrl-C holds (docs/recording.md)")
    p.add_argument("file", metavar="FILE", help="a bag written by crtk-ctl record / blackbox (folder or .mcap)")
    p.add_argument("--topic", choices=("setpoint_js", "measured_js"), default="setpoint_js",
                   help="the positions to play: what was commanded (setpoint_js, default) or what was measured")
    p.add_argument("--speed", metavar="F", type=_checked(_speed_problem), default=1.0,
                   help="play F times as fast as recorded, 0.05 to 4 (default 1)")
    p.add_argument("--rate", metavar="HZ", type=_positive_float, default=50.0,
                   help="interpolate_jp samples per second (default 50, at most the loop rate)")
    p.add_argument("--yes", action="store_true",
                   help="move to the first position without asking (needed when stdin is not a terminal)")
    p = add("plot", "plot a recording: per joint, measured against setpoint (position, velocity, effort where "
                    "recorded), operating-state changes and events marked, on the recording's clock; needs "
                    "matplotlib: pip install 'crtk-bridge[plot]' (docs/recording.md)")
    p.add_argument("file", metavar="FILE", help="a bag written by crtk-ctl record / blackbox (folder or .mcap)")
    p.add_argument("-o", "--output", required=True, metavar="OUT",
                   help="the file to write: .png, .svg or .html (a page holding the SVG)")
    p.add_argument("--joints", nargs="+", metavar="JOINT", help="these joints only (default: every joint)")
    p.add_argument("--from", dest="t_from", metavar="S", type=float, default=None,
                   help="from S seconds after the recording's start")
    p.add_argument("--to", dest="t_to", metavar="S", type=float, default=None,
                   help="up to S seconds after the recording's start")
    ns_option = getattr(p, "_option_string_actions", {}).get("--ns")
    if ns_option is not None:
        ns_option.help = "the namespace to plot (default: the first recorded)"
    return parser


def _speed_problem(value: float) -> str | None:
    if not (math.isfinite(value) and 0.05 <= value <= 4.0):
        return f"{value:g} is not in 0.05..4 (1: the recorded timing)"
    return None


# -- output -------------------------------------------------------------------------------------

def _emit_json(obj) -> None:
    print(json.dumps(obj, separators=(",", ":")), flush=True)


def _fmt_state(st: dict) -> str:
    yn = {True: "yes", False: "no"}
    return (f"{st.get('state')}  homed: {yn[bool(st.get('is_homed'))]}  "
            f"busy: {yn[bool(st.get('is_busy'))]}  (busy_seq {st.get('busy_seq')})")


def _fmt_stamp(stamp) -> str:
    stamp = float(stamp or 0.0)
    return "stamp 0 (invalid)" if stamp == 0.0 else f"stamp {stamp:.3f}"


def _js_lines(dev: Device, topic: str, data: dict) -> list[str]:
    names = list(data.get("name") or dev.joint_names)
    pos, vel, eff = (list(data.get(k) or []) for k in ("position", "velocity", "effort"))
    n = max(len(names), len(pos), len(vel), len(eff))
    width = max([len(x) for x in names] + [5])
    lines = [f"{dev.name} {topic}  {_fmt_stamp(data.get('stamp'))}"]
    units = list(getattr(dev, "joint_units", None) or [])
    for i in range(n):
        name = names[i] if i < len(names) else f"joint{i}"
        cols = []
        # the daemon's joint order: a joint it reports is in its `list` units (a prismatic one in m)
        unit = units[dev.joint_names.index(name)] if name in dev.joint_names and units else "rad"
        for vec, label in zip((pos, vel, eff), vocabulary.JOINT_UNITS.get(unit, vocabulary.JOINT_UNITS["rad"])):
            if i < len(vec):
                cols.append(f"{fmt_number(vec[i], sign=True)} {label}")
        lines.append(f"  {name:<{width}}  " + "   ".join(cols))
    return lines


def _js_oneline(dev: Device, data: dict) -> str:
    names = list(data.get("name") or dev.joint_names)
    pos = list(data.get("position") or [])
    vals = " ".join(f"{names[i] if i < len(names) else i}={fmt_number(p, sign=True)}"
                    for i, p in enumerate(pos))
    stamp = float(data.get("stamp") or 0.0)
    return f"{stamp:.3f}  {vals}" if stamp else f"(invalid)  {vals}"


def _vec_text(vec) -> str:
    return " ".join(fmt_number(v, sign=True) for v in vec) if vec else "-"


def _cart_lines(dev: Device, topic: str, data: dict, frame: str = "spatial") -> list[str]:
    """A pose, twist or wrench, readable: 4 decimals, units named."""
    head = f"{dev.name} {topic}"
    if topic in CV_TOPICS + CF_TOPICS:
        head += f" ({frame})"
    frames = ""
    if data.get("frame_id") or data.get("child_frame_id"):
        frames = f"  {data.get('child_frame_id', '?')} in {data.get('frame_id', '?')}"
    lines = [f"{head}  {_fmt_stamp(data.get('stamp'))}{frames}"]
    if topic in CV_TOPICS:
        lines += [f"  linear       {_vec_text(data.get('linear'))} m/s",
                  f"  angular      {_vec_text(data.get('angular'))} rad/s"]
    elif topic in CF_TOPICS:
        lines += [f"  force        {_vec_text(data.get('force'))} N",
                  f"  torque       {_vec_text(data.get('torque'))} N·m"]
    else:
        lines += [f"  position     {_vec_text(data.get('position'))} m (x y z)",
                  f"  orientation  {_vec_text(data.get('orientation'))} (qx qy qz qw)"]
    return lines


def _cart_oneline(topic: str, data: dict) -> str:
    stamp = float(data.get("stamp") or 0.0)
    when = f"{stamp:.3f}" if stamp else "(invalid)"
    if topic in CV_TOPICS:
        return f"{when}  v={_vec_text(data.get('linear'))}  w={_vec_text(data.get('angular'))}"
    if topic in CF_TOPICS:
        return f"{when}  f={_vec_text(data.get('force'))}  t={_vec_text(data.get('torque'))}"
    return f"{when}  p={_vec_text(data.get('position'))}  q={_vec_text(data.get('orientation'))}"


def _dict_line(data: dict) -> str:
    def f(v):
        return f"{v:.6g}" if isinstance(v, float) else str(v)
    return "  ".join(f"{k}={f(v)}" for k, v in data.items())


# -- commands -----------------------------------------------------------------------------------

def _check_len(dev: Device, cmd: str, values: Sequence[float]) -> None:
    """One number per joint of ``dev`` (when it lists its joints), all finite: refused here, before
    anything is sent, by the daemon's own reader (crtk_bridge/vectors.py)."""
    from crtk_bridge.vectors import floats
    names = dev.joint_names
    floats(list(values), f"{dev.name}: {cmd}", len(names) or None, names or None)


def _pose_arg(dev: Device, cmd: str, values: Sequence[float], relative: bool) -> tuple:
    """X Y Z QX QY QZ QW as a (position, quaternion) pair; a relative command also takes just
    DX DY DZ (no rotation)."""
    values = list(values)
    if relative and len(values) == 3:
        values += [0.0, 0.0, 0.0, 1.0]
    if len(values) != 7:
        want = "DX DY DZ [QX QY QZ QW]" if relative else "X Y Z QX QY QZ QW"
        raise CommandError("bad_request", f"{dev.name}: {cmd} needs {want}, got {len(values)} values")
    return values[:3], values[3:]


def _stream_rate(args, robot: Robot) -> float:
    """--rate, capped at the daemon's loop rate (said once on stderr): a sample is a request the
    control loop answers in its next cycle, so it cannot take more."""
    loop = robot.loop_rate_hz
    if loop is None or args.rate <= loop:
        return args.rate
    note = (f"--rate {args.rate:g} Hz is above {robot.name}'s loop rate ({loop:g} Hz): "
            f"streaming at {loop:g} Hz")
    if args.json:
        print(json.dumps({"warning": "rate_capped", "message": note}, separators=(",", ":")),
              file=sys.stderr, flush=True)
    else:
        _err(note)
    return loop


@contextlib.contextmanager
def _stops_on_interrupt(devices: Sequence[Device], what: str):
    """Ctrl-C while ``what`` (a move waited on, a stream, a home) runs: hold every device it moves,
    then :class:`Interrupted` says whether that worked. A move sent without --wait is not
    concerned: it runs to its end once crtk-ctl leaves (docs/protocol.md, Client loss)."""
    try:
        yield
    except KeyboardInterrupt:
        failed = []
        for dev in devices:
            try:
                dev.hold()
            except KeyboardInterrupt:
                raise Interrupted(f"interrupted twice: {what} not stopped, hold of {dev.name} not "
                                  "confirmed; `crtk-ctl hold` stops it") from None
            except (CrtkBridgeError, ConnectionError, TimeoutError) as exc:
                failed.append(f"{dev.name}: {exc}")
        if failed:
            raise Interrupted(f"interrupted: {what} may still run, hold failed ({'; '.join(failed)})") from None
        held = f" ({', '.join(d.name for d in devices)})" if len(devices) > 1 else ""
        raise Interrupted(f"interrupted: {what} stopped with hold{held}") from None


def _stream(args, robot: Robot, dev: Device) -> int:
    """A stream command: sent once, or with --duration at --rate until then (Device.stream)."""
    cmd = args.command
    kind = "joint" if cmd in STREAM_COMMANDS else CART_STREAM_COMMANDS[cmd][1]
    if kind == "joint":
        _check_len(dev, cmd, args.values)
        payload = args.values
    elif kind in ("pose", "delta"):
        payload = _pose_arg(dev, cmd, args.values, kind == "delta")
    else:
        if len(args.values) != 6:
            raise CommandError("bad_request", f"{dev.name}: {cmd} needs 6 values "
                               f"({'VX VY VZ WX WY WZ' if kind == 'twist' else 'FX FY FZ TX TY TZ'}), "
                               f"got {len(args.values)}")
        payload = args.values
    frame = getattr(args, "frame", "spatial")
    report = None
    if args.duration is None:
        if cmd in ENDLESS_COMMANDS:
            raise UsageError(f"{cmd} needs --duration S: a velocity or effort command has no end, "
                             "and the daemon stops it when crtk-ctl disconnects")
        method = getattr(dev, cmd)
        method(payload, frame=frame) if kind in ("twist", "wrench") else method(payload)
    else:
        rate = _stream_rate(args, robot)
        with _stops_on_interrupt([dev], f"{dev.name} {cmd} stream"):
            report = dev.stream(cmd, payload, args.duration, rate, frame=frame)
    obj = {"cmd": cmd, "ns": dev.name, "ok": True}
    if kind in ("twist", "wrench"):
        obj["frame"] = frame
    if report is not None:
        obj.update(samples=report.samples, rate_hz=report.rate_hz, held=report.held)
    if args.json:
        _emit_json(obj)
    else:
        line = f"{dev.name}: {cmd} sent" + (f" ({frame})" if "frame" in obj else "")
        if report is not None:
            line += (f": {report.samples} samples in {report.elapsed_s:.2f} s at up to {report.rate_hz:g} Hz"
                     + (", then hold" if report.held else ""))
        print(line)
    return 0


def _last_error(robot: Robot, since: int) -> str:
    evs = list(robot.connection.events)[since:]
    for ev in reversed(evs):
        if ev.kind == "error":
            return f"; {ev.data.get('code')}: {ev.data.get('message')}"
    return ""


def _run(args, robot: Robot) -> int:
    if args.command in ("record", "blackbox"):
        return _record(args, robot)
    if args.command == "replay":
        return _replay(args, robot)
    base, _, frame = (args.ns or "").rpartition("/")
    if args.ns not in robot.namespaces and frame in FRAMES and base in robot.namespaces:
        raise UsageError(f"--ns {args.ns}: {frame} is a frame, not a namespace: use --ns {base} --frame {frame} "
                         "(twists and wrenches in the tip's axes; docs/cartesian.md)")
    dev = robot.device(args.ns)
    cmd = args.command
    out_json = args.json

    if cmd == "state":
        st = dev.operating_state_full()
        _emit_json(st) if out_json else print(f"{robot.name}: {_fmt_state(st)}")
        return 0

    if cmd in WAIT_DEFAULTS:
        timeout = args.timeout if args.timeout is not None else WAIT_DEFAULTS[cmd]
        n_events = len(robot.connection.events)
        if cmd == "home":  # moves every namespace: Ctrl-C holds them all
            moved = [d for d in map(robot.device, robot.namespaces) if d.supports("hold")]
            with _stops_on_interrupt(moved, f"{robot.name} home"):
                reached = dev.home(timeout)
        else:
            reached = getattr(dev, cmd)(timeout)
        st = dev.operating_state_full()
        if out_json:
            _emit_json({"cmd": cmd, "reached": reached, **st})
        else:
            print(f"{robot.name}: {_fmt_state(st)}")
        if not reached:
            raise Failure(f"{cmd}: {TARGETS[cmd]} not reached within {timeout:g} s "
                          f"(state {st.get('state')}){_last_error(robot, n_events)}")
        return 0

    if cmd == "calibrate":
        # here, not at the top: the profile model and its YAML writer are for this command only
        from crtk_bridge.client import calibrate
        return calibrate.run(robot, args.profile, args.gripper, args.import_path, sys.stdin.fileno(), sys.stdout)

    if cmd == "list":
        info = robot.list()
        if out_json:
            _emit_json(info)
            return 0
        print(f"robot {info.get('robot')}  protocol {info.get('protocol_version')}  "
              f"daemon {info.get('daemon_version')}  socket {robot.connection.path}")
        for ns in info.get("namespaces", []):
            print(f"{ns.get('name')}:")
            units = ns.get("units") or []  # a prismatic joint (m, m/s, N) is marked; the others are rad
            joints = [f"{j} (m)" if i < len(units) and units[i] == "m" else j for i, j in enumerate(ns.get("joints") or [])]
            print(f"  joints:   {', '.join(joints) or '-'}")
            print(f"  commands: {', '.join(ns.get('commands') or []) or '-'}")
            if ns.get("queries"):
                print(f"  queries:  {', '.join(ns['queries'])}")
            if ns.get("topics"):
                print(f"  topics:   {', '.join(ns['topics'])}")
        return 0

    if cmd == "get":
        topic = args.topic
        if topic in CARTESIAN_TOPICS:
            data = dev._cartesian_query(topic, args.frame)
            _emit_json(data) if out_json else print("\n".join(_cart_lines(dev, topic, data, args.frame)))
        elif topic in JS_TOPICS:
            data = robot.connection.request(topic, dev.name)
            _emit_json(data) if out_json else print("\n".join(_js_lines(dev, topic, data)))
        elif topic == "operating_state":
            data = robot.connection.request("operating_state")
            _emit_json(data) if out_json else print(f"{robot.name}: {_fmt_state(data)}")
        else:
            data = robot.period_statistics()
            if out_json:
                _emit_json(data)
            else:
                print(f"{robot.name} period_statistics")
                for k, v in data.items():
                    print(f"  {k:<16} {v:.6g}" if isinstance(v, float) else f"  {k:<16} {v}")
        return 0

    if cmd == "echo":
        topic = args.topic
        count = 0
        with dev.subscribe(topic, args.rate, frame=args.frame) as sub:
            if args.count is not None and args.count <= 0:
                return 0
            for frame in sub:
                if out_json:
                    _emit_json(frame)
                elif topic in JS_TOPICS:
                    print(_js_oneline(dev, frame), flush=True)
                elif topic in CARTESIAN_TOPICS:
                    print(_cart_oneline(topic, frame), flush=True)
                elif topic == "operating_state":
                    print(_fmt_state(frame), flush=True)
                else:
                    print(_dict_line(frame), flush=True)
                count += 1
                if args.count is not None and count >= args.count:
                    break
        return 0

    if cmd in ("move_jp", "move_jr", "move_cp", "move_cr"):
        if cmd in ("move_jp", "move_jr"):
            _check_len(dev, cmd, args.position)
            goal = args.position
        else:
            goal = _pose_arg(dev, cmd, args.values, cmd == "move_cr")
        done = None
        timeout = args.timeout if args.timeout is not None else MOVE_WAIT_DEFAULT
        # --wait: Ctrl-C from the send on (the daemon may have the move before its reply) holds
        with _stops_on_interrupt([dev], f"{dev.name} {cmd}") if args.wait else contextlib.nullcontext():
            handle = getattr(dev, cmd)(goal)
            if args.wait:
                done = handle.wait(timeout=timeout)
        if out_json:
            obj = {"cmd": cmd, "ns": dev.name, "busy_seq": handle.busy_seq}
            if done is not None:
                obj["done"] = done
                obj["state"] = dev.operating_state()
            _emit_json(obj)
        else:
            print(f"{dev.name}: {cmd} accepted (busy_seq {handle.busy_seq})")
        if done is False:
            raise Failure(f"{cmd}: motion not ended within {timeout:g} s")
        if done:
            state = dev.operating_state()
            if state == "FAULT":
                raise Failure(f"{cmd}: motion ended with the robot in FAULT")
            if not out_json:
                print(f"{dev.name}: {cmd} done ({state})")
        return 0

    if cmd in STREAM_COMMANDS or cmd in CART_STREAM_COMMANDS:
        return _stream(args, robot, dev)

    if cmd in ("hold", "free"):
        getattr(dev, cmd)()
        _emit_json({"cmd": cmd, "ns": dev.name, "ok": True}) if out_json else print(
            f"{dev.name}: {cmd} sent")
        return 0

    if cmd == "fk":
        _check_len(dev, cmd, args.values)
        dev._check_query("forward_kinematics")
        data = robot.connection.request("forward_kinematics", dev.name, {"jp": args.values})
        if out_json:
            _emit_json(data)
        else:
            lines = _cart_lines(dev, "forward_kinematics", data)
            print("\n".join([f"{dev.name} forward_kinematics  {data.get('child_frame_id', '?')} in "
                             f"{data.get('frame_id', '?')}"] + lines[1:]))
        return 0

    if cmd == "ik":
        if args.seed is not None:
            _check_len(dev, "ik --seed", args.seed)
        dev._check_query("inverse_kinematics")
        payload = encode_pose(_pose_arg(dev, cmd, args.values, False), f"{dev.name}: ik")
        if args.seed is not None:
            payload["jp"] = list(args.seed)
        data = robot.connection.request("inverse_kinematics", dev.name, payload)
        if out_json:
            _emit_json(data)
        elif data.get("result"):
            names = dev.joint_names
            jp = list(data.get("jp") or [])
            width = max([len(x) for x in names] + [5])
            print(f"{dev.name} inverse_kinematics  ok  residual "
                  f"{float(data.get('residual_position', 0.0)) * 1000:.3f} mm, "
                  f"{float(data.get('residual_orientation', 0.0)):.4f} rad")
            for i, q in enumerate(jp):
                print(f"  {names[i] if i < len(names) else f'joint{i}':<{width}}  {fmt_number(q, sign=True)} rad")
        if not data.get("result"):
            raise CommandError("ik_failed", f"{dev.name}: {data.get('message') or 'IK did not converge'}")
        return 0

    if cmd == "events":
        return _events(robot, args)

    raise AssertionError(f"unhandled command {cmd}")  # argparse choices make this unreachable


def _record_line(r: dict) -> str:
    seconds = r.get("seconds")
    span = f", {seconds:.1f} s" if seconds is not None else ""
    lost = f", lost {r['lost']}" if "lost" in r else ""
    return (f"{r['path']}: {r['samples']} cycles (cycles {r['first_cycle']}..{r['last_cycle']}{span}){lost}, "
            f"{r['bytes'] / 1e6:.2f} MB")


def _record(args, robot: Robot) -> int:
    """``record`` and ``blackbox``: the daemon writes the bag; Ctrl-C stops a recording."""
    if args.command == "blackbox":
        r = robot.blackbox(args.out, timeout=args.timeout or 120.0)
        _emit_json(r) if args.json else print(_record_line(r))
        return 0
    ns = args.ns if isinstance(args.ns, list) else ([args.ns] if args.ns else None)
    started = robot.record(args.out, duration_s=args.duration, namespaces=ns)
    if not args.json:
        print(f"recording {started['path']}" + (f" for {args.duration:g} s" if args.duration else
                                                 " (Ctrl-C to stop)"), flush=True)
    try:
        if args.duration is not None:
            r = robot.record_stop(started["recording"], wait=True, timeout=args.duration + 60.0)
        else:
            while True:
                time.sleep(3600)
    except KeyboardInterrupt:
        r = robot.record_stop(started["recording"], timeout=60.0)
    if "error" in r:
        raise Failure(r["error"])
    _emit_json(r) if args.json else print(_record_line(r))
    return 0


def _replay(args, robot: Robot) -> int:
    """``replay``: move_jp to the first position (asked), then the recording as interpolate_jp
    samples at its timing (client/replay.py); Ctrl-C holds."""
    from crtk_bridge.client import bagfile, replay

    dev = robot.device(args.ns)
    rec = bagfile.read(args.file, topics=(args.topic,))
    p = replay.plan(rec, robot.name, dev.name, args.topic, dev.joint_names)
    rate = args.rate if robot.loop_rate_hz is None else min(args.rate, robot.loop_rate_hz)
    q, _, _, _ = dev.measured_js()
    offset, joint = replay.largest_offset(p, q)
    what = (f"{dev.name}: replay of {p.duration:.1f} s of /{dev.name}/{args.topic} from {rec.path} at speed "
            f"{args.speed:g}; first a move_jp to its first position ({offset:.3f} rad away on {joint})")
    if not args.yes:
        if not sys.stdin.isatty():
            raise UsageError(f"{what}: give --yes to move without being asked (stdin is not a terminal)")
        answer = input(f"{what}. Move? [y/N] ")
        if answer.strip().lower() not in ("y", "yes"):
            raise Failure(f"{dev.name}: replay not started (answered {answer.strip() or 'no'!r})")
    elif not args.json:
        print(what, flush=True)
    timeout = args.timeout if args.timeout is not None else MOVE_WAIT_DEFAULT
    with _stops_on_interrupt([dev], f"{dev.name} replay"):
        handle = dev.move_jp(p.q[0].tolist())
        if not handle.wait(timeout=timeout):
            raise Failure(f"{dev.name}: replay: the move to the first position did not end within {timeout:g} s")
        if dev.operating_state() == "FAULT":
            raise Failure(f"{dev.name}: replay: the move to the first position ended in FAULT")
        report = replay.stream(dev, p, args.speed, rate)
    obj = {"cmd": "replay", "ns": dev.name, "file": str(rec.path), "topic": args.topic, "speed": args.speed,
           "samples": report.samples, "duration_s": report.duration_s, "rate_hz": rate}
    if args.json:
        _emit_json(obj)
    else:
        print(f"{dev.name}: replayed {p.duration:.2f} s of {args.topic} in {report.elapsed_s:.2f} s "
              f"({report.samples} interpolate_jp samples at up to {rate:g} Hz)")
    return 0


def _plot(args) -> int:
    """``plot``: no daemon; matplotlib only here (client/plot.py)."""
    from crtk_bridge.client import plot

    out = plot.write(args.file, args.output, ns=args.ns, joints=args.joints, t_from=args.t_from, t_to=args.t_to)
    _emit_json({"cmd": "plot", "output": str(out)}) if args.json else print(f"wrote {out}")
    return 0


def _fmt_event(ev, received: float | None = None) -> str:
    """One event as a line: its stamp, or when it has none (0), the time it was ``received``."""
    d = ev.data
    extra = "".join(f"  {k}={d[k]}" for k in ("joint", "register", "value") if k in d)
    stamp = d.get("stamp")
    if not (isinstance(stamp, (int, float)) and not isinstance(stamp, bool) and stamp > 0):
        stamp = received
    when = f"{stamp:.3f}" if stamp else "-"
    message = _one_line(d.get("message", ""))
    ns = d.get("ns")
    # messages name their robot (or namespace) already: do not say it twice
    if not ns or message.startswith(f"{ns}: ") or message.startswith(f"{str(ns).split('/')[0]}: "):
        return f"{when}  {ev.kind:<7} {d.get('code')}  {message}{extra}"
    return f"{when}  {ev.kind:<7} {d.get('code')}  {ns}: {message}{extra}"


def _events(robot: Robot, args) -> int:
    """Print events as they arrive (the reader thread queues them) until --count or Ctrl-C,
    from the moment the connection opened: those that came while connecting are printed first."""
    import queue

    q: queue.Queue = queue.Queue()
    robot.connection.listen_events(lambda ev: q.put((ev, time.time())))  # stamped as received
    kinds = set(args.kind or ("status", "warning", "error"))
    count = 0
    if args.count is not None and args.count <= 0:
        return 0
    while True:
        try:
            ev, received = q.get(timeout=0.5)
        except queue.Empty:
            if robot.connection.closed:
                raise DaemonConnectionError(f"crtk-bridge at {robot.connection.path} went away")
            continue
        if ev.kind not in kinds:
            continue
        if args.json:
            _emit_json({"event": ev.kind, "data": ev.data})
        else:
            print(_fmt_event(ev, received), flush=True)
        count += 1
        if args.count is not None and count >= args.count:
            return 0


def _teleop(args, timeout: float) -> int:
    """``crtk-ctl teleop``: one line per state change (``--json``: one object) until Ctrl-C,
    ``--duration`` or an error; the follower holds when it ends."""

    def open_robot(what: str) -> Robot:
        if args.zenoh_connect:
            return connect(robot=what, timeout=timeout, zenoh_connect=args.zenoh_connect,
                           zenoh_config=args.zenoh_config, zenoh_lease_ms=args.zenoh_lease_ms)
        if "/" in what or what.endswith(".sock"):
            return connect(socket=what, timeout=timeout)
        return connect(robot=what, timeout=timeout)

    def show(state: str, message: str) -> None:
        if args.json:
            _emit_json({"teleop": state, "message": message})
        else:
            print(f"teleop {state}: {_one_line(message)}", flush=True)

    leader = open_robot(args.leader)
    try:
        follower = open_robot(args.follower)
        try:
            t = teleop.Teleop(leader, follower, pairs=args.pair, rate_hz=args.rate,
                              tolerance=args.tolerance, align=args.align, on_state=show)
            t.run(args.duration)
        finally:
            follower.close()
    finally:
        leader.close()
    return 0


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def _without_refused(message: str) -> str:
    """'so101: move_jp refused: robot is DISABLED' -> 'so101: robot is DISABLED': the line already
    says '<cmd> refused (<code>)', so the daemon's own 'refused' is not repeated."""
    return re.sub(r"^([^:\s]+: )[\w ]{1,40}? refused: ", r"\1", message, count=1)


def _err(text: str) -> None:
    print(f"{PROG}: {_one_line(text)}", file=sys.stderr, flush=True)


def _emit_json_error(code: str, message: str, cmd: str | None = None) -> None:
    """An error as one JSON object on stderr (``--json``): ``{"error": code, "message": ...}``."""
    obj = {"error": code, "message": _one_line(message)}
    if cmd:
        obj["cmd"] = cmd
    print(json.dumps(obj, separators=(",", ":")), file=sys.stderr, flush=True)


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``crtk-ctl`` with ``argv`` (default ``sys.argv[1:]``); return the exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    Parser.json_errors = "--json" in argv
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exc:  # --help (0) or a usage error (2, argparse printed why)
        return exc.code if isinstance(exc.code, int) else 2

    def fail(code: str, text: str, status: int, cmd: str | None = None, message: str | None = None) -> int:
        if args.json:
            _emit_json_error(code, message or text, cmd or args.command)
        else:
            _err(text)
        return status

    robot = None
    try:
        request_timeout = args.timeout if args.timeout is not None else 5.0
        if args.command == "robots":
            names = list_robots(args.zenoh_connect, request_timeout, args.zenoh_config, args.zenoh_lease_ms)
            if not names:
                where = (f"on the Zenoh network at {', '.join(args.zenoh_connect)}" if args.zenoh_connect else
                         f"no *.sock in {default_socket_dir()} nor {SYSTEM_SOCKET_DIR}")
                raise DaemonConnectionError(f"no crtk-bridge daemon running: {where} "
                                            "(start one: crtk-bridge --profile FILE [--sim])")
            _emit_json({"robots": names}) if args.json else print("\n".join(names))
            return 0
        if args.command == "teleop":
            return _teleop(args, request_timeout)
        if args.command == "plot":
            return _plot(args)
        robot = connect(socket=args.socket, robot=args.robot, timeout=request_timeout,
                        zenoh_connect=args.zenoh_connect, zenoh_config=args.zenoh_config,
                        zenoh_lease_ms=args.zenoh_lease_ms)
        return _run(args, robot)
    except KeyboardInterrupt:
        return 130
    except Interrupted as exc:
        return fail("interrupted", str(exc), 130)
    except CommandError as exc:
        what = getattr(exc, "cmd", None) or args.command
        return fail(exc.code, f"{what} refused ({exc.code}): {_without_refused(exc.message)}", 1, what,
                    exc.message)
    except (DaemonConnectionError, ConnectionError) as exc:
        return fail("no_daemon", str(exc), 2)
    except TimeoutError as exc:
        return fail("timeout", str(exc), 1)
    except Failure as exc:
        return fail("failed", str(exc), 1)
    except UsageError as exc:
        return fail("usage", str(exc), 2)
    except KeyError as exc:  # unknown --ns
        return fail("unknown_namespace", exc.args[0] if exc.args else str(exc), 1)
    except CrtkBridgeError as exc:
        return fail("error", str(exc), 1)
    except BrokenPipeError:  # `crtk-ctl echo ... | head`
        try:
            sys.stdout = open("/dev/null", "w")  # noqa: SIM115 - silence the flush at exit
        except OSError:
            pass
        return 0
    finally:
        if robot is not None:
            try:
                robot.close()
            except KeyboardInterrupt:
                pass


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
