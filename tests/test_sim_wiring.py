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
    assert wired.backend["timeout_ms"] == SerialServoBackend.SIM_TIMEOUT_MS > DEFAULT_MARGIN_MS
    own = msgspec.structs.replace(profile, backend={**profile.backend, "timeout_ms": 12.5})
    assert cls.sim_profile(own, "/tmp/some-pty").backend["timeout_ms"] == 12.5
    # and the backend built from it takes it
    assert cls(wired, source=name).config.timeout_ms == SerialServoBackend.SIM_TIMEOUT_MS


class _FakeSimulator:
    def __init__(self, profile_path, device, workdir, bus="", host_ports=(), raise_priority=False):
        self.link = f"{workdir}/tty-{bus}"
        self.control = f"{workdir}/sim-{bus}.sock"


def test_every_bus_of_a_several_bus_profile_is_wired_by_its_backend(monkeypatch, tmp_path):
    profile = load_profile(PROFILES / "bimanual_so101.yaml")
    monkeypatch.setattr(daemon, "SimulatorProcess", _FakeSimulator)
    started: list = []
    wired = daemon._simulate_buses(profile, str(PROFILES / "bimanual_so101.yaml"), str(tmp_path), started, False)
    assert len(started) == 2
    for bus in ("left", "right"):
        section = wired.backends[bus]
        assert section["port"] == f"{tmp_path}/tty-{bus}"
        assert section["timeout_ms"] == SerialServoBackend.SIM_TIMEOUT_MS
        assert section["type"] == "feetech" and section["baudrate"] == profile.backends[bus]["baudrate"]
