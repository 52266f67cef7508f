"""Shared fixtures: real daemon and simulator processes, waited on with deadlines."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from crtk_bridge.profile import load_profile

from . import in_child

ROOT = Path(__file__).resolve().parent.parent
SO101 = ROOT / "profiles" / "so101.yaml"
SO101_URDF = ROOT / "profiles" / "urdf" / "so101.urdf"
KOCH = ROOT / "profiles" / "koch.yaml"
CANOPEN = ROOT / "profiles" / "canopen_2axis.yaml"
UR5E = ROOT / "profiles" / "ur5e.yaml"
ROBOTIQ = ROOT / "profiles" / "robotiq_2f85.yaml"


def profile_data(path: Path) -> dict:
    """A profile as data, with its URDF paths made absolute so a copy can live anywhere."""
    import yaml

    data = yaml.safe_load(path.read_text())
    for ns in data["namespaces"]:
        if "kinematics" in ns:
            ns["kinematics"]["urdf"] = str((path.parent / ns["kinematics"]["urdf"]).resolve())
    return data


def so101_data() -> dict:
    """profiles/so101.yaml as data, with its URDF path made absolute so a copy can live anywhere."""
    return profile_data(SO101)


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on now (for a test's Zenoh endpoints)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_until(predicate, timeout=10.0, interval=0.01, what="condition"):
    """Poll ``predicate`` until it is truthy; fail the test naming ``what`` after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(interval)


# Arm goals (rad, by joint index; an arm with fewer joints takes the first ones, one with more
# holds the others at 0) used by the end-to-end tests on every simulated robot; SimRobot checks
# each lies inside the robot's limits with a margin.
SAFE_GOALS = {
    "small": (0.1, 0.2, 0.3, 0.0, 0.0),
    "reach": (0.6, 0.3, -0.4, 0.2, 0.0),
    "far": (-0.6, 0.3, -0.4, 0.2, 0.0),
    "wide": (1.2, -1.0, 1.0, 0.5, 1.5),
}
GOAL_MARGIN = 0.1  # rad inside the position limits
#: what a test needs of a robot when it says nothing (``@pytest.mark.requires(...)``): the tests
#: written before the suite ran on other buses read servo registers through the simulator's dump
DEFAULT_REQUIRES = ("servo_bus",)


def _counts_per_rad(joint, row=None) -> float:
    """Device position units per joint radian, signed by the joint's direction: the row's
    ``units_per_rad`` (a UR: urad), else the backend keys ``counts_per_revolution`` x
    ``gear_ratio`` when the joint has them, else a 4096-tick servo (both serial profiles' servos)."""
    if row is not None and row.units_per_rad is not None:
        return row.units_per_rad
    keys = joint.backend
    cpr = keys.get("counts_per_revolution", 4096) * keys.get("gear_ratio", 1)
    return keys.get("direction", 1) * cpr / (2 * np.pi)


