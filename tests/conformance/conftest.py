"""One backend conformance suite over the actuator contract (issue 8 item 8), as python-can tests
every interface with one suite: every registered backend whose registration names a simulator
(crtk_bridge/registry.py) runs every test here against that simulator, in process, through the
real vendor SDK path.

A backend is a ROW: the profile it runs on and how a test reaches into its simulator (which device
a joint is, how to silence it, give it an error, read its goal and torque). A registered backend
with a simulator and no row fails ``test_every_simulated_backend_has_a_row``: adding CANopen or UR
means adding one row here (and its simulator's hooks), nothing else. The composite actuator of a
robot on several buses (backends/composite.py) runs the same suite on robots of mixed buses
(:data:`COMPOSITES`: two Feetech arms; a UR arm with a Dynamixel gripper; a CiA 402 pan / tilt
whose pan homes natively beside a Feetech arm; a Feetech arm with a Dynamixel gripper), each bus
on its own backend's simulator, driven through its own backend's row.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import msgspec
import numpy as np
import pytest

from crtk_bridge import registry
from crtk_bridge.backends import backend_class, create_backend
from crtk_bridge.core.actuator import Actuator, Fault, effective_period_s
from crtk_bridge.core.cycle import CycleRunner
from crtk_bridge.core.control import Controller
from crtk_bridge.registry import backend_simulator
from crtk_bridge.profile import Profile, load_profile
from crtk_bridge.sim import simulator_class


ROOT = Path(__file__).resolve().parents[2]


def wait_until(*args, **kwargs):
    """tests/conftest.py's (imported on call: that module imports this one's ROWS)."""
    from ..conftest import wait_until as wait

    return wait(*args, **kwargs)


@dataclass(frozen=True)
class Row:
    """How the suite drives one backend's simulator. ``device(profile, i)`` is the simulator's id
    of joint ``i``; the rest take (simulator, device id)."""

    backend: str
    profile: Path
    device: Callable[[Profile, int], int]
    silence: Callable[[object, int], None]
    inject_error: Callable[[object, int], None]  # a device error: the device reports it, stops
    clear_errors: Callable[[object], None]  # what an operator does; a latched error may remain
    torque: Callable[[object, int], bool]
    goal: Callable[[object, int], int]  # raw goal register (unit of the device)
    present: Callable[[object, int], int]  # raw position register
    error_latched: bool  # the error stays until enable resets the device (Dynamixel reboot)
    set_present: Callable[[object, int, int], None]  # move the device's shaft (raw position) by hand
    error_code: str = "servo_error"  # the fault code of inject_error
    silent_code: str = "bus_timeout"  # the fault code of silence (naming the joint)
    #: a silenced device still takes what it is sent (a servo that does not reply); False: it
    #: hears nothing either (a CAN node off the bus), so torque off cannot reach it until it is back
    silent_hears: bool = True
    #: whether the FAULT that inject_error causes names the joint
    error_names_joint: bool = True
    #: every joint is one device on one link (a UR arm): no joint can fall silent alone
    one_device: bool = False
    #: a DISABLED arm is held by its brakes (a UR powered off): nothing displaces it by hand
    braked_when_disabled: bool = False
    #: device position units per joint radian (``goal`` / ``present`` / ``set_present``); None:
    #: from the joint's backend keys (tests/conftest.py _counts_per_rad)
    units_per_rad: float | None = None
    #: the simulator another process started (``crtk-bridge --sim``), reached over its control
    #: socket: ``remote(path)`` (default: tests/conftest.py RemoteSim)
    remote: Callable[[str], object] | None = None
    #: ``prepare(sim)`` before a test drives it: quick where the real device is slow
    prepare: Callable[[object], None] | None = None
    #: the device applies no torque and holds nothing (what ``free`` leaves); None: torque off
    free: Callable[[object, int], bool] | None = None
    #: how to make the simulator (default: the device's ``from_profile(profile)``)
    make_sim: Callable[[Profile], object] | None = None
    #: wait until the simulator has taken every command sent so far (a servo bus answers in
    #: order: a read is that; RTDE inputs are taken at the controller's next tick)
    settle: Callable[[object], None] | None = None
    #: the profile's joint limits leave room within the device's own range (a gripper's opening
    #: limits ARE its stroke's ends: nothing beyond them to clamp or not)
    room_beyond_limits: bool = True


def _servo_id(profile: Profile, i: int) -> int:
    return int(profile.joints[i].backend["id"])


def _servo_row(backend: str, profile: str, latched: bool) -> Row:
    """A serial servo bus simulator (crtk_bridge.sim.bus.BusSimulator); 0x20 = overload on both
    vendors' error registers."""
    return Row(
        backend=backend, profile=ROOT / "profiles" / profile, device=_servo_id,
        silence=lambda sim, sid: sim.set_fault(sid, "silent"),
        inject_error=lambda sim, sid: sim.set_fault(sid, "error_bits", 0x20),
        clear_errors=lambda sim: sim.clear_faults(),
        torque=lambda sim, sid: sim.servo(sid).read("Torque_Enable") == 1,
        goal=lambda sim, sid: sim.servo(sid).read("Goal_Position"),
        present=lambda sim, sid: sim.servo(sid).read("Present_Position"),
        error_latched=latched,
        set_present=lambda sim, sid, raw: sim.servo(sid).write("Present_Position", raw),
    )


