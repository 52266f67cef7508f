"""The Zenoh transport's configuration: off by default, the command line over the profile, the
exposure rule (loopback, or TLS + access control), and the daemon's one-line start-up errors."""

from __future__ import annotations

import json
import shutil
import socket
import subprocess
import sys

import pytest
import yaml

from .conftest import ROOT, SO101, free_port, so101_data
from crtk_bridge.profile import ZenohTls, load_profile
from crtk_bridge.transport.zenoh_session import (
    bound_listen,
    ZenohConfig, ZenohConfigError, ZenohConnectError, check_exposure, is_loopback, open_session,
    session_config, zenoh_config)


def test_off_unless_an_endpoint_or_the_section():
    profile = load_profile(SO101)
    assert zenoh_config(profile) is None
    assert zenoh_config(profile, ros_domain_id=3) is None  # a domain alone does not turn it on
    joined = zenoh_config(profile, connect=["tcp/127.0.0.1:7447"], ros_domain_id=3)
    # joining a router still listens on loopback (peers on this PC connect directly), nothing more
    assert (joined.connect, joined.listen, joined.ros_domain_id) == (["tcp/127.0.0.1:7447"], ["tcp/127.0.0.1:0"], 3)
    listening = zenoh_config(profile, listen=["tcp/127.0.0.1:7448"])
    assert (listening.connect, listening.listen, listening.ros_domain_id) == ([], ["tcp/127.0.0.1:7448"], 0)


def test_command_line_replaces_the_profile_lists(tmp_path):
    data = so101_data()
    data["transport"] = {"zenoh": {"connect": ["tcp/127.0.0.1:1"], "ros_domain_id": 7,
                                   "tls": {"root_ca_certificate": "ca.pem"}}}
    path = tmp_path / "p.yaml"
    path.write_text(yaml.safe_dump(data))
    profile = load_profile(path)
    from_profile = zenoh_config(profile)
    assert from_profile.listen == ["tcp/127.0.0.1:0"]  # the section alone: loopback, any port
    assert from_profile.tls.root_ca_certificate == str(tmp_path / "ca.pem")  # relative to the profile
    merged = zenoh_config(profile, connect=["tcp/127.0.0.1:2"], ros_domain_id=1)
    assert (merged.connect, merged.ros_domain_id) == (["tcp/127.0.0.1:2"], 1)


@pytest.mark.parametrize("endpoint,local", [
    ("tcp/127.0.0.1:7447", True), ("tcp/127.3.0.1:7447", True), ("tcp/localhost:7447", True),
    ("tcp/[::1]:7447", True), ("unixsock-stream//tmp/zenoh.sock", True), ("udp/127.0.0.1:7447", True),
    ("tcp/0.0.0.0:7447", False), ("tcp/[::]:7447", False), ("tcp/192.168.1.10:7447", False),
    ("tls/lab-router.example.org:7447", False), ("quic/10.0.0.2:7447?iface=eth0", False),
])
def test_loopback(endpoint, local):
    assert is_loopback(endpoint) is local


ACL = {"enabled": True, "default_permission": "deny", "rules": [], "subjects": [], "policies": []}
CERTS = ZenohTls(root_ca_certificate="/c/ca.pem", listen_certificate="/c/d.pem", listen_private_key="/c/d.key")


@pytest.mark.parametrize("config,key", [
    (ZenohConfig(listen=["tcp/0.0.0.0:7447"]), "only a tls/ endpoint may"),
    (ZenohConfig(listen=["tcp/0.0.0.0:7447"], tls=CERTS, access_control=ACL), "only a tls/ endpoint may"),
    (ZenohConfig(listen=["tls/0.0.0.0:7447"], access_control=ACL), "set transport.zenoh.tls.listen_certificate"),
    (ZenohConfig(listen=["tls/0.0.0.0:7447"], tls=ZenohTls(listen_certificate="/c/d.pem"), access_control=ACL),
     "set transport.zenoh.tls.listen_private_key"),
    (ZenohConfig(listen=["tls/0.0.0.0:7447"], tls=CERTS), "set transport.zenoh.access_control"),
    (ZenohConfig(listen=["tls/0.0.0.0:7447"], tls=CERTS, access_control={**ACL, "enabled": False}),
     "set transport.zenoh.access_control"),
    (ZenohConfig(listen=[], connect=["tcp/10.0.0.1:7447"]), "transport.zenoh.connect (--zenoh-connect)"),
    (ZenohConfig(listen=[], connect=["tls/10.0.0.1:7447"], access_control=ACL),
     "set transport.zenoh.tls.root_ca_certificate"),
    (ZenohConfig(listen=["127.0.0.1:7447"]), "is not a Zenoh endpoint"),
])
def test_exposure_refused_naming_the_key(config, key):
    with pytest.raises(ZenohConfigError) as err:
        check_exposure(config, "so101")
    text = str(err.value)
    assert text.startswith("so101: transport.zenoh.") and key in text and "\n" not in text