@dataclass(frozen=True, eq=False)
class SimRobot:
    """One simulated robot the end-to-end suite runs on: its profile, namespaces, and how a test
    reaches into its simulator (``row``: the conformance suite's hooks for its backend, used
    through :class:`RemoteSim` on the daemon's simulator control socket).

    Tests choose by what the robot offers, never by name: ``capabilities`` (see
    :func:`robot_capabilities`), the joint count, the commands ``list`` advertises. Device ids
    (servo ids, CANopen node ids) are strings, as the simulators' dump keys.
    """

    id: str
    profile: Path
    backend: str
    name: str  # the robot's (profile) name: the ``ns`` of robot-wide events, e.g. a FAULT
    arm: str
    gripper: str | None  # the second namespace (one joint), if any
    joint_names: tuple[str, ...]
    gripper_joint: str | None
    arm_ids: tuple[str, ...]
    gripper_id: str | None
    servo_id: dict  # joint name -> device id (int)
    pos_min: np.ndarray
    pos_max: np.ndarray
    vel_max: np.ndarray
    home: np.ndarray
    counts_per_rad: dict  # device id -> device position units per joint radian (signed)
    servo_timeout_s: float
    rate_hz: float
    goals: dict  # name -> np.ndarray, see SAFE_GOALS
    row: object  # tests.conformance.conftest.Row
    capabilities: frozenset

    @classmethod
    def load(cls, id: str, path: Path) -> SimRobot:
        from .conformance.conftest import ROWS

        p = load_profile(path)
        row = ROWS[p.backend_type]
        arm_ns = p.namespaces[0]
        grip_ns = p.namespaces[1] if len(p.namespaces) > 1 else None
        by_name = {j.name: j for j in p.joints}
        index = {j.name: i for i, j in enumerate(p.joints)}
        arm = [by_name[n] for n in arm_ns.joints]
        grip = by_name[grip_ns.joints[0]] if grip_ns is not None else None
        lo = np.array([j.limits.position_min for j in arm])
        hi = np.array([j.limits.position_max for j in arm])
        goals = {k: np.array((tuple(v) + (0.0,) * len(arm))[:len(arm)]) for k, v in SAFE_GOALS.items()}
        # an arm: the suite's goals fit its limits; a gripper alone (one joint, metres) is no arm:
        # its goals are the same share of its range as each goal's first joint is of +-1.5 rad
        is_arm = len(arm) > 1
        if not is_arm:
            goals = {k: lo + (hi - lo) * (0.5 + v[0] / 3.0) for k, v in SAFE_GOALS.items()}
        for k, g in goals.items():
            assert not is_arm or np.all(g >= lo + GOAL_MARGIN) and np.all(g <= hi - GOAL_MARGIN), \
                f"{path}: SAFE_GOALS[{k!r}] = {g} is not inside the limits of {arm_ns.name}"
        device = {j.name: row.device(p, index[j.name]) for j in p.joints}
        return cls(id=id, profile=path, backend=p.backend_type, name=p.name, arm=arm_ns.name,
                   gripper=grip_ns.name if grip_ns is not None else None,
                   joint_names=tuple(arm_ns.joints), gripper_joint=grip.name if grip is not None else None,
                   arm_ids=tuple(str(device[j.name]) for j in arm),
                   gripper_id=str(device[grip.name]) if grip is not None else None,
                   servo_id=device, pos_min=lo, pos_max=hi,
                   vel_max=np.array([j.limits.velocity_max for j in arm]),
                   home=np.array([j.home for j in arm]),
                   counts_per_rad={str(device[j.name]): _counts_per_rad(j, row) for j in p.joints},
                   servo_timeout_s=p.safety.servo_timeout_s, rate_hz=float(p.loop.rate_hz), goals=goals,
                   row=row, capabilities=robot_capabilities(p, grip_ns is not None, is_arm))

    @property
    def n(self) -> int:
        return len(self.joint_names)

    @property
    def servo_ids(self) -> tuple[str, ...]:
        """Every device id (the arm's, then the gripper's)."""
        return self.arm_ids + ((self.gripper_id,) if self.gripper_id is not None else ())

    def data(self) -> dict:
        return profile_data(self.profile)

    def vec(self, *by_index: tuple[int, float], **by_joint: float) -> np.ndarray:
        """An arm vector, zero except the given joints: ``robot.vec(elbow_flex=0.1)`` or, on any
        arm, ``robot.vec((robot.j(2), 0.1))`` (values add up where indices coincide)."""
        out = np.zeros(self.n)
        for i, value in by_index:
            out[i] += value
        for name, value in by_joint.items():
            out[self.joint_names.index(name)] += value
        return out

    def j(self, k: int) -> int:
        """The arm joint playing the role of the five-joint arm's joint ``k`` on this arm (an arm
        with fewer joints: its last)."""
        return min(k, self.n - 1)

    def sim(self, control_path: str) -> RemoteSim:
        """The robot's simulator behind its control socket, as the conformance row's hooks use it
        (the row's ``remote``, else :class:`RemoteSim`)."""
        return (self.row.remote or RemoteSim)(control_path)

    def prepare(self, control_path: str) -> None:
        """The row's ``prepare`` on a simulator just started (quick where the device is slow)."""
        if self.row.prepare is not None:
            self.row.prepare(self.sim(control_path))

    def torque(self, sim: RemoteSim, ids=None) -> dict[str, bool]:
        """Torque (power stage) on, per device id (every device unless ``ids``)."""
        return {i: bool(self.row.torque(sim, int(i))) for i in (self.servo_ids if ids is None else ids)}

    def free(self, sim: RemoteSim, ids=None) -> dict[str, bool]:
        """Free (no torque applied, nothing held; the row's ``free`` hook, else torque off), per
        device id (every device unless ``ids``)."""
        hook = self.row.free or (lambda s, i: not self.row.torque(s, i))
        return {i: bool(hook(sim, int(i))) for i in (self.servo_ids if ids is None else ids)}


