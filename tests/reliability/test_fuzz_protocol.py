"""Property-based fuzzing of the socket protocol (hypothesis) against one ``--sim`` daemon shared
by the module (issue 9, reliability suite).

Properties, checked after every example:
* the daemon never dies (its process runs, a fresh session is answered, no traceback in its log);
* every well-framed request (a non-blank line ended by a newline) gets exactly one reply, in
  order, and its code is one docs/protocol.md lists (never ``internal``: no input is a bug);
* a reply's id is the request's whenever the line is a JSON object with an integer id (however
  wrong its other fields), else null;
* no ill-typed value moves the robot: with the robot ENABLED, the servos' Goal_Position read on
  the simulator's control socket is unchanged;
* the control loop keeps its rate through all of it.

Examples are derandomized (CI reproducible) and bounded so the module runs in about a minute.
Counts (inputs, replies, codes) are printed to the terminal when the module ends (also without -s)
and written to ``fuzz_counts.json`` in pytest's temporary directory.
"""

from __future__ import annotations

import json
import re
from collections import Counter
import socket
import threading
import time

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from crtk_bridge.sim.control import control_request

from ..conftest import ROOT, wait_until
from ..test_client_cartesian_e2e import daemon  # noqa: F401 - one so101 --sim daemon for the module

#: what the fuzz tried and got back; printed in the terminal at the end of the module
FUZZ: Counter = Counter()
FUZZ_CODES: Counter = Counter()

ARM, GRIPPER = "so101", "so101/gripper"
N_ARM = 5
MAX_LINE = 1 << 16
MAX_DEPTH = 32
SENTINEL_ID = 7_777_777_777_777
SENTINEL = b'{"id":7777777777777,"cmd":"operating_state"}\n'


def documented_codes() -> set[str]:
    """The error codes docs/protocol.md lists in its "Error codes" table."""
    text = (ROOT / "docs" / "protocol.md").read_text()
    table = text.split("## Error codes", 1)[1].split("\n## ", 1)[0]
    return set(re.findall(r"^\| `([a-z_]+)` \|", table, re.M))