def _node_id(profile: Profile, i: int) -> int:
    return int(profile.joints[i].backend["node_id"])


class URSimAdapter:
    """The simulated UR controller (sim/ur.py) behind the calls the suite makes of a simulator.
    A "device" is a joint index, its unit the microradian. Quick power-on and brake release; a
    protective stop may be unlocked 0.3 s after it (UR: 5 s). Either its own controller
    (``URSimAdapter(profile)``) or, end to end, the one a daemon's ``--sim`` started
    (:meth:`attach`)."""

    QUICK = {"power_on_s": 0.1, "brake_release_s": 0.1, "unlock_delay_s": 0.3}

    def __init__(self, profile: Profile | None = None, *, handle=None):
        self.sim = handle if handle is not None else simulator_class("ur").from_profile(profile, **self.QUICK)

    @classmethod
    def attach(cls, control_path: str) -> URSimAdapter:
        return cls(handle=simulator_class("ur").attach(control_path))

    def prepare(self) -> None:
        """The quick timings on a controller started with the real ones (``--sim``)."""
        self.sim.control({"cmd": "timings", **self.QUICK})

    @property
    def rx_bytes(self) -> int:
        """Bytes the controller received from clients on every port."""
        return self.state()["rx_bytes"]

    def devices(self) -> dict[str, dict]:
        """One entry per joint (the suite's device ids), with where it is (rad)."""
        return {str(i): {"q": q} for i, q in enumerate(self.state()["q"])}

    def clear_faults(self) -> None:
        """What an operator does by hand: reset a safeguard stop, release an e-stop button (a
        protective stop stays until enable unlocks it)."""
        kind = {"SAFEGUARD_STOP": "safeguard", "ROBOT_EMERGENCY_STOP": "robot_estop",
                "SYSTEM_EMERGENCY_STOP": "system_estop"}.get(self.state()["safety_mode"])
        if kind is not None:
            self.sim.release(kind)

    def hand(self, i: int, raw: int) -> None:
        """A hand pushes joint ``i`` to ``raw`` urad (refused unless the arm is in teach mode:
        its brakes hold it otherwise)."""
        q = self.state()["q"]
        q[i] = raw / 1e6
        self.sim.control({"cmd": "hand", "q": q, "speed": 2.0})

    @property
    def port(self) -> str:
        return self.sim.port

    def start(self) -> None:
        self.sim.start()

    def stop(self) -> None:
        self.sim.stop()

    def state(self) -> dict:
        return self.sim.state()

    def set_torque_delay(self, seconds: float) -> None:
        self.sim.control({"cmd": "timings", "power_on_s": max(seconds, self.QUICK["power_on_s"])})  # a slow power on

    def set_unplugged(self, unplugged: bool) -> None:
        if unplugged:  # every connection dropped, new ones refused for a while
            # (a blocking control call in flight then ends with the backend's ur_rtde worker,
            # which the backend ends at the loss)
            self.sim.link_loss(0.5, ports=("rtde", "dashboard", "script"))

    def settle(self) -> None:
        """Ten controller ticks (20 ms): RTDE inputs sent before now have been applied (the
        simulator takes them on its own thread; two ticks were not always enough under load)."""
        t0 = self.state()["ticks"]
        wait_until(lambda: self.state()["ticks"] >= t0 + 10, 2, interval=0.001, what="ten controller ticks")