def robot_capabilities(profile, has_gripper: bool, is_arm: bool = True) -> frozenset:
    """What a robot offers the suite, from its profile and its simulator (never its name):

    - ``arm``: its first namespace is an arm of several joints in radians, within whose limits the
      suite's arm goals (:data:`SAFE_GOALS`) lie. A gripper alone (one joint, its opening in
      metres, no measured velocity: the Robotiq 2F) is not: the modules that drive arm poses in
      rad-sized steps, check stopping distances or measured velocity need ``arm``
      (test_e2e_joint, test_e2e_sim, test_e2e_velocity_bounds); the gripper's own commands are
      tested in test_backend_robotiq.py, and the rest of the suite (processes, requests, streams,
      faults, slow enable, crtk-ctl) runs on it with goals that are shares of its range;

    - ``gripper``: a second, one-joint namespace;
    - ``servo_bus``: the simulator is a serial servo bus (servo registers and the ``servos`` dump);
    - ``fault:<kind>``: a fault kind its simulator injects into one device (``silent``, ...);
    - ``park``: ``shutdown.action: park``;
    - ``kinematics``: a namespace with a URDF (cartesian commands);
    - ``calibration``: its backend imports another tool's calibration file (``calibrate import``);
    - ``native_cartesian``: its backend does cartesian control itself (a UR: servoL / speedL, its
      TCP pose and wrench), no IK or Jacobian mapping in the daemon.
    """
    import importlib

    from crtk_bridge.backends import backend_class
    from crtk_bridge.core.actuator import Actuator
    from crtk_bridge.registry import backend_simulator
    from crtk_bridge.sim.bus import BusSimulator

    sim_cls = backend_simulator(profile.backend_type)
    caps = {f"fault:{k.value}" for k in getattr(importlib.import_module(sim_cls.__module__), "FaultKind", ())}
    if issubclass(sim_cls, BusSimulator):
        caps.add("servo_bus")
    if has_gripper:
        caps.add("gripper")
    if is_arm:
        caps.add("arm")
    if profile.shutdown.action == "park":
        caps.add("park")
    if any(ns.kinematics is not None for ns in profile.namespaces):
        caps.add("kinematics")
    if backend_class(profile.backend_type).calibration_import is not Actuator.calibration_import:
        caps.add("calibration")
    # traits are final only once open; a backend whose traits never depend on its devices (a UR
    # arm) keeps them as the class constant TRAITS its _traits_hook returns
    traits = getattr(backend_class(profile.backend_type), "TRAITS", None)
    if traits is not None and traits.capabilities.native_cartesian:
        caps.add("native_cartesian")
    return frozenset(caps)