CODES = documented_codes()
FUZZ_SETTINGS = settings(derandomize=True, database=None, deadline=None, max_examples=300,
                         suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


# ---------------------------------------------------------------- the daemon and a wire session
class Wire:
    """A raw session. ``exchange`` sends lines and a sentinel request, and returns the replies that
    came before the sentinel's (replies to one session are in order)."""

    def __init__(self, path, timeout=20.0):
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.sock.settimeout(timeout)
        self.sock.connect(str(path))
        self.f = self.sock.makefile("rb")
        self.events: list[dict] = []  # error events seen while waiting for replies

    def replies_until(self, rid) -> list[dict]:
        out = []
        while True:
            line = self.f.readline()
            assert line, "the daemon closed the session"
            msg = json.loads(line)
            if msg.get("event") == "error":
                self.events.append(msg["data"])
            if "ok" not in msg:
                continue  # events and stream frames
            if msg.get("id") == rid:
                return out
            out.append(msg)

    def exchange(self, lines: list[bytes]) -> list[dict]:
        data = b"".join(lines) + SENTINEL
        sender = threading.Thread(target=self.sock.sendall, args=(data,), daemon=True)
        sender.start()  # send while reading: a long exchange must not fill both buffers
        replies = self.replies_until(SENTINEL_ID)
        sender.join(10)
        return replies

    def call(self, cmd, ns=None, data=None, rid=1) -> dict:
        msg = {"id": rid, "cmd": cmd, **({"ns": ns} if ns else {}), **({"data": data} if data is not None else {})}
        self.sock.sendall(json.dumps(msg).encode() + b"\n")
        while True:
            r = json.loads(self.f.readline())
            if r.get("event") == "error":
                self.events.append(r["data"])
            if r.get("id") == rid and "ok" in r:
                return r

    def close(self):
        try:
            self.sock.close()
        except OSError:
            pass


def code(reply: dict) -> str:
    return "ok" if reply.get("ok") is True else reply["error"]["code"]


def check_replies(lines: list[bytes], replies: list[dict], expected_ids: list | None = None) -> None:
    """Exactly one reply per non-blank line, each with a documented code; ids as expected."""
    framed = [ln for ln in lines if ln.strip()]
    FUZZ["lines_sent"] += len(lines)
    FUZZ["requests_framed"] += len(framed)
    FUZZ["replies"] += len(replies)
    for r in replies:
        FUZZ_CODES[code(r)] += 1
    assert len(replies) == len(framed), (len(framed), replies[:5])
    for r in replies:
        c = code(r)
        assert c == "ok" or (c in CODES and c != "internal"), r
        if not r["ok"]:
            msg = r["error"]["message"]
            assert isinstance(msg, str) and "\n" not in msg and "Traceback" not in msg, r
            assert "codec" not in msg, r  # the decoder's own words never reach a client (issue 18)
    if expected_ids is not None:
        assert [r["id"] for r in replies] == expected_ids


def assert_alive(daemon) -> None:
    assert daemon.proc.poll() is None, "the daemon died:\n" + daemon.output()[-3000:]
    w = Wire(daemon.socket_path)
    try:
        assert w.call("list", rid=1)["ok"]
    finally:
        w.close()


@pytest.fixture(scope="module")
def wire(daemon):
    """One long-lived session for the examples (a session per example is tested too, below)."""
    w = Wire(daemon.socket_path)
    yield w
    w.close()


@pytest.fixture(scope="module", autouse=True)
def fuzz_report(request, tmp_path_factory):
    yield
    if not FUZZ:
        return
    lines = ["protocol fuzz counts: " + "  ".join(f"{k}={v}" for k, v in sorted(FUZZ.items())),
             "protocol fuzz reply codes: " + "  ".join(f"{k}={v}" for k, v in FUZZ_CODES.most_common())]
    out = tmp_path_factory.getbasetemp() / "fuzz_counts.json"
    out.write_text(json.dumps({"counts": FUZZ, "codes": FUZZ_CODES}, indent=1))
    plugins = request.config.pluginmanager
    tr, capture = plugins.get_plugin("terminalreporter"), plugins.get_plugin("capturemanager")
    if tr is not None and capture is not None:
        with capture.global_and_fixture_disabled():  # shown without -s too
            tr.write_line("")
            for line in lines + [f"(written to {out})"]:
                tr.write_line(line)


def loop_cycles(daemon) -> tuple[float, int]:
    w = Wire(daemon.socket_path)
    try:
        return time.monotonic(), w.call("period_statistics")["data"]["cycles"]
    finally:
        w.close()


@pytest.fixture(scope="module", autouse=True)
def loop_start(daemon):
    """The loop's rate over a quiet second (the baseline on this host now), then the fuzz's start."""
    t0, c0 = loop_cycles(daemon)
    time.sleep(1.0)  # the baseline's measurement window
    t1, c1 = loop_cycles(daemon)
    return (c1 - c0) / (t1 - t0), t1, c1


# ---------------------------------------------------------------- strategies
_text = st.text(alphabet=st.characters(blacklist_categories=("Cs",)), max_size=12)
_scalars = (st.none() | st.booleans() | st.integers() | st.integers(min_value=-(10**30), max_value=10**30)
            | st.floats(allow_nan=True, allow_infinity=True) | _text)
json_values = st.recursive(_scalars, lambda c: st.lists(c, max_size=6) | st.dictionaries(_text, c, max_size=4),
                           max_leaves=24)
COMMANDS = ["list", "operating_state", "period_statistics", "measured_js", "setpoint_js", "goal_js",
            "enable", "disable", "pause", "resume", "home", "unhome", "servo_jp", "servo_jr", "servo_jv",
            "interpolate_jp", "interpolate_jr", "interpolate_jv", "move_jp", "move_jr", "hold", "free",
            "subscribe", "unsubscribe", "acquire", "release", "measured_cp", "servo_cp", "move_cp",
            "servo_cv", "forward_kinematics", "inverse_kinematics", "servo_jf", "no_such_cmd"]
_missing = object()


def _number_vectors(n):
    return st.lists(st.floats(-0.3, 0.3), min_size=n, max_size=n)


def _plausible_data(cmd):
    """Data shaped for ``cmd`` (vectors for the arm or the gripper), or none for commands without."""
    vectors = st.one_of(_number_vectors(N_ARM), _number_vectors(1))
    if cmd in ("servo_jp", "servo_jr", "interpolate_jp", "interpolate_jr", "move_jp", "move_jr"):
        return st.fixed_dictionaries({"position": vectors})
    if cmd in ("servo_jv", "interpolate_jv"):
        return st.fixed_dictionaries({"velocity": vectors})
    if cmd == "servo_jf":
        return st.fixed_dictionaries({"effort": vectors})
    if cmd == "subscribe":
        return st.fixed_dictionaries({"topic": st.sampled_from(["measured_js", "operating_state", "x"]),
                                      "rate_hz": st.one_of(st.floats(0.1, 2000), json_values)})
    if cmd == "unsubscribe":
        return st.fixed_dictionaries({"sub": st.integers(0, 5)})
    if cmd in ("servo_cp", "move_cp", "inverse_kinematics"):
        return st.fixed_dictionaries({"position": st.lists(st.floats(-0.3, 0.3), min_size=3, max_size=3),
                                      "orientation": st.just([0.0, 0.0, 0.0, 1.0])})
    if cmd == "servo_cv":
        three = st.lists(st.floats(-0.05, 0.05), min_size=3, max_size=3)
        return st.fixed_dictionaries({"linear": three, "angular": three})
    if cmd == "forward_kinematics":
        return st.fixed_dictionaries({"jp": vectors})
    return st.just(_missing)


def _mostly(draw, plausible, anything=None):
    """A plausible value 4 times in 5, else an arbitrary JSON value or nothing at all."""
    if draw(st.integers(0, 4)):
        return draw(plausible)
    return draw(st.one_of(json_values if anything is None else anything, st.just(_missing)))


@st.composite
def requests(draw):
    """A request object: mostly plausible (an integer id, known commands, valid namespaces,
    well-shaped data), each field sometimes replaced by an arbitrary JSON value or left out, and
    sometimes not an object at all."""
    obj = {}
    rid = _mostly(draw, st.integers(0, 10**6), st.integers(-(2**70), 2**70) | json_values)
    cmd = _mostly(draw, st.sampled_from(COMMANDS))
    ns = _mostly(draw, st.sampled_from([ARM, ARM, GRIPPER, "so101/body", "nope"]))
    data = _mostly(draw, _plausible_data(cmd))
    for key, value in (("id", rid), ("cmd", cmd), ("ns", ns), ("data", data)):
        if value is not _missing:
            obj[key] = value
    if not draw(st.integers(0, 4)):
        extra = draw(st.dictionaries(_text, json_values, max_size=2))
        obj.update({k: v for k, v in extra.items() if k not in obj})
    return obj if draw(st.integers(0, 9)) else draw(json_values)


def expected_id(obj, line: bytes):
    """The id docs/protocol.md says the reply carries: the request's whenever the line is a JSON
    object with an integer id, however wrong its other fields (a cmd or ns of another type, too
    deep, ill-typed data)."""
    try:
        json.loads(line, parse_constant=lambda c: (_ for _ in ()).throw(ValueError(c)))
    except ValueError:
        return None  # NaN / Infinity are not JSON
    if len(line) > MAX_LINE or not isinstance(obj, dict):
        return None  # an over-long line is not read
    rid = obj.get("id", _missing)
    return rid if type(rid) is int else None


def mutate(data: bytes, ops) -> bytes:
    b = bytearray(data)
    for kind, pos, byte in ops:
        if not b:
            b.append(byte)
            continue
        i = pos % len(b)
        if kind == 0:
            b[i] = byte
        elif kind == 1:
            b.insert(i, byte)
        elif kind == 2:
            del b[i]
        else:
            b[i:i] = b[i:i + 1 + byte % 16]  # duplicate a run
    return bytes(b).replace(b"\n", b" ")


VALID_TEMPLATES = [
    {"id": 1, "cmd": "servo_jp", "ns": ARM, "data": {"position": [0.0] * N_ARM, "velocity": [0.0] * N_ARM}},
    {"id": 2, "cmd": "move_jr", "ns": ARM, "data": {"position": [0.01, 0.0, 0.0, 0.0, 0.0]}},
    {"id": 3, "cmd": "subscribe", "ns": ARM, "data": {"topic": "measured_js", "rate_hz": 50}},
    {"id": 4, "cmd": "move_cp", "ns": ARM, "data": {"position": [0.2, 0.0, 0.2], "orientation": [0, 0, 0, 1]}},
    {"id": 5, "cmd": "interpolate_jv", "ns": GRIPPER, "data": {"velocity": [0.0]}},
    {"id": 6, "cmd": "measured_js", "ns": ARM},
]


# ---------------------------------------------------------------- properties
@FUZZ_SETTINGS
@given(st.lists(st.binary(min_size=0, max_size=300), min_size=1, max_size=6))
def test_random_bytes_get_one_reply_per_line(daemon, wire, chunks):
    lines = [c.replace(b"\n", b"") + b"\n" for c in chunks]
    check_replies(lines, wire.exchange(lines))


@FUZZ_SETTINGS
@given(st.lists(requests(), min_size=1, max_size=5))
def test_random_requests_get_one_reply_with_a_documented_code(daemon, objs):
    lines, ids = [], []
    for obj in objs:
        line = json.dumps(obj, allow_nan=True).encode() + b"\n"
        lines.append(line)
        ids.append(expected_id(obj, line))
    w = Wire(daemon.socket_path)  # a session per example: its control and subscriptions end with it
    try:
        check_replies(lines, w.exchange(lines), ids)
    finally:
        w.close()


@FUZZ_SETTINGS
@given(st.sampled_from(VALID_TEMPLATES),
       st.lists(st.tuples(st.integers(0, 3), st.integers(0, 10**6), st.integers(0, 255)), min_size=1, max_size=8))
def test_mutated_requests_get_one_reply_each(daemon, template, ops):
    line = mutate(json.dumps(template).encode(), ops) + b"\n"
    w = Wire(daemon.socket_path)
    try:
        check_replies([line], w.exchange([line]))
    finally:
        w.close()


@settings(FUZZ_SETTINGS, max_examples=60)
@given(st.integers(MAX_DEPTH - 2, 40_000), st.sampled_from([b"[", b'{"a":']), st.booleans())
def test_deep_nesting_is_refused_and_the_session_lives(daemon, wire, levels, opener, in_id):
    closer = b"]" if opener == b"[" else b"}"
    nested = opener * levels + b"0" + closer * levels
    if in_id:  # where a reply id would be recovered from
        line = b'{"id":' + nested + b',"cmd":"list"}\n'
    else:
        line = b'{"id":3,"cmd":"move_jp","ns":"so101","data":{"position":' + nested + b"}}\n"
    (r,) = wire.exchange([line]) or [None]
    check_replies([line], [r])
    assert code(r) == "bad_request"
    # the id 3 is read from a line however deep its data (an id that is itself nested is none)
    assert r["id"] == (None if len(line) > MAX_LINE or in_id else 3), r
    FUZZ["deep_lines"] += 1


@settings(FUZZ_SETTINGS, max_examples=20)
@given(st.integers(MAX_LINE - 200, 6 * MAX_LINE), st.booleans())
def test_huge_lines_are_refused_and_the_session_goes_on(daemon, wire, size, valid_json):
    head = b'{"id":9,"cmd":"list","pad":"'
    body = (b"x" if valid_json else b"\xff") * max(0, size - len(head) - 3)
    line = head + body + b'"}\n'
    replies = wire.exchange([line])
    check_replies([line], replies)
    if len(line) > MAX_LINE:
        assert code(replies[0]) == "bad_request" and replies[0]["id"] is None
    FUZZ["huge_lines"] += 1


@settings(FUZZ_SETTINGS, max_examples=60)
@given(st.binary(min_size=1, max_size=2000), st.booleans())
def test_partial_frame_then_disconnect_leaves_the_daemon_serving(daemon, partial, half_close):
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.connect(str(daemon.socket_path))
    s.sendall(partial.replace(b"\n", b" "))
    if half_close:
        s.shutdown(socket.SHUT_WR)
    s.close()
    FUZZ["partial_frames"] += 1
    assert_alive(daemon)


# ---------------------------------------------------------------- ill-typed values never move the robot
ILL = st.sampled_from([True, False, None, "0", "0.1", "", [0.0], [[0.0]], {"x": 0.0}, [], "NaN"])
_POSE = {"position": 3, "orientation": 4}
#: motion commands and the vectors of their payload (field -> length)
MOTION = [(c, {"position": N_ARM}) for c in ("servo_jp", "servo_jr", "interpolate_jp", "interpolate_jr",
                                             "move_jp", "move_jr")]
MOTION += [("servo_jp", {"position": N_ARM, "velocity": N_ARM}), ("servo_jv", {"velocity": N_ARM}),
           ("interpolate_jv", {"velocity": N_ARM})]
MOTION += [(c, _POSE) for c in ("servo_cp", "interpolate_cp", "move_cp", "servo_cr", "interpolate_cr", "move_cr")]
MOTION += [(c, {"linear": 3, "angular": 3}) for c in ("servo_cv", "interpolate_cv")]


def goal_ticks(sim) -> np.ndarray:
    servos = control_request(sim, {"cmd": "dump"})["servos"]
    return np.array([servos[k]["goal_position"] for k in sorted(servos, key=int)])


#: faults a loaded host can cause (the simulator answering late); any other fault fails the test
LOAD_FAULTS = ("bus_timeout", "bus_corrupt", "torque_off_unconfirmed")


def settle(w: Wire, sim: str) -> None:
    """ENABLED, homed, nothing running, both namespaces holding, Goal_Position registers still."""
    if w.call("operating_state")["data"]["state"] == "PAUSED":  # an earlier example sent pause
        assert code(w.call("resume")) == "ok", w.events[-3:]
    if code(w.call("enable")) != "ok":  # FAULT -> ENABLED retries; a late reply can fail it once
        assert code(w.call("enable")) == "ok", w.events[-3:]
    if not w.call("operating_state")["data"]["is_homed"]:  # an earlier example sent unhome
        assert code(w.call("home")) == "ok"
    wait_until(lambda: not w.call("operating_state")["data"]["is_busy"], 30, what="moves of earlier examples ended")
    for ns in (ARM, GRIPPER):
        assert code(w.call("hold", ns)) == "ok"
    last = [goal_ticks(sim)]

    def still():
        now = goal_ticks(sim)
        same = np.array_equal(now, last[0])
        last[0] = now
        return same

    wait_until(still, 10, interval=0.05, what="goal registers still")
    w.events.clear()  # faults from here on are the fuzz's


@pytest.fixture(scope="module")
def enabled_still(daemon):
    """A session holding control with the robot ENABLED and holding still; yields (session, sim)."""
    w = Wire(daemon.socket_path)
    sim = daemon.sim_control_path()
    wait_until(lambda: code(w.call("acquire")) == "ok", 10, what="control free for the fuzz session")
    settle(w, sim)
    yield w, sim
    w.call("disable")
    w.close()


@settings(FUZZ_SETTINGS, max_examples=300)
@given(st.sampled_from(MOTION), st.integers(0, N_ARM - 1), ILL, st.booleans(), st.floats(-0.3, 0.3))
def test_ill_typed_values_never_move_the_robot(daemon, enabled_still, motion, joint, bad, whole, fill):
    w, sim = enabled_still
    if w.call("operating_state")["data"]["state"] != "ENABLED":
        assert all(e["code"] in LOAD_FAULTS for e in w.events), w.events[-3:]
        FUZZ["load_faults_recovered"] += 1  # the host starved the simulator: enable again
        settle(w, sim)
    cmd, fields = motion
    payload = {f: [fill] * n for f, n in fields.items()}
    if "orientation" in payload:
        payload["orientation"] = [0.0, 0.0, 0.0, 1.0]
    field = list(fields)[joint % len(fields)]
    if whole:
        payload[field] = bad
    else:
        payload[field][joint % fields[field]] = bad
    before = goal_ticks(sim)
    line = json.dumps({"id": 41, "cmd": cmd, "ns": ARM, "data": payload}).encode() + b"\n"
    (r,) = w.exchange([line]) or [None]
    check_replies([line], [r], [41])
    assert code(r) == "bad_request" and "`data." in r["error"]["message"], r
    assert not w.call("operating_state")["data"]["is_busy"]
    assert np.array_equal(goal_ticks(sim), before), f"{cmd} {payload} moved the robot"
    FUZZ["ill_typed_refused"] += 1


# ---------------------------------------------------------------- load
def test_a_flood_gets_every_reply_and_does_not_stall_others(daemon):
    n = 5000
    flooder = Wire(daemon.socket_path, timeout=60)
    lines = [b'{"id":%d,"cmd":"%s","ns":"so101"}\n' % (i, b"measured_js" if i % 2 else b"operating_state")
             for i in range(n)]
    blob = b"".join(lines)
    flooder.sock.sendall(blob)  # and reads nothing for now: its replies pile up in the daemon
    other = Wire(daemon.socket_path)
    t0 = time.monotonic()
    assert other.call("operating_state", rid=5)["ok"]
    assert time.monotonic() - t0 < 5.0, "a flooding session stalled another"
    other.close()
    replies = flooder.replies_until(SENTINEL_ID) if flooder.sock.sendall(SENTINEL) is None else []
    check_replies(lines, replies, list(range(n)))
    flooder.close()
    FUZZ["flood_requests"] += n
    assert_alive(daemon)


def test_200_simultaneous_connections_are_each_answered(daemon):
    socks = []
    try:
        for _ in range(200):
            s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            s.settimeout(30)
            s.connect(str(daemon.socket_path))
            socks.append(s)
        for i, s in enumerate(socks):
            s.sendall(b'{"id":%d,"cmd":"measured_js","ns":"so101"}\n' % i)
        for i, s in enumerate(socks):
            f = s.makefile("rb")
            while True:
                msg = json.loads(f.readline())
                if "ok" in msg:
                    break
            assert msg["id"] == i and msg["ok"] and msg["data"]["stamp"] > 0
        FUZZ["simultaneous_connections"] += len(socks)
    finally:
        for s in socks:
            s.close()
    assert_alive(daemon)


def test_zz_daemon_survived_and_the_loop_kept_its_rate(daemon, loop_start):
    """Runs last in the module (name order within the file is definition order; this is last)."""
    assert_alive(daemon)
    baseline, t0, c0 = loop_start
    t1, c1 = loop_cycles(daemon)
    rate = (c1 - c0) / (t1 - t0)
    FUZZ["loop_hz_quiet"] = round(baseline)
    FUZZ["loop_hz_under_fuzz"] = round(rate)
    # a ratio to the same host's quiet rate measured in this run (the host is shared and noisy)
    assert rate > 0.75 * baseline, f"loop at {rate:.1f} Hz under the fuzz, {baseline:.1f} Hz quiet"
    log = daemon.output()
    assert "Traceback" not in log, log[-3000:]
