"""The Foxglove live view (``crtk-bridge --foxglove-listen``; docs/recording.md): a WebSocket client
written here from the protocol (ws-protocol: JSON ``serverInfo`` / ``advertise``, the client's
``subscribe``, binary message-data frames) subscribes to ``measured_js`` and decodes its CDR with
rosbags; ``/robot_description`` carries the URDF to every subscriber; beyond loopback the option
is refused without the Zenoh transport's TLS + access control opt-in."""

from __future__ import annotations

import asyncio
import json
import shutil
import struct
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest
import yaml

from crtk_bridge.client import connect
from crtk_bridge.transport.ros.types import TYPESTORE

from .conftest import ROOT, DaemonProcess, free_port, so101_data

websockets = pytest.importorskip("websockets")  # in the test extra: CI has it
pytest.importorskip("foxglove")

# what the Foxglove app offers: foxglove-sdk 0.30 accepts only its foxglove.sdk.v1 (HTTP 400 to a client
# offering foxglove.websocket.v1 alone), whose messages are ws-protocol's
SUBPROTOCOLS = ["foxglove.websocket.v1", "foxglove.sdk.v1"]


@pytest.fixture(scope="module")
def daemon():
    tmp = Path(tempfile.mkdtemp(prefix="crtk-fg-"))
    data = so101_data()
    data["recording"] = {"blackbox_s": 0}
    (tmp / "so101.yaml").write_text(yaml.safe_dump(data))
    port = free_port()
    d = DaemonProcess(["--profile", str(tmp / "so101.yaml"), "--sim", "--foxglove-listen", f"127.0.0.1:{port}"],
                      tmp / "so101.sock", tmp / "daemon.log")
    d.port = port
    try:
        yield d
    finally:
        d.print_tail()
        d.stop()
        shutil.rmtree(tmp, ignore_errors=True)


async def _subscribe(port: int, topics: list[str], wanted: dict[str, int], timeout: float = 20.0) -> tuple:
    """Connect, read the advertisements, subscribe to ``topics``; collect the binary
    message-data frames until ``wanted[topic]`` messages of each came. Returns (serverInfo,
    advertised channels by topic, {topic: [(log_time, payload)]})."""
    async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=SUBPROTOCOLS, open_timeout=10) as ws:
        assert ws.subprotocol in SUBPROTOCOLS
        info, channels, got = None, {}, {t: [] for t in topics}
        subs: dict[int, str] = {}

        async def loop():
            nonlocal info
            async for frame in ws:
                if isinstance(frame, str):
                    msg = json.loads(frame)
                    if msg["op"] == "serverInfo":
                        info = msg
                    elif msg["op"] == "advertise":
                        new = []
                        for ch in msg["channels"]:
                            channels[ch["topic"]] = ch
                            if ch["topic"] in topics and ch["topic"] not in subs.values():
                                sid = len(subs) + 1
                                subs[sid] = ch["topic"]
                                new.append({"id": sid, "channelId": ch["id"]})
                        if new:
                            await ws.send(json.dumps({"op": "subscribe", "subscriptions": new}))
                    continue
                op = frame[0]
                if op != 0x01:  # message data: opcode, uint32 subscription id, uint64 log time, payload
                    continue
                sid, log_time = struct.unpack_from("<IQ", frame, 1)
                got[subs[sid]].append((log_time, bytes(frame[13:])))
                if all(len(got[t]) >= n for t, n in wanted.items()):
                    return

        await asyncio.wait_for(loop(), timeout)
        return info, channels, got


def test_a_foxglove_client_gets_measured_js_and_the_urdf(daemon):
    topics = ["/so101/measured_js", "/robot_description", "/so101/operating_state", "/tf"]
    with connect(socket=str(daemon.socket_path), timeout=10.0) as robot:
        robot.enable()
        robot.device("so101").move_jp([0.2, 0.1, -0.1, 0.0, 0.1])
        info, channels, got = asyncio.run(_subscribe(daemon.port, topics, {t: 1 for t in topics} |
                                                     {"/so101/measured_js": 20}))
    assert "so101" in info["name"]
    assert not ({"clientPublish", "services", "parameters"} & set(info.get("capabilities", [])))  # read-only
    ch = channels["/so101/measured_js"]
    assert ch["encoding"] == "cdr" and ch["schemaName"] == "sensor_msgs/msg/JointState"
    assert ch["schemaEncoding"] == "ros2msg" and "float64[] position" in ch["schema"]
    msgs = [TYPESTORE.deserialize_cdr(data, "sensor_msgs/msg/JointState") for _, data in got["/so101/measured_js"]]
    assert list(msgs[0].name) == ["shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll"]
    assert all(len(m.position) == 5 for m in msgs)
    stamps = [m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 for m in msgs]
    assert all(b > a for a, b in zip(stamps, stamps[1:]))  # successive cycles
    times = [t for t, _ in got["/so101/measured_js"]]
    assert all(b > a for a, b in zip(times, times[1:]))
    # the latched topics reach a subscriber who came after they were first sent
    urdf = TYPESTORE.deserialize_cdr(got["/robot_description"][0][1], "std_msgs/msg/String").data
    assert "<robot" in urdf and "shoulder_pan" in urdf
    state = TYPESTORE.deserialize_cdr(got["/so101/operating_state"][-1][1], "crtk_msgs/msg/OperatingState")
    assert state.state == "ENABLED"
    # /tf: base -> the tip (the graph's) and base -> every URDF link, so the 3D panel poses the arm
    import re
    tf = TYPESTORE.deserialize_cdr(got["/tf"][-1][1], "tf2_msgs/msg/TFMessage")
    links = set(re.findall(r'<link name="([^"]+)"', urdf)) - {"base_link"}
    assert {t.child_frame_id for t in tf.transforms} == links and {t.header.frame_id for t in tf.transforms} == {"base_link"}
    # the shipped layout (docs/foxglove/) reads topics the live view advertises
    layout = json.loads((ROOT / "docs" / "foxglove" / "so101_layout.json").read_text())
    used = set(re.findall(r'"(/[a-z0-9_/]+?)(?:\.[a-z_\[\]0-9.]+)?"', json.dumps(layout["configById"])))
    assert "/so101/measured_js" in used and "/robot_description" in used and "/so101/error" in used
    assert used <= set(channels), used - set(channels)
    assert set(layout["configById"]) == _panels(layout["layout"])


