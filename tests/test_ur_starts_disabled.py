"""The robot starts DISABLED on a UR too: a daemon that opens on an arm found powered on with its
brakes released (by the pendant, or left so by a daemon that died ENABLED) powers it off in ``configure``,
as the serial backends switch torque off there, instead of reporting DISABLED over a live arm."""

from __future__ import annotations

import pytest

from crtk_bridge.backends.ur.backend import UrBackend
from crtk_bridge.profile import load_profile
from crtk_bridge.sim import simulator_class

from .conftest import ROOT, wait_until

UR5E = ROOT / "profiles" / "ur5e.yaml"


@pytest.fixture
def sim():
    s = simulator_class("ur").from_profile(load_profile(UR5E), power_on_s=0.1, brake_release_s=0.1)
    s.start()
    yield s
    s.stop()


def test_an_arm_found_running_is_powered_off_at_start(sim):
    from dashboard_client import DashboardClient

    dash = DashboardClient(sim.host)
    dash.connect()
    try:
        dash.powerOn()
        wait_until(lambda: sim.state()["robot_mode"] == "IDLE", 5, what="the arm powered on")
        dash.brakeRelease()
        wait_until(lambda: sim.state()["robot_mode"] == "RUNNING", 5, what="the brakes released")
    finally:
        dash.disconnect()
    backend = UrBackend(UrBackend.sim_profile(load_profile(UR5E), sim.port))
    try:
        backend.open()
        backend.configure()
        assert sim.state()["robot_mode"] == "POWER_OFF", sim.state()
        assert not backend.is_enabled
    finally:
        backend.close()