class RemoteSim:
    """A running simulator reached over its control socket, offering the calls of an in-process
    simulator that the conformance rows' hooks make (``servo(id).read/write``, ``set_fault``,
    ``clear_faults``, ``set_unplugged``, ``set_torque_delay``): one set of hooks per backend for
    both suites."""

    def __init__(self, path: str):
        self.path = str(path)

    def req(self, **request) -> dict:
        from crtk_bridge.sim.control import control_request

        reply = control_request(self.path, request)
        assert reply.get("ok"), (request, reply)
        return reply

    def servo(self, device_id: int) -> _RemoteDevice:
        return _RemoteDevice(self, int(device_id))

    drive = servo

    def set_fault(self, device_id: int, kind: str, code: int = 0) -> None:
        self.req(cmd="fault", id=int(device_id), kind=kind, bits=code)

    def clear_faults(self) -> None:
        self.req(cmd="clear_faults")

    def set_unplugged(self, on: bool) -> None:
        self.req(cmd="unplug", on=bool(on))

    def set_torque_delay(self, seconds: float) -> None:
        self.req(cmd="torque_delay", seconds=seconds)


    def devices(self) -> dict[str, dict]:
        """The simulator's dump, per device id (the serial buses' ``servos``, the drives')."""
        dump = self.req(cmd="dump")
        return dump["servos"] if "servos" in dump else dump["drives"]


class _RemoteDevice:
    def __init__(self, sim: RemoteSim, device_id: int):
        self.sim, self.id = sim, device_id

    def read(self, register: str) -> int:
        return self.sim.req(cmd="read", id=self.id, register=register)["value"]

    def write(self, register: str, value: int) -> None:
        self.sim.req(cmd="write", id=self.id, register=register, value=int(value))


SIM_ROBOTS = {r.id: r for r in (SimRobot.load("so101-feetech", SO101), SimRobot.load("koch-dynamixel", KOCH),
                                SimRobot.load("canopen-2axis", CANOPEN), SimRobot.load("ur5e", UR5E),
                                SimRobot.load("robotiq-2f85", ROBOTIQ))}


def only_on(*ids: str):
    """Restrict a test that uses ``sim_daemon`` / ``sim_robot`` to some simulated robots."""
    return pytest.mark.parametrize("sim_robot", [SIM_ROBOTS[i] for i in ids], ids=list(ids), indirect=True)


def requires(item_or_metafunc) -> set[str]:
    """The capabilities a test needs: the union of its ``requires`` markers (module, class,
    function), else :data:`DEFAULT_REQUIRES`."""
    marks = list(item_or_metafunc.definition.iter_markers("requires"))
    if not marks:
        return set(DEFAULT_REQUIRES)
    return {c for m in marks for c in m.args}


def sim_robot_params(metafunc) -> list:
    """Every simulated robot, those lacking a capability the test needs skipped saying which."""
    need = requires(metafunc)
    out = []
    for r in SIM_ROBOTS.values():
        missing = sorted(need - r.capabilities)
        marks = [pytest.mark.skip(reason=f"{r.profile.name} lacks {', '.join(missing)}")] if missing else []
        out.append(pytest.param(r, id=r.id, marks=marks))
    return out


def pytest_configure(config):
    # a suite started in the background of a non-interactive shell (`cmd &`, a CI runner without job
    # control) inherits SIGINT ignored, and so would every crtk-ctl and daemon it starts: the tests
    # of what Ctrl-C does would see nothing. A handled signal is reset to its default by exec, so
    # handling it here gives each child the SIGINT a terminal would
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    # every daemon a test faults writes its black box (docs/recording.md) under $XDG_STATE_HOME:
    # a folder of the test run's, never the user's ~/.local/state
    config._crtk_state_home = os.environ["XDG_STATE_HOME"] = tempfile.mkdtemp(prefix="crtk-test-state-")
    config.pluginmanager.register(in_child, "crtk-in-child")  # the in_child marker (tests/in_child.py)
    # pytest-xdist's ``-n N`` alone distributes single tests (``--dist load``): here whole test
    # files go to each worker (``loadfile``), so a module's fixtures stay one (its shared daemons,
    # its in_child child pytest, a module-scoped simulator) and its tests keep their order
    if getattr(config.option, "dist", "no") == "load":
        config.option.dist = "loadfile"
    config.addinivalue_line("markers", "requires(*capabilities): the simulated robots a test using sim_robot "
                            "runs on (tests/conftest.py robot_capabilities); none given: servo_bus")
    config.addinivalue_line("markers", "reuse_daemon: the test leaves its robot as it found it, or in a state "
                            "sim_daemon can restore (DISABLED, at its start pose, no fault): one daemon per "
                            "robot per module serves every such test (tests/conftest.py SharedDaemons)")