def _panels(node) -> set:
    return {node} if isinstance(node, str) else _panels(node["first"]) | _panels(node["second"])


def _start(args: list[str], tmp: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "crtk_bridge.cli", *args, "--socket", str(tmp / "x.sock")],
                          capture_output=True, text=True, cwd=ROOT, timeout=60)


def test_beyond_loopback_is_refused_without_the_tls_and_access_control_opt_in(tmp_path):
    data = so101_data()
    (tmp_path / "p.yaml").write_text(yaml.safe_dump(data))
    out = _start(["--profile", str(tmp_path / "p.yaml"), "--sim", "--foxglove-listen", "0.0.0.0:8765"], tmp_path)
    err = out.stderr.strip().splitlines()
    assert out.returncode == 1 and len(err) == 1, out.stderr
    assert err[0].startswith("crtk-bridge: so101: --foxglove-listen 0.0.0.0:8765 reaches beyond this PC: only with "
                             "TLS: set transport.zenoh.tls.listen_certificate")
    assert not (tmp_path / "x.sock").exists()
    # TLS certificates alone are not the opt-in: access control must be on too
    data["transport"] = {"zenoh": {"tls": {"listen_certificate": "cert.pem", "listen_private_key": "key.pem"}}}
    (tmp_path / "p.yaml").write_text(yaml.safe_dump(data))
    out = _start(["--profile", str(tmp_path / "p.yaml"), "--foxglove-listen", "192.0.2.1:8765"], tmp_path)
    assert out.returncode == 1 and "set transport.zenoh.access_control (enabled: true)" in out.stderr, out.stderr
    out = _start(["--profile", str(tmp_path / "p.yaml"), "--foxglove-listen", "8765"], tmp_path)
    assert out.returncode == 1 and "give HOST:PORT, e.g. 127.0.0.1:8765" in out.stderr, out.stderr


def test_a_port_taken_ends_start_up_in_one_line(tmp_path):
    import socket
    (tmp_path / "p.yaml").write_text(yaml.safe_dump(so101_data()))
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        out = _start(["--profile", str(tmp_path / "p.yaml"), "--sim", "--foxglove-listen", f"127.0.0.1:{port}"], tmp_path)
    err = [line for line in out.stderr.splitlines() if line.startswith("crtk-bridge: so101")]
    assert out.returncode == 1 and len(err) == 1, out.stderr
    assert err[0].startswith(f"crtk-bridge: so101: --foxglove-listen 127.0.0.1:{port}: the Foxglove server did not start")
    assert "Traceback" not in out.stderr and not (tmp_path / "x.sock").exists()


def test_without_foxglove_sdk_the_option_names_the_extra(tmp_path):
    (tmp_path / "p.yaml").write_text(yaml.safe_dump(so101_data()))
    code = ("import sys; sys.modules['foxglove'] = None; from crtk_bridge.cli import main; "
            f"sys.exit(main(['--profile', {str(tmp_path / 'p.yaml')!r}, '--sim', '--foxglove-listen', '127.0.0.1:0', "
            f"'--socket', {str(tmp_path / 'x.sock')!r}]))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert out.returncode == 1 and out.stderr.strip() == ("crtk-bridge: so101: --foxglove-listen needs foxglove-sdk, "
                                                          "an optional extra: pip install 'crtk-bridge[foxglove]'")


def test_the_exposure_rule_accepts_loopback_and_the_opt_in():
    from types import SimpleNamespace

    from crtk_bridge.recording.exposure import check

    bare = SimpleNamespace(name="so101", transport=SimpleNamespace(zenoh=None))
    assert check("127.0.0.1:0", bare).url == "ws://127.0.0.1:0"
    assert check("[::1]:8765", bare).url == "ws://[::1]:8765"
    assert check("localhost:8765", bare).tls_cert is None
    tls = SimpleNamespace(listen_certificate="/c.pem", listen_private_key="/k.pem")
    opted = SimpleNamespace(name="so101", transport=SimpleNamespace(zenoh=SimpleNamespace(
        tls=tls, access_control={"enabled": True})))
    got = check("0.0.0.0:8765", opted)
    assert (got.tls_cert, got.tls_key, got.url) == ("/c.pem", "/k.pem", "wss://0.0.0.0:8765")
