"""Process wiring: the front process (this one, asyncio) and the control process (forked).

``run(profile_path, ...)`` loads the profile, starts the simulator when asked (``--sim``), forks
the control process with a command pair and a shared-memory snapshot, serves the socket API, and
shuts everything down in order on SIGTERM / SIGINT: motion stops and torque goes off in the
control process first, then the socket is removed and the simulator stopped. Exit status 0 on a
requested shutdown, 1 when start-up fails or the control process dies.
"""

from __future__ import annotations

import asyncio
import logging
import multiprocessing
import os
import re
import signal
import socket
import stat
import subprocess
import sys
import tempfile
import time

import msgspec

from . import systemd
from .backends import backend_class, create_backend
from .client.paths import default_socket_path
from .core.actuator import SimWiring
from .core.kinematics_check import check_kinematics
from .core.loop import control_main
from .core.samples import SampleRing, ring_slots
from .core.snapshot import Layout, SnapshotBuffer
from .errors import BackendUnavailableError, CrtkBridgeError
from .profile import Profile, load_profile
from .registry import simulator_device
from .server.link import ControlLink
from .server.server import Server
from .sim.loopback import free_loopback_host, ports_free
from .spawn import module_argv, module_env
from .transport.zenoh_session import ZenohConfig, check_exposure, open_session, zenoh_config

log = logging.getLogger("crtk_bridge.daemon")

STARTUP_TIMEOUT_S = 20.0
HOST_ATTEMPTS = 3  # --sim on a loopback address another process took meanwhile: tries in all
SHUTDOWN_TIMEOUT_S = 3.0  # below the unit's TimeoutStopSec=5, so our own clean-up runs
#: longest AF_UNIX socket path in bytes (Linux ``sun_path`` is 108 bytes with the final NUL)
AF_UNIX_PATH_MAX = 107


def _die_with_parent() -> None:
    """In a child before exec: SIGTERM it when the daemon dies, however it dies (Linux prctl)."""
    try:
        import ctypes

        PR_SET_PDEATHSIG = 1
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)
    except (OSError, AttributeError):
        pass  # not Linux: the daemon's normal shutdown still stops the simulator


#: the nice value ``--sim`` asks for its simulator (where permitted): a device on a bus is never
#: late because the PC is busy, so neither is the simulated one, which the control loop
#: (SCHED_FIFO) would otherwise find silent on a loaded host and rightly FAULT
SIM_NICE = -10


def _simulator_child(raise_priority: bool) -> None:
    """In the simulator's process before exec: dies with the daemon; a raised priority if asked
    and permitted (else none, silently: the daemon says once what real-time it could not have)."""
    _die_with_parent()
    if raise_priority:
        try:
            os.setpriority(os.PRIO_PROCESS, 0, SIM_NICE)
        except OSError:
            pass