def pytest_unconfigure(config):
    if hasattr(config, "_crtk_state_home"):
        shutil.rmtree(config._crtk_state_home, ignore_errors=True)


# pytest-xdist (``python -m pytest -q -n 2``): its controller collects nothing, so the
# LeRobot conftest's build is started from here when the first worker has collected (the workers
# collect the same tests), and stopped when the controller's session ends
@pytest.hookimpl(optionalhook=True)
def pytest_xdist_node_collection_finished(node, ids):
    from .lerobot import conftest as lerobot

    lerobot.xdist_collected(node.config, ids)


def pytest_sessionfinish(session):
    if not hasattr(session.config, "workerinput") and "tests.lerobot.conftest" in sys.modules:
        sys.modules["tests.lerobot.conftest"].stop_build()


def pytest_generate_tests(metafunc):
    if "sim_robot" not in metafunc.fixturenames:
        return
    for m in metafunc.definition.iter_markers("parametrize"):
        names = m.args[0] if m.args else m.kwargs.get("argnames", "")
        if "sim_robot" in (names.replace(" ", "").split(",") if isinstance(names, str) else names):
            return  # only_on: the test chose its robots
    metafunc.parametrize("sim_robot", sim_robot_params(metafunc), indirect=True)


@contextlib.contextmanager
def standalone_sim(robot: SimRobot, tmp: Path):
    """``crtk-sim <device>`` on its own (so what the devices do during and after a daemon's
    shutdown can be read), and a copy of the robot's profile wired to it by its backend
    (``sim_profile``): a pty link, or for a simulator on fixed TCP ports (a UR controller) a free
    127.0.0.N. Yields (profile path, the robot's remote simulator: :meth:`SimRobot.sim`)."""
    import yaml

    from crtk_bridge.backends import backend_class
    from crtk_bridge.registry import simulator_device
    from crtk_bridge.sim.loopback import free_loopback_host

    control = tmp / "sim.sock"
    wiring = backend_class(robot.backend).simulator
    if wiring.host_ports:
        endpoint = free_loopback_host(wiring.host_ports)
        where = ["--host", endpoint]

        def ready() -> bool:
            with socket.socket() as probe:
                probe.settimeout(0.5)
                return control.exists() and probe.connect_ex((endpoint, wiring.host_ports[0])) == 0
    else:
        endpoint = str(tmp / "tty")
        where = ["--link", endpoint]

        def ready() -> bool:
            return Path(endpoint).exists() and control.exists()
    sim = subprocess.Popen([sys.executable, "-m", "crtk_bridge.sim.cli", simulator_device(robot.backend), "--profile",
                            str(robot.profile), *where, "--control", str(control), "--parent-pid", str(os.getpid())],
                           stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, cwd=ROOT)
    try:
        wait_until(lambda: ready() or sim.poll() is not None, 15, what="simulator endpoint")
        assert sim.poll() is None, sim.stderr.read().decode()
        robot.prepare(str(control))
        data = robot.data()
        data["backend"] = dict(backend_class(robot.backend).sim_profile(load_profile(robot.profile), endpoint).backend)
        profile = tmp / "sim-profile.yaml"
        profile.write_text(yaml.safe_dump(data))
        yield profile, robot.sim(str(control))
    finally:
        sim.terminate()
        sim.wait(10)


