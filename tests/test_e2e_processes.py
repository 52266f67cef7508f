"""The two-process design's failure paths: either process dying leaves the robot safe."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest
import yaml

from crtk_bridge.client import connect
from crtk_bridge.sim.control import control_request

from .conftest import SO101, DaemonProcess, so101_data, wait_until

pytestmark = pytest.mark.requires()  # every simulated robot (each test kills a process: a daemon of its own)


def _control_pid(daemon_pid: int) -> int:
    """The forked control process: the child running the daemon's own command line (the others
    are the simulator and multiprocessing's resource tracker)."""
    with open(f"/proc/{daemon_pid}/task/{daemon_pid}/children") as f:
        children = [int(x) for x in f.read().split()]
    for pid in children:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            if b"crtk_bridge.cli" in f.read():
                return pid
    raise AssertionError(f"no control process among {children}")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    with open(f"/proc/{pid}/stat") as f:
        return f.read().split()[2] != "Z"


def test_front_process_killed_mid_motion_control_process_stops_safely(short_tmp):
    link, control = short_tmp / "tty", short_tmp / "sim.sock"
    sim = subprocess.Popen([sys.executable, "-m", "crtk_bridge.sim.cli", "feetech", "--profile", str(SO101),
                            "--link", str(link), "--control", str(control)],
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        wait_until(lambda: link.exists() and control.exists(), 15, what="simulator link")
        data = so101_data()
        data["backend"]["port"] = str(link)
        profile = short_tmp / "p.yaml"
        profile.write_text(yaml.safe_dump(data))
        daemon = DaemonProcess(["--profile", str(profile)], short_tmp / "d.sock", short_tmp / "d.log")
        try:
            ctl_pid = _control_pid(daemon.proc.pid)
            robot = connect(socket=str(daemon.socket_path))
            arm = robot.device("so101")
            assert arm.enable(5.0)
            arm.move_jp([1.2, -1.0, 1.0, 0.5, 1.5])
            wait_until(lambda: control_request(str(control), {"cmd": "dump"})["servos"]["1"]["present_velocity"] != 0,
                       5, what="arm moving")
            daemon.proc.send_signal(signal.SIGKILL)  # the front process dies without a word
            daemon.proc.wait(5)
            robot.close()
            wait_until(lambda: not _alive(ctl_pid), 5, what="control process exit after losing the front")
            servos = control_request(str(control), {"cmd": "dump"})["servos"]
            assert all(s["torque_enable"] == 0 for s in servos.values()), servos
        finally:
            daemon.stop()
    finally:
        sim.terminate()
        sim.wait(10)


def test_control_process_killed_front_reports_fault_and_exits_nonzero(sim_daemon):
    robot = connect(socket=str(sim_daemon.socket_path))
    try:
        ctl_pid = _control_pid(sim_daemon.proc.pid)
        mark = robot.connection.event_count
        before = time.time()
        os.kill(ctl_pid, signal.SIGKILL)
        wait_until(lambda: any(e.data.get("code") == "control_process_died"
                               for e in robot.connection.events_since(mark)), 5, what="control_process_died event")
        st = robot.connection.operating_state or {}
        assert st.get("state") == "FAULT"
        # stamped as every event is (s since the epoch), not 0: `crtk-ctl events` printed '-' (issue 18)
        died = next(e for e in robot.connection.events_since(mark) if e.data.get("code") == "control_process_died")
        assert before - 1 <= died.data["stamp"] <= time.time() + 1
        assert before - 1 <= st["stamp"] <= time.time() + 1
    finally:
        robot.close()
    assert sim_daemon.proc.wait(10) == 1


def test_client_loss_notice_reaches_others_as_one_warning_only(sim_daemon):
    import json
    import socket as _socket
    import threading

    lines: list[dict] = []
    watcher = _socket.socket(_socket.AF_UNIX, _socket.SOCK_STREAM)
    watcher.connect(str(sim_daemon.socket_path))

    def read():
        for line in watcher.makefile("rb"):
            lines.append(json.loads(line))

    threading.Thread(target=read, daemon=True).start()
    robot = connect(socket=str(sim_daemon.socket_path))
    arm = robot.device(robot.namespaces[0])
    assert arm.enable(5.0)
    arm.servo_jp(arm.measured_jp()[0])
    robot.close()  # the controlling session goes away mid-stream
    wait_until(lambda: any(m.get("data", {}).get("code") == "control_released" for m in lines), 5,
               what="control_released warning")
    assert not [m for m in lines if "ok" in m], "a reply nobody asked for reached another session"
    watcher.close()


def test_simulator_does_not_outlive_a_killed_daemon(sim_daemon):
    """SIGKILL to the daemon: its simulator stops, and the --sim work folder (its link and control
    socket) goes with it: the daemon had no chance to remove it (folders piled up in /tmp)."""
    sim_pid = workdir = None
    with open(f"/proc/{sim_daemon.proc.pid}/task/{sim_daemon.proc.pid}/children") as f:
        for pid in map(int, f.read().split()):
            with open(f"/proc/{pid}/cmdline", "rb") as c:
                argv = c.read().split(b"\0")
                if b"crtk_bridge.sim.cli" in argv:
                    sim_pid = pid
                    workdir = os.path.dirname(argv[argv.index(b"--control") + 1].decode())
    assert sim_pid is not None and os.path.basename(workdir).startswith("crtk-bridge-"), workdir
    assert os.path.isdir(workdir)
    sim_daemon.proc.send_signal(signal.SIGKILL)
    sim_daemon.proc.wait(5)
    wait_until(lambda: not _alive(sim_pid), 5, what="simulator exit after the daemon was killed")
    assert not os.path.exists(workdir), os.listdir(workdir)