def test_exposure_accepted():
    check_exposure(ZenohConfig(listen=["tcp/127.0.0.1:7447", "tcp/[::1]:7447"], connect=["tcp/localhost:7447"]),
                   "so101")
    check_exposure(ZenohConfig(listen=["tls/0.0.0.0:7447"], connect=["tls/10.0.0.1:7447"], tls=CERTS,
                               access_control=ACL), "so101")


def test_session_config_is_safe_by_default():
    conf = session_config(ZenohConfig())
    assert conf.get_json("scouting/multicast/enabled") == "false"
    assert conf.get_json("listen/endpoints") == '["tcp/127.0.0.1:0"]'  # Zenoh's own default: tcp/[::]:0
    conf = session_config(ZenohConfig(listen=["tls/0.0.0.0:1"], tls=CERTS, access_control=ACL))
    assert conf.get_json("transport/link/tls/listen_certificate") == '"/c/d.pem"'
    assert '"default_permission":"deny"' in conf.get_json("access_control")


def test_unreachable_router_and_busy_port_errors():
    port = free_port()
    with pytest.raises(ZenohConnectError) as err:
        open_session(ZenohConfig(listen=[], connect=[f"tcp/127.0.0.1:{port}"], connect_timeout_s=0.3), "so101")
    assert str(err.value).startswith(f"so101: cannot reach the Zenoh router or peer at tcp/127.0.0.1:{port}")
    assert "start a router" in str(err.value) and "zenohd" in str(err.value)
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        busy = taken.getsockname()[1]
        with pytest.raises(ZenohConnectError, match=rf"^so101: cannot listen on tcp/127.0.0.1:{busy} .*in use"):
            open_session(ZenohConfig(listen=[f"tcp/127.0.0.1:{busy}"]), "so101")


def test_a_listen_on_port_0_is_told_with_the_port_bound():
    """What the daemon's banner says: tcp/127.0.0.1:0 is the port the system gave, one a peer can
    connect to; an endpoint with its own port is kept as written."""
    fixed = f"tcp/127.0.0.1:{free_port()}"
    bound: list[str] = []
    session = open_session(ZenohConfig(listen=["tcp/127.0.0.1:0", fixed]), "so101", bound=bound)
    try:
        assert len(bound) == 2 and bound[1] == fixed
        assert bound[0].startswith("tcp/127.0.0.1:") and bound[0] != "tcp/127.0.0.1:0", bound
        with socket.create_connection(("127.0.0.1", int(bound[0].rsplit(":", 1)[1])), timeout=5):
            pass  # the session listens there
    finally:
        session.close()
    # the query part stays; a host not matched keeps its 0
    assert bound_listen(["tcp/127.0.0.1:0?iface=lo", "udp/127.0.0.3:0"], {("tcp", "127.0.0.1", 4711)}) == \
        ["tcp/127.0.0.1:4711?iface=lo", "udp/127.0.0.3:0"]


def _daemon(args: list[str], timeout: float = 30.0) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "crtk_bridge.cli", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=timeout)


def test_daemon_refuses_a_listen_beyond_loopback(short_tmp):
    done = _daemon(["--profile", str(SO101), "--sim", "--socket", str(short_tmp / "s.sock"),
                    "--zenoh-listen", "tcp/0.0.0.0:7447"])
    assert done.returncode == 1
    assert done.stderr.strip().splitlines() == [
        "crtk-bridge: so101: transport.zenoh.listen (--zenoh-listen) tcp/0.0.0.0:7447 reaches beyond this "
        "PC: only a tls/ endpoint may (with transport.zenoh.tls and transport.zenoh.access_control); use "
        "loopback, or see docs/zenoh.md, 'Across machines'"]
    assert "simulated" not in done.stdout  # refused before the simulator started


def test_daemon_says_the_router_is_unreachable(short_tmp):
    data = so101_data()
    data["transport"] = {"zenoh": {"connect_timeout_s": 0.3}}
    path = short_tmp / "so101.yaml"
    path.write_text(yaml.safe_dump(data))
    port = free_port()
    done = _daemon(["--profile", str(path), "--sim", "--socket", str(short_tmp / "s.sock"),
                    "--zenoh-connect", f"tcp/127.0.0.1:{port}"])
    assert done.returncode == 1
    (line,) = done.stderr.strip().splitlines()
    assert line.startswith(f"crtk-bridge: so101: cannot reach the Zenoh router or peer at tcp/127.0.0.1:{port} ")
    assert "start a router there (e.g. `zenohd -l" in line
    assert not (short_tmp / "s.sock").exists()