@pytest.fixture
def short_tmp():
    """A short temp dir: Unix socket paths must stay under 108 bytes."""
    d = tempfile.mkdtemp(prefix="crtk-")
    yield Path(d)
    shutil.rmtree(d, ignore_errors=True)


class DaemonProcess:
    """``crtk-bridge`` as a real subprocess."""

    def __init__(self, args: list[str], socket_path: Path, log_path: Path, robot: SimRobot | None = None):
        self.robot = robot
        self.socket_path = socket_path
        self.log_path = log_path
        self._log = open(log_path, "wb")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "crtk_bridge.cli", *args, "--socket", str(socket_path)],
            stdout=self._log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, cwd=ROOT,
        )
        try:
            wait_until(lambda: socket_path.exists() or self.proc.poll() is not None, 30, what="daemon socket")
        except AssertionError:
            self.stop()
            raise
        if self.proc.poll() is not None:
            raise AssertionError(f"daemon exited with {self.proc.returncode}:\n{self.output()}")

    def output(self) -> str:
        self._log.flush()
        return self.log_path.read_text(errors="replace")

    def print_tail(self, lines: int = 30) -> None:
        """The end of the daemon's output on stdout (pytest shows it when the test failed)."""
        try:
            print(f"--- {self.log_path.name} (last {lines} lines) ---\n" + "\n".join(self.output().splitlines()[-lines:]))
        except (OSError, ValueError):
            pass

    def sim_control_path(self) -> str:
        for line in self.output().splitlines():
            if "simulator control socket" in line:
                return line.rsplit(" ", 1)[-1].rstrip(")")
        raise AssertionError("daemon did not print its simulator control socket:\n" + self.output())

    def terminate(self, timeout=15.0) -> int:
        self.proc.send_signal(signal.SIGTERM)
        return self.proc.wait(timeout)

    def _disable_quietly(self) -> None:
        """Teardown: disable (torque off) first, so that SIGTERM does not park an arm a test left
        ENABLED (profiles with shutdown.action: park); tests of shutdown use :meth:`terminate`."""
        try:
            with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
                s.settimeout(3.0)
                s.connect(str(self.socket_path))
                s.sendall(b'{"id": 1, "cmd": "disable"}\n')
                f = s.makefile("rb")
                for line in f:
                    if json.loads(line).get("id") == 1:
                        break
        except (OSError, ValueError):
            pass  # the daemon is gone or busy: SIGTERM still stops it safely

    def stop(self) -> None:
        if self.proc.poll() is None:
            self._disable_quietly()
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._log.close()


@pytest.fixture(scope="module")
def sim_robot(request) -> SimRobot:
    """Each simulated robot in turn (one end-to-end suite over every backend with a simulator),
    parametrized by :func:`pytest_generate_tests` after what the test ``requires``."""
    return request.param


def start_sim_daemon(robot: SimRobot, tmp: Path) -> DaemonProcess:
    """``crtk-bridge --profile <robot profile> --sim`` on a socket in ``tmp``, its simulator
    prepared (the row's ``prepare``)."""
    d = DaemonProcess(["--profile", str(robot.profile), "--sim"], tmp / f"{robot.id}.sock",
                      tmp / f"{robot.id}.log", robot=robot)
    try:
        robot.prepare(d.sim_control_path())
    except BaseException:
        d.stop()
        raise
    return d


RESTORE_TOL = 0.01  # rad: a shared daemon's arm this close to its start pose is left where it is


