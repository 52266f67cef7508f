"""servo_cv / interpolate_cv end to end: crtk-ctl streams a twist to the daemon on --sim and the
simulated SO-101's tip, measured with measured_cp, moves as far as the twist says (issue 8 item 7)."""

from __future__ import annotations

import numpy as np
import pytest

from crtk_bridge.client import connect
from crtk_bridge.client.cli import main as ctl_main

from .conftest import only_on, wait_until

START = [0.1, 0.2, 0.3, 0.0, 0.0]  # rad: an ordinary pose, far from singularities and limits
SETTLED = 0.0005  # m: the simulated servos' tracking lag has died out


def measured_tip(c):
    return np.array(c.request("measured_cp", "so101")["position"])


def settled_tip(c):
    """The tip once the servos have caught up with a held setpoint."""
    def close():
        sp = c.request("setpoint_cp", "so101")
        return sp["stamp"] > 0 and np.linalg.norm(measured_tip(c) - sp["position"]) < SETTLED
    wait_until(close, 10, what="the tip settled on its setpoint")
    return measured_tip(c)


@only_on("so101-feetech")  # the Koch profile has no kinematics section
@pytest.mark.parametrize("cmd,axis", [("servo_cv", 1), ("interpolate_cv", 2)])
def test_crtk_ctl_twist_stream_moves_the_tip_as_far_as_the_twist_says(sim_daemon, capsys, cmd, axis):
    sock = str(sim_daemon.socket_path)
    robot = connect(socket=sock)
    c = robot.connection
    try:
        assert robot.device("so101").enable(5.0)
        seq = c.request("move_jp", "so101", {"position": START})["busy_seq"]
        wait_until(lambda: c.idle_seq >= seq, 15, what="move_jp to the start pose")
        c.request("release")  # crtk-ctl takes control, as a user's second terminal would
        p0 = settled_tip(c)

        linear = ["0", "0", "0"]
        linear[axis] = "0.02"
        # 0.02 m/s for 1 s, streamed at crtk-ctl's 50 Hz; crtk-ctl's exit ends the stream (the
        # daemon holds when the controlling session disconnects)
        assert ctl_main(["--socket", sock, cmd, *linear, "0", "0", "0", "--duration", "1"]) == 0
        assert cmd in capsys.readouterr().out
        p1 = settled_tip(c)
        d = p1 - p0
        assert d[axis] == pytest.approx(0.020, abs=0.002), f"tip moved {d} m"
        off_axis = np.delete(d, axis)
        assert np.all(np.abs(off_axis) < 0.002), f"tip left its line: moved {d} m"
        assert c.request("operating_state")["state"] == "ENABLED"
    finally:
        robot.close()