class RobotiqSimAdapter:
    """The simulated 2F gripper (sim/robotiq.py) for the suite: activated already (a gripper keeps
    its activation while powered; activation runs the fingers over their whole stroke, which would
    move them before ``enable`` holds them), quick activations (0.3 s); a slow enable
    (``set_torque_delay``) is a gripper that needs activating again (a power cycle) and activates
    that slowly."""

    def __init__(self, profile: Profile | None = None, *, handle=None):
        self.sim = handle if handle is not None else simulator_class("robotiq").from_profile(
            profile, activation_s=0.3, activated=True)

    def __getattr__(self, name):
        return getattr(self.sim, name)

    def set_torque_delay(self, seconds: float) -> None:
        g = self.sim.gripper
        with g.lock:
            g.action, g.gact, g.gsta = 0, False, 0
        self.sim.set_activation_s(seconds)


ROWS = {
    "feetech": _servo_row("feetech", "so101.yaml", latched=False),
    "dynamixel": _servo_row("dynamixel", "koch.yaml", latched=True),
    # CiA 402 drives (crtk_bridge.sim.canopen402, in process on a python-can virtual channel):
    # an EMCY faults the drive, which stays in FAULT until the master's fault reset (enable)
    "canopen402": Row(
        backend="canopen402", profile=ROOT / "profiles" / "canopen_2axis.yaml", device=_node_id,
        silence=lambda sim, nid: sim.set_fault(nid, "silent"),
        inject_error=lambda sim, nid: sim.set_fault(nid, "emcy", 0x5000),
        clear_errors=lambda sim: sim.clear_faults(),
        # the drive answers the serial servos' register names (in counts), so these hooks also
        # work through the simulator's control socket (tests/conftest.py RemoteSim)
        torque=lambda sim, nid: sim.drive(nid).read("Torque_Enable") == 1,
        goal=lambda sim, nid: sim.drive(nid).read("Goal_Position"),
        present=lambda sim, nid: sim.drive(nid).read("Present_Position"),
        error_latched=True,
        set_present=lambda sim, nid, raw: sim.drive(nid).write("Present_Position", raw),
        error_code="drive_fault", silent_code="tpdo_missing", silent_hears=False,
        # free: the power stage stays on, in CST with zero target torque (backend.py write)
        free=lambda sim, nid: sim.drive(nid).read("Torque_Enable") == 0 or (
            sim.drive(nid).read("mode") == 10 and sim.drive(nid).read("target_torque") == 0),
    ),
    # one UR5e on the simulated controller: torque = powered with brakes released; goal = the
    # servo target the controller follows, present = the joint's position (urad); free = teach
    # mode, where a hand may push the arm (set_present)
    "ur": Row(
        backend="ur", profile=ROOT / "profiles" / "ur5e.yaml", device=lambda profile, i: i,
        silence=lambda sim, i: sim.set_unplugged(True),
        inject_error=lambda sim, i: sim.sim.inject_stop("protective", cause="conformance test"),
        clear_errors=lambda sim: None,  # a protective stop stays until enable unlocks it
        torque=lambda sim, i: sim.state()["robot_mode"] == "RUNNING",
        goal=lambda sim, i: round(1e6 * sim.state()["target_q"][i]),
        present=lambda sim, i: round(1e6 * sim.state()["q"][i]),
        error_latched=True, error_code="protective_stop", error_names_joint=False,
        one_device=True, braked_when_disabled=True, units_per_rad=1e6,
        make_sim=URSimAdapter, settle=URSimAdapter.settle, remote=URSimAdapter.attach, prepare=URSimAdapter.prepare,
        set_present=lambda sim, i, raw: sim.hand(i, raw),
        free=lambda sim, i: sim.state()["teach_mode"],
    ),
    # a Robotiq 2F-85 (crtk_bridge.sim.robotiq, in process on a pty): the device is the gripper
    # (its slave id), its unit the gripper's position count (0 open .. 255 closed: -2553 per m of
    # opening between the simulator's stroke ends 13 and 230); torque = gGTO (acting on its
    # position request); silence = no communication; the error an overcurrent (gFLT 0x0E), a major
    # fault only the reset of the next enable clears
    "robotiq": Row(
        backend="robotiq", profile=ROOT / "profiles" / "robotiq_2f85.yaml", device=_servo_id,
        silence=lambda sim, sid: sim.set_fault(sid, "no_communication"),
        inject_error=lambda sim, sid: sim.set_fault(sid, "overcurrent"),
        clear_errors=lambda sim: sim.clear_faults(),
        torque=lambda sim, sid: sim.servo(sid).read("Torque_Enable") == 1 if hasattr(sim, "servo")
        else sim.gripper.read("Torque_Enable") == 1,
        goal=lambda sim, sid: sim.servo(sid).read("Goal_Position") if hasattr(sim, "servo")
        else sim.gripper.read("Goal_Position"),
        present=lambda sim, sid: sim.servo(sid).read("Present_Position") if hasattr(sim, "servo")
        else sim.gripper.read("Present_Position"),
        set_present=lambda sim, sid, raw: sim.servo(sid).write("Present_Position", raw) if hasattr(sim, "servo")
        else sim.gripper.write("Present_Position", raw),
        error_latched=True, error_code="gripper_fault", silent_code="bus_timeout",
        units_per_rad=-(230 - 13) / 0.085, make_sim=RobotiqSimAdapter, room_beyond_limits=False,
        prepare=lambda sim: sim.req(cmd="activation", seconds=0.3) if hasattr(sim, "req") else None,
    ),
}
#: the joints the suite silences and faults (test_conformance.py: min(2, n - 1), min(3, n - 1)): a
#: composite row takes those behaviours from the row of the bus that owns them
SILENCED_JOINT, FAULTED_JOINT = 2, 3
TEST_PROFILES = ROOT / "tests" / "profiles"