@pytest.fixture(scope="module")
def certs(tmp_path_factory):
    """A throw-away CA and a certificate for localhost it signed (openssl, as a lab would make them)."""
    if shutil.which("openssl") is None:
        pytest.skip("openssl is not installed: cannot make test certificates")
    d = tmp_path_factory.mktemp("certs")
    (d / "ext").write_text("subjectAltName=DNS:localhost,IP:127.0.0.1\n")
    for cmd in ("req -x509 -newkey rsa:2048 -nodes -keyout ca.key -out ca.pem -days 1 -subj /CN=crtk-test-ca",
                "req -newkey rsa:2048 -nodes -keyout d.key -out d.csr -subj /CN=localhost",
                "x509 -req -in d.csr -CA ca.pem -CAkey ca.key -CAcreateserial -out d.pem -days 1 -extfile ext"):
        subprocess.run(["openssl", *cmd.split()], cwd=d, check=True, capture_output=True)
    return d


def test_a_tls_endpoint_needs_the_ca(certs, tmp_path):
    """The tls keys reach Zenoh: a daemon-side session listening on tls/ with its certificate is
    reached by a client that trusts the CA (a Zenoh configuration file), and not without it."""
    from crtk_bridge.client import DaemonConnectionError, list_robots

    endpoint = f"tls/localhost:{free_port()}"
    daemon = open_session(ZenohConfig(listen=[endpoint], tls=ZenohTls(
        listen_certificate=str(certs / "d.pem"), listen_private_key=str(certs / "d.key"))), "so101")
    try:
        token = daemon.liveliness().declare_token("crtk_bridge/so101/daemon")
        trust = tmp_path / "client.json5"
        trust.write_text(json.dumps({"transport": {"link": {"tls": {"root_ca_certificate": str(certs / "ca.pem")}}}}))
        assert list_robots(zenoh_connect=endpoint, timeout=5.0, zenoh_config=str(trust)) == ["so101"]
        with pytest.raises(DaemonConnectionError, match="a tls/ endpoint also needs the CA"):
            list_robots(zenoh_connect=endpoint, timeout=0.5)  # the daemon's certificate is not trusted
        token.undeclare()
    finally:
        daemon.close()


def test_check_refuses_an_exposed_profile(short_tmp):
    data = so101_data()
    data["transport"] = {"zenoh": {"listen": ["tcp/192.168.1.10:7447"]}}
    path = short_tmp / "so101.yaml"
    path.write_text(yaml.safe_dump(data))
    done = _daemon(["check", "--profile", str(path)])
    assert done.returncode == 1
    assert done.stderr.strip() == (
        "crtk-bridge: so101: transport.zenoh.listen (--zenoh-listen) tcp/192.168.1.10:7447 reaches beyond this "
        "PC: only a tls/ endpoint may (with transport.zenoh.tls and transport.zenoh.access_control); use "
        "loopback, or see docs/zenoh.md, 'Across machines'")


@pytest.mark.parametrize("allowed", [False, True], ids=["deny-all", "liveliness-allowed"])
def test_access_control_reaches_zenoh(allowed):
    """transport.zenoh.access_control is Zenoh's own section: with default_permission deny and no
    rule, a client cannot even see the daemon's token; with a rule allowing liveliness on
    crtk_bridge/** for the loopback interface, it can."""
    from crtk_bridge.client import list_robots

    rules = [{"id": "see daemons", "permission": "allow", "flows": ["ingress", "egress"],
              "messages": ["liveliness_token", "liveliness_query", "declare_liveliness_subscriber", "reply"],
              "key_exprs": ["crtk_bridge/**"]}] if allowed else []
    acl = {"enabled": True, "default_permission": "deny", "rules": rules,
           "subjects": [{"id": "this pc", "interfaces": ["lo"]}],
           "policies": [{"rules": ["see daemons"], "subjects": ["this pc"]}] if allowed else []}
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    daemon = open_session(ZenohConfig(listen=[endpoint], access_control=acl), "so101")
    try:
        token = daemon.liveliness().declare_token("crtk_bridge/so101/daemon")
        assert list_robots(zenoh_connect=endpoint, timeout=1.0) == (["so101"] if allowed else [])
        token.undeclare()
    finally:
        daemon.close()
