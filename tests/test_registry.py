"""The one registry of backends and their simulators (crtk_bridge/registry.py): a backend that lives
in ANOTHER distribution, registered by its ``crtk_bridge.backends`` entry point (a temporary
dist-info on the path, as pip would install it), is found by the daemon's profile check, by
``crtk-bridge check``, by ``crtk-sim`` and by ``--sim``, exactly as a shipped one."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import yaml

from crtk_bridge import registry
from crtk_bridge.backends import backend_class, create_backend
from crtk_bridge.errors import BackendUnavailableError, ProfileError
from crtk_bridge.profile import load_profile

from .conftest import ROOT, DaemonProcess, so101_data

#: a third-party distribution "acme-crtk": a servo bus backend and its simulator (here the Feetech
#: ones under another name), and a second backend whose vendor SDK is not installed
PLUGIN = {
    "acme_crtk/__init__.py": "",
    "acme_crtk/registration.py": """
        from crtk_bridge.registry import Registration
        ACME = Registration("acme_crtk.backend:AcmeBackend", simulator="acme_crtk.sim:AcmeSimulator")
        NO_SDK = Registration("acme_crtk.nosdk:NoSdkBackend")
        NOT_ONE = "acme_crtk.backend:AcmeBackend"
    """,
    "acme_crtk/backend.py": """
        from crtk_bridge.backends.feetech.backend import FeetechBackend
        class AcmeBackend(FeetechBackend):
            pass
    """,
    "acme_crtk/sim.py": """
        from crtk_bridge.sim.feetech import FeetechSimulator
        class AcmeSimulator(FeetechSimulator):
            vendor = "acme"  # the profile's backend.type it simulates
    """,
    "acme_crtk/nosdk.py": """
        import acme_vendor_sdk_not_installed  # noqa: F401
    """,
    "acme_crtk-1.0.dist-info/METADATA": "Metadata-Version: 2.1\nName: acme-crtk\nVersion: 1.0\n",
    "acme_crtk-1.0.dist-info/entry_points.txt": """
        [crtk_bridge.backends]
        acme = acme_crtk.registration:ACME
        acme_nosdk = acme_crtk.registration:NO_SDK
        acme_wrong = acme_crtk.registration:NOT_ONE
        feetech = acme_crtk.registration:ACME
    """,
}


@pytest.fixture
def plugin(tmp_path, monkeypatch) -> Path:
    """The distribution installed in a folder on sys.path (and on PYTHONPATH for child processes);
    returns a profile of its ``acme`` backend."""
    site = tmp_path / "site"
    for rel, text in PLUGIN.items():
        path = site / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(textwrap.dedent(text).lstrip())
    monkeypatch.syspath_prepend(str(site))
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(p for p in (str(site), os.environ.get("PYTHONPATH")) if p))
    data = so101_data()
    data["backend"]["type"] = "acme"
    profile = tmp_path / "acme.yaml"
    profile.write_text(yaml.safe_dump(data))
    return profile


def test_an_entry_point_backend_is_registered_and_built_like_a_shipped_one(plugin):
    assert "acme" in registry.names() and "acme_nosdk" in registry.names()
    assert "acme" not in registry.BUILTIN
    profile = load_profile(plugin)
    backend = create_backend(profile, source=str(plugin))  # what the daemon does before anything starts
    assert type(backend).__name__ == "AcmeBackend"
    assert registry.simulator_device("acme") == "acme"
    assert registry.backend_simulator("acme").__name__ == "AcmeSimulator"
    assert registry.devices()["acme"] == "acme"
    # a shipped name cannot be taken over by an entry point
    assert backend_class("feetech").__name__ == "FeetechBackend"
    assert registry.devices()["feetech"] == "feetech"


def test_registry_errors_name_the_backend_and_what_to_install(plugin):
    with pytest.raises(BackendUnavailableError) as info:  # its vendor SDK is missing: the distribution to install
        backend_class("acme_nosdk")
    assert str(info.value) == ("backend 'acme_nosdk' needs a package that is not installed "
                               "(acme_vendor_sdk_not_installed): pip install 'acme-crtk'")
    with pytest.raises(ProfileError, match=r"backend 'acme_wrong': entry point 'acme_wrong' of acme-crtk "
                                           r"\(acme_crtk.registration:NOT_ONE\) is a str, not a "
                                           r"crtk_bridge.registry.Registration"):
        backend_class("acme_wrong")
    with pytest.raises(BackendUnavailableError, match="backend 'acme_nosdk' has no simulator"):
        registry.simulator_device("acme_nosdk")
    with pytest.raises(ProfileError) as info:  # an unknown name lists the entry points' too
        backend_class("kuka", "my.yaml")
    assert "my.yaml: backend.type: unknown backend 'kuka'; valid backends: acme, acme_nosdk, acme_wrong, " in str(info.value)


def test_a_shipped_backend_without_its_sdk_names_its_extra(monkeypatch):
    monkeypatch.setitem(registry.BUILTIN, "feetech", registry.Registration("acme_vendor_sdk_not_installed.x:B"))
    with pytest.raises(BackendUnavailableError) as info:
        backend_class("feetech")
    assert str(info.value).endswith("pip install 'crtk-bridge[feetech]'")


def test_every_shipped_registration_names_its_backend_simulator_and_wiring():
    for name, reg in registry.BUILTIN.items():
        cls = backend_class(name)
        assert reg.simulator is not None and cls.simulator is not None, name  # how --sim wires it
        assert registry.backend_simulator(name) is registry.simulator_class(registry.simulator_device(name))
    assert registry.simulator_device("canopen402") == "canopen"


def test_check_crtk_sim_and_sim_find_an_entry_point_backend(plugin, short_tmp):
    # crtk-bridge check: the profile of the other distribution's backend is valid
    proc = subprocess.run([sys.executable, "-m", "crtk_bridge.cli", "check", "--profile", str(plugin)],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "valid profile for robot 'so101' (acme, 6 joints" in proc.stdout
    # crtk-sim lists its simulator as a device
    proc = subprocess.run([sys.executable, "-m", "crtk_bridge.sim.cli", "--help"], cwd=ROOT,
                          capture_output=True, text=True, timeout=60)
    assert "acme" in proc.stdout and "acme_nosdk" not in proc.stdout, proc.stdout
    # --sim: the daemon starts that simulator (crtk-sim acme) and drives the backend on it
    from crtk_bridge.client import connect

    d = DaemonProcess(["--profile", str(plugin), "--sim"], short_tmp / "acme.sock", short_tmp / "acme.log")
    try:
        assert "crtk-bridge: simulated acme bus on" in d.output()
        robot = connect(socket=str(short_tmp / "acme.sock"))
        try:
            arm = robot.device("so101")
            assert arm.enable(10.0)
            p, _ = arm.measured_jp()
            assert p.shape == (5,) and np.all(np.isfinite(p))
            arm.move_jp(p + 0.05).wait()
            moved, _ = arm.measured_jp()
            assert np.allclose(moved, p + 0.05, atol=0.01)
        finally:
            robot.close()
    finally:
        d.stop()