def _accepts(host: str, port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.settimeout(0.5)
        return probe.connect_ex((host, port)) == 0


def pty_link(workdir: str, bus: str | None = None) -> str:
    """Where ``--sim`` links a serial bus simulator's pty (``bus``: one of several buses)."""
    return os.path.join(workdir, f"tty-{bus}" if bus else "tty")


class SimulatorProcess:
    """``crtk-sim <device>`` as a child process, serving its endpoint at ``link``: a pty link, or
    for a simulator with fixed TCP ports (``host_ports``) a free loopback address."""

    def __init__(self, profile_path: str, device: str, workdir: str, bus: str | None = None,
                 host_ports: tuple[int, ...] = (), raise_priority: bool = False, tool_link: str | None = None):
        tag = f"-{bus}" if bus else ""  # several buses: one simulator each
        self.control = os.path.join(workdir, f"sim{tag}.sock")
        # a free 127.0.0.N is free when probed, not yet bound: another process starting a simulator
        # meanwhile (parallel test workers, two daemons) may take it first; the simulator then
        # exits (cannot bind) and a freshly chosen address is tried
        for attempt in range(HOST_ATTEMPTS if host_ports else 1):
            if host_ports:
                self.link = free_loopback_host(host_ports)
                where = ["--host", self.link]
            else:
                self.link = pty_link(workdir, bus)
                where = ["--link", self.link]
            self.proc = subprocess.Popen(
                module_argv("crtk_bridge.sim.cli", device, "--profile", profile_path, *where, "--control", self.control,
                            *(["--bus", bus] if bus else []), *(["--tool-link", tool_link] if tool_link else []),
                            "--parent-pid", str(os.getpid()), "--workdir", workdir),
                stdout=subprocess.DEVNULL, stdin=subprocess.DEVNULL,
                env=module_env(),  # this package's simulator, whatever the current folder holds (spawn.py)
                start_new_session=True,  # a terminal Ctrl-C must not kill the bus under the control process
                # ...but a daemon killed outright must not leave it running; SIM_NICE with realtime
                preexec_fn=lambda: _simulator_child(raise_priority),
            )
            started = self._started(host_ports)
            if started or attempt == HOST_ATTEMPTS - 1 or ports_free(self.link, host_ports):
                break
            log.info("--sim: %s was taken while the simulator started; trying another address", self.link)
        if not started:
            raise CrtkBridgeError(f"--sim: the simulator exited with status {self.proc.returncode}")

    def _started(self, host_ports: tuple[int, ...]) -> bool:
        """Wait for the simulator's endpoint: True once it serves, False if it exited first."""
        def started() -> bool:
            if not os.path.exists(self.control):
                return False
            return _accepts(self.link, host_ports[0]) if host_ports else os.path.exists(self.link)

        deadline = time.monotonic() + STARTUP_TIMEOUT_S
        while not started():
            if self.proc.poll() is not None:
                return False
            if time.monotonic() > deadline:
                self.stop()
                raise CrtkBridgeError("--sim: the simulator did not start")
            time.sleep(0.02)
        return True

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(SHUTDOWN_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


def check_socket_path(path: str, robot: str) -> list[str]:
    """Fail at once, in one line, when the daemon could not serve ``path``: too long for AF_UNIX,
    a file that is not a socket, a directory that cannot be created, or another daemon already
    answering there. Creates the directory (mode 0750) and returns the directories it created,
    innermost first (removed again when the start fails). Blocks for at most one local connect.
    Called before the simulator and the control process start. Raises CrtkBridgeError."""
    size = len(os.fsencode(path))
    if size > AF_UNIX_PATH_MAX:
        raise CrtkBridgeError(f"{robot}: socket path {path} is {size} bytes, longer than the AF_UNIX "
                              f"limit of {AF_UNIX_PATH_MAX}: give a shorter --socket")
    parent = os.path.dirname(os.path.abspath(path))
    created = []
    missing = parent
    while not os.path.isdir(missing) and os.path.dirname(missing) != missing:
        created.append(missing)
        missing = os.path.dirname(missing)
    try:
        os.makedirs(parent, mode=0o750, exist_ok=True)
    except OSError as exc:
        raise CrtkBridgeError(f"{robot}: cannot create the socket directory {parent}: "
                              f"{exc.strerror or exc}") from None
    if not os.access(parent, os.W_OK | os.X_OK):
        raise CrtkBridgeError(f"{robot}: cannot create the socket {path}: no write permission on {parent}")
    try:
        mode = os.lstat(path).st_mode
    except FileNotFoundError:
        return created
    except OSError as exc:
        raise CrtkBridgeError(f"{robot}: cannot use the socket path {path}: {exc.strerror or exc}") from None
    if not stat.S_ISSOCK(mode):
        raise CrtkBridgeError(f"{robot}: {path} exists and is not a socket; not replacing it "
                              f"(give another --socket)")
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as probe:
        probe.settimeout(1.0)
        try:
            probe.connect(path)
        except TimeoutError:
            pass  # a daemon too busy to accept is still a daemon
        except OSError:
            return created  # a stale socket left by a daemon that died: the server replaces it
    raise CrtkBridgeError(f"{robot}: another daemon is already serving {path} (stop it, or give "
                          f"another --socket)")


def _control_process(profile: Profile, source: str, chan: socket.socket, front: socket.socket,
                     snap: SnapshotBuffer, realtime: bool, samples: SampleRing | None = None) -> None:
    # the fork copied the front's end of the pair: close it, or the loop would never see EOF
    # when the front process dies (and would keep the robot enabled with nobody in charge)
    front.close()
    code = control_main(profile, lambda: create_backend(profile, source=source), chan, snap, realtime=realtime,
                        samples=samples)
    sys.exit(code)


def zenoh_services(server: Server, session, config: ZenohConfig) -> list:
    """What the front process serves on its Zenoh session (docs/zenoh.md), in start order.

    Each service is built with the running server (its sessions, control rules, link to the
    control process and events), the open ``zenoh.Session`` and the transport's configuration,
    and has ``async start()`` and ``async close()``. Started on the event loop before the socket
    serves (a failure ends start-up with the robot still DISABLED); closed after the control
    process stopped (a remote client sees the robot stop first).
    """
    from .transport.ros.graph import RosGraph
    from .transport.tunnel import TunnelServer

    return [TunnelServer(server, session, config),
            RosGraph(session, server, domain_id=config.ros_domain_id, rate_hz=config.publish_rate_hz)]


async def _serve(server: Server, link: ControlLink, proc: multiprocessing.Process,
                 zenoh: tuple | None = None) -> int:
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    signals = 0

    def on_signal() -> None:
        # the first SIGTERM / SIGINT shuts down (a park first, if the profile says so); any later
        # one switches torque off at once. Counted here, not only in the control process: a
        # signal sent by pid (kill, systemd's main-process kill) reaches this process alone,
        # while a terminal's Ctrl-C reaches both (the control process counts its own)
        nonlocal signals
        signals += 1
        stop.set()
        if signals > 1 and server.shutting_down:
            link.send_nowait("_torque_off")

    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, on_signal)
    link.attach(loop, server.on_control_lost)
    services = []
    try:
        if server.recorder is not None:  # the black box runs from the start
            server.recorder.start()
            await server.recorder.start_recording()  # --record / recording.dir: before anyone can enable
        if zenoh is not None:  # before the socket: nobody can have enabled the robot if one fails
            session, config = zenoh
            for service in zenoh_services(server, session, config):
                await service.start()
                services.append(service)
        await server.start()
    except BaseException:
        # a start-up that fails (a Zenoh twin, a socket already served) ends what it started: the
        # drain thread before run() unlinks the ring it reads
        await _close_services(server, services)
        if server.recorder is not None:
            await server.recorder.close()
        raise
    live = server.recorder.live if server.recorder is not None else None
    print(f"crtk-bridge: {server.robot} ({server.profile.backend_type}, {len(server.profile.joints)} joints) "
          f"serving CRTK on {server.socket_path}"
          + (f" and Zenoh ({_zenoh_where(zenoh[1])})" if zenoh else "")
          + (f"; Foxglove live view on {live.url} (read-only)" if live is not None else ""), flush=True)
    systemd.ready(f"serving {server.socket_path}")
    watchdog = systemd.watchdog_period()
    watchdog_task = loop.create_task(_watchdog(link, watchdog)) if watchdog else None

    stop_wait = loop.create_task(stop.wait())
    lost_wait = loop.create_task(server.control_lost.wait())
    await asyncio.wait({stop_wait, lost_wait}, return_when=asyncio.FIRST_COMPLETED)
    status = 1 if server.control_lost.is_set() else 0
    systemd.stopping()
    if watchdog_task:
        watchdog_task.cancel()
    # control process first: motion stops, torque off; then the socket goes
    server.shutting_down = True
    link.send_nowait("_shutdown")
    if signals > 1:  # two signals before the shutdown began: no park
        link.send_nowait("_torque_off")
    # a shutdown park (profile shutdown.action: park) runs within shutdown.timeout_s before torque off
    sd = server.profile.shutdown
    limit = SHUTDOWN_TIMEOUT_S + (sd.timeout_s if sd.action == "park" else 0.0)
    await loop.run_in_executor(None, proc.join, limit)
    if proc.is_alive():
        log.error("%s: the control process did not stop in %s s; killing it", server.robot, limit)
        proc.kill()
        proc.join()
        status = 1
    elif proc.exitcode not in (0, None) and status == 0:
        status = 1
    if server.recorder is not None:  # after the loop's last cycles: recordings hold the stop
        await server.recorder.close()
    await _close_services(server, services)
    await server.close()
    for t in (stop_wait, lost_wait):
        t.cancel()
    return status


async def _close_services(server: Server, services: list) -> None:
    for service in reversed(services):
        try:
            await service.close()
        except Exception:
            log.exception("%s: closing a Zenoh service failed", server.robot)


def _zenoh_where(config: ZenohConfig) -> str:
    parts = [f"connected to {', '.join(config.connect)}"] if config.connect else []
    if config.listen:
        parts.append(f"listening on {', '.join(config.listen)}")
    return "; ".join(parts + [f"ROS domain {config.ros_domain_id}"])


async def _watchdog(link: ControlLink, period: float) -> None:
    """Ping systemd's watchdog only while the control loop is cycling."""
    last = -1
    while True:
        await asyncio.sleep(period / 2)
        cycles = link.cycles()
        if cycles != last:
            systemd.watchdog_ping()
            last = cycles


def _sim_wiring(backend_type: str, source: str) -> tuple[str, SimWiring]:
    """(the ``crtk-sim`` device, how --sim wires it) of backend ``backend_type``: the registry
    names its simulator (crtk_bridge/registry.py), the backend how its profile takes the
    simulator's endpoint (actuator.SimWiring)."""
    try:
        device = simulator_device(backend_type, source)
    except BackendUnavailableError as exc:
        raise CrtkBridgeError(f"--sim: {exc}") from None
    wiring = backend_class(backend_type, source).simulator
    if wiring is None:
        raise CrtkBridgeError(f"--sim: {source}: backend {backend_type!r} declares no SimWiring "
                              f"(Actuator.simulator) though its registration names a simulator")
    return device, wiring


def _simulate_buses(profile: Profile, profile_path: str, workdir: str,
                    simulators: list[SimulatorProcess], realtime: bool) -> Profile:
    """--sim with several buses: one simulator per bus; the profile wired to their ports.
    Appends each started simulator to ``simulators`` (so they are stopped however this ends).

    A bus behind another bus's device (its endpoint ``socket://HOST:PORT``, where HOST is the
    other bus's endpoint and PORT that device's ``SimWiring.tool_port``: a gripper on a UR's tool
    flange) gets its simulator on a pty, which the other bus's simulator relays PORT to; its
    backend then reaches it through that simulator's PORT, as on the real robot."""
    wirings = {bus: _sim_wiring(str(section["type"]), profile_path) for bus, section in profile.backends.items()}
    behind = _behind(profile, wirings)  # bus -> (the bus whose device it is behind, the port)
    relays = {front: pty_link(workdir, bus) for bus, (front, _) in behind.items()}
    backends, started = {}, {}
    for bus, section in profile.backends.items():
        device, wiring = wirings[bus]
        simulator = SimulatorProcess(profile_path, device, workdir, bus=bus, host_ports=wiring.host_ports,
                                     raise_priority=realtime, tool_link=relays.get(bus))
        simulators.append(simulator)
        started[bus] = simulator
    for bus, section in profile.backends.items():
        simulator = started[bus]
        endpoint, where = simulator.link, f"on {simulator.link}"
        if bus in behind:
            front, port = behind[bus]
            endpoint = f"socket://{started[front].link}:{port}"
            where = f"behind bus {front!r}'s port {port} ({endpoint}; its line {simulator.link})"
        # the bus's section wired the way --sim wires a one-bus profile (the backend's sim_profile:
        # its endpoint, and the simulator's defaults where the section sets no value of its own)
        one_bus = msgspec.structs.replace(profile, backend=dict(section))
        backends[bus] = backend_class(str(section["type"]), profile_path).sim_profile(one_bus, endpoint).backend
        print(f"crtk-bridge: simulated {section['type']} bus {bus!r} {where} "
              f"(simulator control socket {simulator.control})", flush=True)
    return msgspec.structs.replace(profile, backends=backends)


def _behind(profile: Profile, wirings: dict[str, tuple[str, SimWiring]]) -> dict[str, tuple[str, int]]:
    """bus -> (the bus whose device it sits behind, that device's tool port), for every bus whose
    endpoint is ``socket://HOST:PORT`` with HOST another bus's endpoint and PORT its device's
    ``SimWiring.tool_port`` (a gripper on a UR's tool flange)."""
    out: dict[str, tuple[str, int]] = {}
    for bus, section in profile.backends.items():
        endpoint = str(section.get(wirings[bus][1].endpoint_key) or "")
        m = re.fullmatch(r"socket://([^:/]+):(\d+)/?", endpoint)
        if m is None:
            continue
        for front, other in profile.backends.items():
            wiring = wirings[front][1]
            if (front != bus and wiring.tool_port == int(m.group(2))
                    and str(other.get(wiring.endpoint_key)) == m.group(1)):
                out[bus] = (front, wiring.tool_port)
    return out


def _remove_dir(path: str | None) -> None:
    """Remove ``path`` and the files in it (the --sim work folder), quietly."""
    if not path:
        return
    for name in os.listdir(path) if os.path.isdir(path) else []:
        try:
            os.unlink(os.path.join(path, name))
        except OSError:
            pass
    try:
        os.rmdir(path)
    except OSError:
        pass


def run(profile_path: str, *, sim: bool = False, socket_path: str | None = None, realtime: bool = True,
        zenoh_connect: list[str] | None = None, zenoh_listen: list[str] | None = None,
        ros_domain_id: int | None = None, record_dir: str | None = None, foxglove_listen: str | None = None) -> int:
    """Run the daemon in the foreground until SIGTERM / SIGINT. Returns the exit status.
    ``zenoh_connect`` / ``zenoh_listen`` / ``ros_domain_id`` (the command line's) turn on and
    configure the Zenoh transport over the profile's ``transport.zenoh`` section. A start that
    fails leaves no folder behind that it created (the socket's, the --sim work folder)."""
    created: list[str] = []
    try:
        return _run(profile_path, created, sim=sim, socket_path=socket_path, realtime=realtime,
                    zenoh_connect=zenoh_connect, zenoh_listen=zenoh_listen, ros_domain_id=ros_domain_id,
                    record_dir=record_dir, foxglove_listen=foxglove_listen)
    except BaseException:
        for folder in created:  # innermost first; one another daemon now uses is not empty: kept
            try:
                os.rmdir(folder)
            except OSError:
                break
        raise


def _run(profile_path: str, created: list[str], *, sim: bool, socket_path: str | None, realtime: bool,
         zenoh_connect: list[str] | None, zenoh_listen: list[str] | None, ros_domain_id: int | None,
         record_dir: str | None = None, foxglove_listen: str | None = None) -> int:
    """:func:`run`, adding to ``created`` the folders it creates for the socket."""
    profile = load_profile(profile_path)
    zconfig = zenoh_config(profile, zenoh_connect, zenoh_listen, ros_domain_id)
    if zconfig is not None:
        check_exposure(zconfig, profile.name)  # refused before anything starts
    live = None
    if foxglove_listen is not None:  # loopback, or the Zenoh transport's TLS + access control opt-in
        from .recording.exposure import check as check_live

        live = check_live(foxglove_listen, profile, str(profile_path))
        import importlib.util
        try:
            found = importlib.util.find_spec("foxglove") is not None  # not imported: the fork comes first
        except (ImportError, ValueError):
            found = False
        if not found:
            raise CrtkBridgeError(f"{profile.name}: --foxglove-listen needs foxglove-sdk, an optional extra: "
                                  "pip install 'crtk-bridge[foxglove]'")
    source = str(profile_path)
    # validate the backend section (and that its SDK is installed) before anything starts
    create_backend(profile, source=source)
    check_kinematics(profile, source)  # a wrong frame or joint name, said with its profile key
    socket_path = socket_path or profile.server.socket or default_socket_path(profile.name)
    created.extend(check_socket_path(socket_path, profile.name))  # before the simulator and the control process

    workdir = None
    simulators: list[SimulatorProcess] = []
    if sim:
        workdir = tempfile.mkdtemp(prefix=f"crtk-bridge-{profile.name}-sim-")
        try:
            if profile.backends is None:
                device, wiring = _sim_wiring(profile.backend_type, source)
                simulator = SimulatorProcess(str(profile_path), device, workdir, host_ports=wiring.host_ports,
                                             raise_priority=realtime)
                simulators.append(simulator)
                profile = backend_class(profile.backend_type, source).sim_profile(profile, simulator.link)
                print(f"crtk-bridge: simulated {profile.backend_type} bus on {simulator.link} "
                      f"(simulator control socket {simulator.control})", flush=True)
            else:
                profile = _simulate_buses(profile, str(profile_path), workdir, simulators, realtime)
        except BaseException:  # a simulator that did not start: the others stopped, the work folder gone
            for simulator in simulators:
                simulator.stop()
            _remove_dir(workdir)
            raise

    layout = Layout(len(profile.joints), len(profile.namespaces))
    snap = SnapshotBuffer(layout, create=True)
    # every cycle's sample for recordings and the black box (core/samples.py); the ring covers
    # RING_SECONDS at the profile's rate (a backend pacing the loop runs at its own, slower or not)
    samples = SampleRing(layout, ring_slots(max(profile.loop.rate_hz, 1.0)), create=True)
    zsession = None
    front, back = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    ctx = multiprocessing.get_context("fork")  # forked before any thread or event loop exists
    proc = ctx.Process(target=_control_process, args=(profile, source, back, front, snap, realtime, samples),
                       name=f"crtk-bridge-{profile.name}-control")
    try:
        proc.start()
        back.close()
        server: Server | None = None
        holder: dict = {}

        def on_event(msg: dict) -> None:
            if "server" in holder:
                holder["server"].on_event(msg)
            else:
                early.append(msg)

        early: list[dict] = []
        link = ControlLink(profile, front, snap, on_event)
        try:
            ready = link.wait_ready(STARTUP_TIMEOUT_S)
        except RuntimeError as exc:
            proc.join(SHUTDOWN_TIMEOUT_S)
            if proc.is_alive():
                proc.kill()
            raise CrtkBridgeError(str(exc)) from None
        server = Server(link, ready["commands"], socket_path)
        # imported after the fork: the control process never loads the recorder (rosbags, zenoh)
        from .recording.recorder import Recorder

        server.recorder = Recorder(server, samples, source, record_dir, live)
        holder["server"] = server
        for msg in early:
            server.on_event(msg)
        if zconfig is not None:
            # after the fork (a Zenoh session does not survive it); the robot is still DISABLED,
            # so an unreachable router just ends start-up (the finally below stops the loop)
            bound: list[str] = []
            zsession = open_session(zconfig, profile.name, bound=bound)
            zconfig = msgspec.structs.replace(zconfig, listen=bound)  # port 0: the one bound (banner)
        return asyncio.run(_serve(server, link, proc, (zsession, zconfig) if zsession is not None else None))
    finally:
        if zsession is not None:
            zsession.close()
        if proc.is_alive():
            proc.terminate()
            proc.join(SHUTDOWN_TIMEOUT_S)
        front.close()
        snap.close(unlink=True)
        samples.close(unlink=True)
        for simulator in simulators:
            simulator.stop()
        _remove_dir(workdir)