class SharedDaemons:
    """One daemon per simulated robot for a module's ``reuse_daemon`` tests (an enable or a
    daemon start costs a second on some robots). Before each reuse the daemon is put back as a
    fresh one starts: DISABLED, every namespace at the pose it started in; a daemon that is
    gone, in FAULT, or that cannot be restored is replaced by a fresh one. One runs at a time."""

    def __init__(self):
        self.tmp = Path(tempfile.mkdtemp(prefix="crtk-"))
        self.daemons: dict[str, DaemonProcess] = {}
        self.start_pose: dict[str, dict[str, np.ndarray]] = {}

    def get(self, robot: SimRobot) -> DaemonProcess:
        d = self.daemons.get(robot.id)
        if d is not None and not self._restore(d, self.start_pose[robot.id]):
            self._stop(robot.id)
            d = None
        if d is None:
            for other in list(self.daemons):
                self._stop(other)
            d = self.daemons[robot.id] = start_sim_daemon(robot, self.tmp)
            from crtk_bridge.client import connect

            client = connect(socket=str(d.socket_path))
            try:
                self.start_pose[robot.id] = {ns["name"]: client.device(ns["name"]).measured_jp()[0]
                                             for ns in client.list()["namespaces"]}
            finally:
                client.close()
        return d

    @staticmethod
    def _restore(d: DaemonProcess, start: dict[str, np.ndarray]) -> bool:
        """Put ``d`` back as it started; False where it cannot (the caller replaces it)."""
        from crtk_bridge.client import connect

        if d.proc.poll() is not None:
            return False
        try:
            client = connect(socket=str(d.socket_path))
        except Exception:  # noqa: BLE001 - any failure: a fresh daemon instead
            return False
        try:
            devices = {ns: client.device(ns) for ns in start}
            arm = devices[d.robot.arm]
            if arm.is_fault():
                return False
            away = [ns for ns, dev in devices.items()
                    if not np.allclose(dev.measured_jp()[0], start[ns], atol=RESTORE_TOL)]
            if away:
                if not arm.is_enabled() and not arm.enable(10.0):
                    return False
                handles = [devices[ns].move_jp(start[ns]) for ns in away]
                if not all(h.wait(timeout=20.0) for h in handles):
                    return False
                wait_until(lambda: all(np.allclose(devices[ns].measured_jp()[0], start[ns], atol=RESTORE_TOL)
                                       for ns in away), 5, what="the start pose")
            return (arm.is_disabled() or arm.disable(5.0)) and arm.is_disabled()
        except Exception:  # noqa: BLE001 - any failure: a fresh daemon instead
            return False
        finally:
            client.close()

    def _stop(self, robot_id: str) -> None:
        d = self.daemons.pop(robot_id, None)
        if d is not None:
            d.stop()

    def close(self) -> None:
        for robot_id in list(self.daemons):
            self._stop(robot_id)
        shutil.rmtree(self.tmp, ignore_errors=True)


@pytest.fixture(scope="module")
def shared_daemons():
    pool = SharedDaemons()
    yield pool
    pool.close()


@pytest.fixture
def sim_daemon(request, short_tmp, sim_robot):
    """``crtk-bridge --profile <robot profile> --sim`` on its own socket; ``.robot`` is the SimRobot.
    A test marked ``reuse_daemon`` shares its module's daemon for that robot (:class:`SharedDaemons`)."""
    if request.node.get_closest_marker("reuse_daemon") is not None:
        d = request.getfixturevalue("shared_daemons").get(sim_robot)
        yield d
        d.print_tail()
        return
    d = start_sim_daemon(sim_robot, short_tmp)
    yield d
    d.print_tail()
    d.stop()


class RawSession:
    """A plain JSON-lines session on the socket (as any language would speak it), recording
    every pushed operating_state event in order."""

    def __init__(self, path: str):
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.sock.connect(path)
        self.states: list[dict] = []
        self.events: list[dict] = []
        self.lock = threading.Lock()
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self):
        f = self.sock.makefile("rb")
        for line in f:
            msg = json.loads(line)
            with self.lock:
                if msg.get("event") == "operating_state":
                    self.states.append(msg["data"])
                elif "event" in msg:
                    self.events.append(msg)

    def busy_edges(self) -> list[bool]:
        """is_busy of each state event, with repeats of the same value collapsed."""
        with self.lock:
            out: list[bool] = []
            for s in self.states:
                if not out or out[-1] != s["is_busy"]:
                    out.append(s["is_busy"])
            return out

    def close(self):
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self.sock.close()