def _bus_of(profile: Profile, i: int) -> tuple[int, int]:
    """(bus index, index among that bus's joints) of robot joint ``i``."""
    name = profile.joints[i].name
    ns = next(ns for ns in profile.namespaces if name in ns.joints)
    bus = profile.namespace_bus(ns)
    return profile.bus_names.index(bus), profile.bus_profile(bus).joint_names.index(name)


def _composite_row(name: str, path: Path) -> Row:
    """A robot on several buses (backends/composite.py), each bus simulated by its own backend's
    simulator and driven through its own backend's row (:class:`BusSims`): a device is
    ``bus index * 1000 + the bus row's device id``; the hooks hand each device to its bus's row.
    Per-device behaviours come from the bus of the joint the suite uses them on; a skip flag (the
    joints are one device, braked when disabled) from any bus."""
    profile = load_profile(path)
    rows = [ROWS[profile.bus_profile(bus).backend_type] for bus in profile.bus_names]
    n = len(profile.joints)
    silent = rows[_bus_of(profile, min(SILENCED_JOINT, n - 1))[0]]
    error = rows[_bus_of(profile, min(FAULTED_JOINT, n - 1))[0]]

    def device(p: Profile, i: int) -> int:
        b, k = _bus_of(p, i)
        return b * 1000 + rows[b].device(p.bus_profile(p.bus_names[b]), k)

    def on_bus(hook: str):
        return lambda sim, key, *args: getattr(rows[key // 1000], hook)(sim.sims[key // 1000], key % 1000, *args)

    def free(sim, key):
        row = rows[key // 1000]
        return row.free(sim.sims[key // 1000], key % 1000) if row.free is not None else \
            not row.torque(sim.sims[key // 1000], key % 1000)

    return Row(
        backend=name, profile=path, device=device,
        silence=on_bus("silence"), inject_error=on_bus("inject_error"),
        clear_errors=lambda sim: sim.clear_errors(),
        torque=on_bus("torque"), goal=on_bus("goal"), present=on_bus("present"), set_present=on_bus("set_present"),
        error_latched=error.error_latched, error_code=error.error_code, error_names_joint=error.error_names_joint,
        silent_code=silent.silent_code, silent_hears=silent.silent_hears,
        one_device=silent.one_device, braked_when_disabled=any(r.braked_when_disabled for r in rows),
        units_per_rad=None if len({r.units_per_rad for r in rows}) > 1 else rows[0].units_per_rad,
        room_beyond_limits=all(r.room_beyond_limits for r in rows),
        make_sim=BusSims, settle=lambda sim: sim.settle(), prepare=lambda sim: sim.prepare(), free=free,
    )


class BusSims:
    """The simulators of a several-bus profile, one per bus, each made the way its backend's row
    makes it; the calls a test makes of "the simulator" go to every bus's."""

    def __init__(self, profile: Profile):
        self.names = profile.bus_names
        self.rows = []
        self.sims = []
        for bus in self.names:
            sub = profile.bus_profile(bus)
            row = ROWS[sub.backend_type]
            self.rows.append(row)
            self.sims.append(row.make_sim(sub) if row.make_sim is not None
                             else backend_simulator(sub.backend_type).from_profile(sub))

    def start(self) -> None:
        for s in self.sims:
            s.start()

    def stop(self) -> None:
        for s in self.sims:
            s.stop()

    def wired(self, profile: Profile) -> Profile:
        backends = {}
        for bus, sim in zip(self.names, self.sims):
            cls = backend_class(profile.backends[bus]["type"])
            backends[bus] = cls.sim_profile(profile.bus_profile(bus), sim.port).backend
            if getattr(sim, "interface", None) == "virtual":  # an in-process CAN simulator
                backends[bus] = {**backends[bus], "interface": "virtual", "options": {}}
            if "timeout_ms" in backends[bus] and profile.backends[bus].get("timeout_ms") is None:
                # the buses' simulators are threads of this test process (a UR controller ticks at
                # 500 Hz): a serial reply may wait for the GIL longer than --sim's 30 ms
                backends[bus] = {**backends[bus], "timeout_ms": 100.0}
        return msgspec.structs.replace(profile, backends=backends)

    def clear_errors(self) -> None:
        for row, s in zip(self.rows, self.sims):
            row.clear_errors(s)

    def settle(self) -> None:
        for row, s in zip(self.rows, self.sims):
            if row.settle is not None:
                row.settle(s)
        # a bus served at its own rate takes a setpoint at its own next cycle: two of them
        cycles = self.backend.own_rate_cycles() if self.own_rate else {}
        for bus, n in cycles.items():
            wait_until(lambda: self.backend.own_rate_cycles()[bus] >= n + 2, 2, interval=0.001,
                       what=f"two cycles of bus {bus!r} at its own rate")

    def prepare(self) -> None:
        for row, s in zip(self.rows, self.sims):
            if row.prepare is not None:
                row.prepare(s)

    def set_torque_delay(self, seconds: float) -> None:
        for s in self.sims:
            s.set_torque_delay(seconds)

    def set_unplugged(self, unplugged: bool) -> None:
        for s in self.sims:
            s.set_unplugged(unplugged)

    #: the buses the composite serves at their own rate (set once it is open): their reads run on
    #: their own cycles whatever the loop does, so the bytes the loop's calls put on the buses
    #: leave them out (tests/test_composite.py checks such a bus is not written while disabled)
    own_rate: frozenset = frozenset()
    backend = None  # the composite, once open

    @property
    def rx_bytes(self) -> int:
        return sum(s.rx_bytes for name, s in zip(self.names, self.sims) if name not in self.own_rate)


#: several buses in one robot (backends/composite.py), each row a robot the composite serves:
#: two SO-101 arms on two Feetech buses; a UR arm with a Robotiq 2F-85 gripper (the CRTK spec's
#: `/UR`, `/UR/gripper`; the gripper's bus, slower than the arm's 500 Hz, served at its own
#: rate); a CiA 402 pan / tilt whose pan homes natively beside a Feetech arm; a Feetech arm with
#: a Dynamixel gripper
COMPOSITES = {
    "composite (bimanual_so101)": ROOT / "profiles" / "bimanual_so101.yaml",
    "composite (ur + robotiq gripper)": ROOT / "profiles" / "ur5e_robotiq.yaml",
    "composite (canopen homing + feetech)": TEST_PROFILES / "pantilt_homing_so101.yaml",
    "composite (feetech + dynamixel)": TEST_PROFILES / "so101_xl330_gripper.yaml",
}
COMPOSITE = "composite (bimanual_so101)"
for _name, _path in COMPOSITES.items():
    ROWS[_name] = _composite_row(_name, _path)


def simulated_backends() -> list[str]:
    """Registered backends that declare a simulator (their SDK importable)."""
    out = []
    for name in registry.names():
        try:
            backend_class(name)
        except Exception:  # SDK missing: that backend is not tested here
            continue
        if registry.registration(name).simulator is not None:
            out.append(name)
    return out


class Rig:
    """A backend on its simulator (opened and configured), plus a controller to drive cycles."""

    def __init__(self, row: Row):
        self.row = row
        profile = load_profile(row.profile)
        if profile.backends is not None:  # several buses: one simulator each, the composite
            self.sim = BusSims(profile)
            self.sim.start()
            self.profile = self.sim.wired(profile)
            self.backend: Actuator = create_backend(self.profile)
        else:
            cls = backend_class(row.backend)
            self.sim = (row.make_sim(profile) if row.make_sim is not None
                        else backend_simulator(row.backend).from_profile(profile))
            self.sim.start()
            self.profile = cls.sim_profile(profile, self.sim.port)
            if getattr(self.sim, "interface", None) == "virtual":  # an in-process CAN simulator
                self.profile = msgspec.structs.replace(
                    self.profile, backend={**self.profile.backend, "interface": "virtual", "options": {}})
            self.backend = cls(self.profile)
        self.backend.open()
        self.backend.configure()
        if isinstance(self.sim, BusSims):
            self.sim.own_rate = frozenset(getattr(self.backend, "own_rate", ()))
            self.sim.backend = self.backend
        #: the cycle as production runs it (core/cycle.py): paced by the backend's wait_cycle
        self.runner = CycleRunner(self.backend, effective_period_s(self.profile, self.backend))
        self.fb = self.runner.feedback
        self.ids = [row.device(self.profile, i) for i in range(self.backend.n)]
        self.controller: Controller | None = None

    def make_controller(self) -> Controller:
        self.controller = Controller(self.profile, self.backend, time.time, effective_period_s(self.profile, self.backend))
        self.cycle()
        return self.controller

    def cycle(self, n: int = 1) -> None:
        """``n`` loop cycles, the loop's own (core/cycle.py): wait, read, step, write."""
        c = self.controller
        for _ in range(n):
            self.runner.cycle(c)
            c.outbox.clear() if len(c.outbox) > 10_000 else None

    def read(self) -> Fault | None:
        """One cycle without a controller (wait, read, the write of a cyclic_write backend);
        the read's fault."""
        return self.runner.idle()

    def request(self, rid: int, cmd: str, **kw) -> None:
        self.controller.handle({"id": rid, "cmd": cmd, **kw})

    def enable(self, rid: int, timeout: float = 10.0) -> dict:
        """``enable`` through the controller, cycling until its one reply; returns it."""
        self.request(rid, "enable")
        deadline = time.monotonic() + timeout
        while not self.replies(rid):
            assert time.monotonic() < deadline, "no reply to enable"
            self.cycle()
        return self.replies(rid)[0]

    def enabled_controller(self):
        """A controller whose robot is ENABLED (request id 1)."""
        c = self.make_controller()
        assert self.enable(1)["ok"] and c.state.value == "ENABLED"
        return c

    def replies(self, rid: int) -> list[dict]:
        return [m for m in self.controller.outbox if m.get("id") == rid]

    def events(self, kind: str) -> list[dict]:
        return [m["data"] for m in self.controller.outbox if m.get("event") == kind]

    def measured(self) -> np.ndarray:
        """The measured position, once the simulator has taken every command sent before: two
        cycles (a backend whose read takes what answered the previous cycle's SYNC, CANopen's,
        sees a command written before them in the second)."""
        if self.row.settle is not None:
            self.row.settle(self.sim)
        for _ in range(2):
            assert self.read() is None
        return self.fb.position.copy()

    def close(self) -> None:
        self.backend.close()
        self.sim.stop()


@pytest.fixture(params=simulated_backends() + list(COMPOSITES))
def rig(request):
    row = ROWS.get(request.param)
    if row is None:
        pytest.fail(f"backend {request.param!r} has a simulator but no row in tests/conformance/conftest.py")
    r = Rig(row)
    yield r
    r.close()
