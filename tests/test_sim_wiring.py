"""--sim wiring: each backend's simulator defaults reach the profile it is built from, on one bus
and on each bus of a several-bus profile, and never override a value the profile sets."""

from __future__ import annotations

from pathlib import Path

import msgspec
import pytest

from crtk_bridge import daemon
from crtk_bridge.backends import backend_class
from crtk_bridge.backends.serial_servo import DEFAULT_MARGIN_MS, SerialServoBackend
from crtk_bridge.profile import load_profile

PROFILES = Path(__file__).resolve().parent.parent / "profiles"


@pytest.mark.parametrize("name", ["so101.yaml", "koch.yaml"])
def test_serial_sim_relaxes_the_reply_margin_only_where_the_profile_is_silent(name):
    profile = load_profile(PROFILES / name)
    assert profile.backend.get("timeout_ms") is None  # (the shipped profiles leave it to the default)
    cls = backend_class(profile.backend_type, name)
    wired = cls.sim_profile(profile, "/tmp/some-pty")
    assert wired.backend["port"] == "/tmp/some-pty"
    assert wired.backend["timeout_ms"] == SerialServoBackend.SIM_DEFAULTS["timeout_ms"] == 30.0 > DEFAULT_MARGIN_MS
    own = msgspec.structs.replace(profile, backend={**profile.backend, "timeout_ms": 12.5})
    assert cls.sim_profile(own, "/tmp/some-pty").backend["timeout_ms"] == 12.5
    # and the backend built from it takes it
    assert cls(wired, source=name).config.timeout_ms == 30.0


class _FakeSimulator:
    def __init__(self, profile_path, device, workdir, bus="", host_ports=(), raise_priority=False, tool_link=None):
        self.link = "127.0.0.7" if host_ports else f"{workdir}/tty-{bus}"
        self.control = f"{workdir}/sim-{bus}.sock"
        self.device, self.tool_link = device, tool_link


def test_every_bus_of_a_several_bus_profile_is_wired_by_its_backend(monkeypatch, tmp_path):
    profile = load_profile(PROFILES / "bimanual_so101.yaml")
    monkeypatch.setattr(daemon, "SimulatorProcess", _FakeSimulator)
    started: list = []
    wired = daemon._simulate_buses(profile, str(PROFILES / "bimanual_so101.yaml"), str(tmp_path), started, False)
    assert len(started) == 2
    for bus in ("left", "right"):
        section = wired.backends[bus]
        assert section["port"] == f"{tmp_path}/tty-{bus}"
        assert section["timeout_ms"] == 30.0
        assert section["type"] == "feetech" and section["baudrate"] == profile.backends[bus]["baudrate"]


@pytest.mark.parametrize("name, key, value", [("canopen_2axis.yaml", "tpdo_timeout_ms", 50.0),
                                              ("ur5e.yaml", "link_timeout_s", 0.5), ("ur5e.yaml", "watchdog_hz", 2.0)])
def test_each_backends_sim_defaults_fill_only_what_the_profile_leaves_unset(name, key, value):
    profile = load_profile(PROFILES / name)
    cls = backend_class(profile.backend_type, name)
    assert cls.SIM_DEFAULTS[key] == value
    assert cls.sim_profile(profile, "127.0.0.9").backend[key] == value
    for own in (None, value * 2):  # null is "no value": the simulator's; a number is kept
        mine = msgspec.structs.replace(profile, backend={**profile.backend, key: own})
        assert cls.sim_profile(mine, "127.0.0.9").backend[key] == (value if own is None else own)


def test_a_bus_behind_another_buss_tool_port_is_simulated_behind_it(monkeypatch, tmp_path):
    """A gripper on a UR's tool flange (its port ``socket://<the arm's host>:54321``): --sim starts
    its simulator on a pty that the UR simulator relays its tool port to (``--tool-link``), and
    the gripper's backend reaches it through the UR simulator's address, as on the robot."""
    profile = load_profile(Path(__file__).resolve().parent / "profiles" / "ur5e_xl330_gripper.yaml")
    arm = profile.backends["arm"]
    hand = {**profile.backends["hand"], "port": f"socket://{arm['host']}:54321"}
    profile = msgspec.structs.replace(profile, backends={"arm": arm, "hand": hand})
    monkeypatch.setattr(daemon, "SimulatorProcess", _FakeSimulator)
    started: list = []
    wired = daemon._simulate_buses(profile, "ur5e_gripper.yaml", str(tmp_path), started, False)
    ur, gripper = started
    assert ur.device == "ur" and ur.tool_link == f"{tmp_path}/tty-hand" == gripper.link
    assert gripper.tool_link is None
    assert wired.backends["arm"]["host"] == "127.0.0.7"
    assert wired.backends["hand"]["port"] == "socket://127.0.0.7:54321"
    # a socket port elsewhere (another host, another port) is that bus's own simulator's pty
    for port in ("socket://10.0.0.9:54321", f"socket://{arm['host']}:502"):
        other = msgspec.structs.replace(profile, backends={"arm": arm, "hand": {**hand, "port": port}})
        started = []
        wired = daemon._simulate_buses(other, "ur5e_gripper.yaml", str(tmp_path), started, False)
        assert started[0].tool_link is None and wired.backends["hand"]["port"] == f"{tmp_path}/tty-hand"


def test_sim_on_a_loopback_address_taken_while_it_started_moves_to_another(monkeypatch, short_tmp):
    """``--sim`` for a simulator on fixed TCP ports (a UR controller) picks a free 127.0.0.N, but
    another process (a parallel test worker, a second daemon) may bind it before the simulator
    does: the simulator exits, and a fresh address is tried instead of failing the start."""
    import socket

    from crtk_bridge.sim.loopback import free_loopback_host
    from crtk_bridge.sim.ur import PORTS

    ports = tuple(PORTS.values())
    taken = free_loopback_host(ports)
    held = []
    for port in ports:  # what the other process bound meanwhile
        s = socket.socket()
        s.bind((taken, port))
        s.listen()
        held.append(s)
    picks = iter([taken])
    monkeypatch.setattr(daemon, "free_loopback_host", lambda p: next(picks, None) or free_loopback_host(p))
    sim = daemon.SimulatorProcess(str(PROFILES / "ur5e.yaml"), "ur", str(short_tmp), host_ports=ports)
    try:
        assert sim.link != taken and sim.proc.poll() is None
        with socket.create_connection((sim.link, ports[0]), timeout=5):
            pass
    finally:
        sim.stop()
        for s in held:
            s.close()