class Installed:
    """crtk-bridge installed NON-editable (``pip install .``, a wheel built from a copy of this
    tree) into its own venv in a temporary folder outside the clone. The venv reuses the test
    venv's dependencies through a ``.pth`` (so building it takes seconds, not a download of
    pinocchio), but not its editable crtk_bridge: ``import crtk_bridge`` finds the installed copy.
    :meth:`run` / :meth:`popen` run its console scripts from a folder outside the clone."""

    def __init__(self, base: Path):
        self.base = base
        self.venv = base / "venv"
        self.bin = self.venv / "bin"
        self.python = self.bin / "python"
        self.runtime = base / "run"  # XDG_RUNTIME_DIR: the default sockets, apart from the user's
        self.runtime.mkdir(mode=0o700)

    def env(self, **extra: str) -> dict[str, str]:
        env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONSAFEPATH", "VIRTUAL_ENV")}
        env.update(PATH=f"{self.bin}{os.pathsep}{env.get('PATH', '')}", XDG_RUNTIME_DIR=str(self.runtime), **extra)
        return env

    def cwd(self, name: str) -> Path:
        """A fresh working folder outside the clone."""
        d = Path(tempfile.mkdtemp(prefix=f"{name}-", dir=self.base))
        return d

    def run(self, args: list[str], cwd: Path, timeout: float = 60.0, **kw) -> subprocess.CompletedProcess:
        return subprocess.run([str(self.bin / args[0]), *args[1:]], cwd=cwd, env=self.env(), capture_output=True,
                              text=True, timeout=timeout, stdin=subprocess.DEVNULL, **kw)

    def popen(self, args: list[str], cwd: Path, log: Path) -> subprocess.Popen:
        with open(log, "wb") as f:
            return subprocess.Popen([str(self.bin / args[0]), *args[1:]], cwd=cwd, env=self.env(), stdout=f,
                                    stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)


def _build_installed(base: Path) -> Installed:
    import sysconfig

    inst = Installed(base)
    src = base / "src"
    shutil.copytree(ROOT, src, ignore=shutil.ignore_patterns(
        ".git", ".venv", "build", "dist", "*.egg-info", "__pycache__", ".pytest_cache", "tests", "bench"))
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(inst.venv)], check=True, timeout=120)
    site = Path(subprocess.run([str(inst.python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                               check=True, capture_output=True, text=True).stdout.strip())
    # the test venv's dependencies (and its .pth hooks, e.g. cmeel's for pinocchio), not its crtk_bridge
    ours = {sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]}
    lines = sorted(ours)
    for d in sorted(ours):
        for pth in sorted(Path(d).glob("*.pth")):
            if "crtk" in pth.name or "editable" in pth.name or "distutils" in pth.name:
                continue
            lines += [ln for ln in pth.read_text().splitlines() if ln.startswith("import ")]
    (site / "_crtk_test_deps.pth").write_text("\n".join(lines) + "\n")
    # --ignore-installed: the test venv's crtk-bridge, visible through the .pth, is never touched
    subprocess.run([sys.executable, "-m", "pip", "--python", str(inst.python), "install", "--no-deps", "-q",
                    "--ignore-installed", "--disable-pip-version-check", str(src)], check=True, timeout=600,
                   capture_output=True)
    shutil.rmtree(src)
    return inst


@pytest.fixture(scope="session")
def installed():
    """:class:`Installed`, built once per session."""
    base = Path(tempfile.mkdtemp(prefix="crtk-inst-"))
    try:
        yield _build_installed(base)
    finally:
        shutil.rmtree(base, ignore_errors=True)
