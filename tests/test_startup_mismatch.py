"""Start-up mismatch refusal: the daemon reads each servo's EEPROM when it opens the bus (model,
Homing_Offset, position limits, direction bits) and refuses ENABLE, naming robot, joint, register
and what to do, when they would make positions wrong; it never rewrites the EEPROM. The real daemon
in its own process, on the Feetech and Dynamixel simulators (a servo's EEPROM set by hand, as a
servo configured elsewhere, e.g. by LeRobot's calibration)."""

from __future__ import annotations

import contextlib

import pytest
import yaml

from crtk_bridge.client import connect
from crtk_bridge.errors import CommandError
from crtk_bridge.profile import parse_profile
from crtk_bridge.sim.dynamixel import DynamixelSimulator
from crtk_bridge.sim.feetech import FeetechSimulator

from .conftest import KOCH, DaemonProcess, profile_data, so101_data


def run_daemon(tmp, data: dict, tag: str) -> DaemonProcess:
    path = tmp / f"{tag}.yaml"
    path.write_text(yaml.safe_dump(data))
    return DaemonProcess(["--profile", str(path), "--no-realtime"], tmp / f"{tag}.sock", tmp / f"{tag}.log")


def enable_error(daemon: DaemonProcess, namespace: str) -> str | None:
    """The error of an enable (None when the robot got ENABLED)."""
    robot = connect(socket=str(daemon.socket_path))
    try:
        arm = robot.device(namespace)
        try:
            assert arm.enable(5.0)
        except CommandError as exc:
            return str(exc)
        return None
    finally:
        robot.close()


def test_feetech_homing_offset_and_limits_refuse_enable_until_the_profile_says_so(short_tmp):
    data = so101_data()
    with FeetechSimulator.from_profile(parse_profile(data)) as sim:
        sim.servo(3).write("Homing_Offset", 120)  # elbow_flex: calibrated elsewhere with an offset
        sim.servo(1).write("Max_Position_Limit", 3000)  # shoulder_pan: cuts into range [700, 3400]
        data["backend"]["port"] = sim.port
        d = run_daemon(short_tmp, data, "mismatch")
        try:
            err = enable_error(d, "so101")
        finally:
            d.stop()
        assert err is not None and "so101: enable refused" in err
        assert ("joint 'elbow_flex' (id 3): Homing_Offset is 120, expected 0 "
                "(joints[2] (elbow_flex).calibration.homing_offset): every position it reports is shifted "
                "by 120 ticks") in err
        assert "set joints[2] (elbow_flex).calibration.homing_offset: 120 if the calibration was made with it" in err
        assert ("joint 'shoulder_pan' (id 1): Max_Position_Limit is 3000, expected >= 3400 "
                "(joints[0] (shoulder_pan).calibration.range)") in err
        assert "wrist_flex" not in err  # the servos that agree are not named
        assert sim.servo(3).read("Homing_Offset") == 120  # never rewritten
        assert sim.servo(1).read("Max_Position_Limit") == 3000
        assert all(sim.servo(i).read("Torque_Enable") == 0 for i in sim.ids)

        # the profile now says what the servos hold: the same bus enables
        data["joints"][2]["calibration"]["homing_offset"] = 120
        data["joints"][0]["calibration"]["range"] = [700, 3000]
        d = run_daemon(short_tmp, data, "agreed")
        try:
            assert enable_error(d, "so101") is None
            assert sim.servo(3).read("Torque_Enable") == 1
        finally:
            d.stop()


def test_dynamixel_homing_offset_and_reverse_drive_mode_refuse_enable(short_tmp):
    data = profile_data(KOCH)
    servos = {j["id"]: j["model"] for j in data["joints"]}
    first, last = data["joints"][0], data["joints"][-1]
    with DynamixelSimulator(servos) as sim:
        sim.servo(first["id"]).write("Homing_Offset", -300)
        sim.servo(last["id"]).write("Drive_Mode", 1)
        data["backend"]["port"] = sim.port
        d = run_daemon(short_tmp, data, "koch")
        try:
            err = enable_error(d, data["namespaces"][0]["name"])
        finally:
            d.stop()
        assert err is not None and f"{data['name']}: enable refused" in err
        assert (f"joint {first['name']!r} (id {first['id']}): Homing_Offset is -300, expected 0 "
                f"(joints[0] ({first['name']}).calibration.homing_offset)") in err
        n = len(data["joints"]) - 1
        assert (f"joint {last['name']!r} (id {last['id']}): Drive_Mode is 1, expected bit 0 clear (0) "
                f"(joints[{n}] ({last['name']}).calibration.direction): bit 0 (reverse) flips every "
                f"position") in err
        assert sim.servo(first["id"]).read("Homing_Offset") == -300
        assert sim.servo(last["id"]).read("Drive_Mode") == 1
        assert all(sim.servo(i).read("Torque_Enable") == 0 for i in sim.ids)


def test_homing_offset_key_is_checked_against_each_vendor_register_range():
    from crtk_bridge.backends import create_backend
    from crtk_bridge.errors import ProfileError

    data = so101_data()
    data["joints"][1]["calibration"]["homing_offset"] = 2048  # sign-magnitude, bit 11: at most 2047
    with pytest.raises(ProfileError, match=r"joints\[1\] \(shoulder_lift\)\.calibration\.homing_offset: 2048 is "
                                           r"outside -2047\.\.2047"):
        create_backend(parse_profile(data))
    koch = profile_data(KOCH)  # extended position modes: the range check still applies
    koch["joints"][0].setdefault("calibration", {})["homing_offset"] = -1_044_480
    with pytest.raises(ProfileError, match=r"homing_offset: -1044480 is outside -1044479\.\.1044479"):
        create_backend(parse_profile(koch))
    koch["joints"][0]["calibration"]["homing_offset"] = -1_044_479
    create_backend(parse_profile(koch))


@contextlib.contextmanager
def open_so101():
    """(simulator, open FeetechBackend) of profiles/so101.yaml, in this process."""
    from crtk_bridge.backends.feetech.backend import FeetechBackend

    data = so101_data()
    with FeetechSimulator.from_profile(parse_profile(data)) as sim:
        data["backend"]["port"] = sim.port
        backend = FeetechBackend(parse_profile(data))
        backend.open()
        try:
            yield sim, backend
        finally:
            backend.close()


def test_a_reopened_bus_is_checked_again():
    """After a USB replug the bus is opened again by the backend's worker: the EEPROM is read
    again (someone may have recalibrated the servos elsewhere meanwhile)."""
    with open_so101() as (sim, backend):
        assert backend._enable_refusal is None
        sim.servo(4).write("Homing_Offset", -7)
        backend._port.closePort()  # the adapter went away
        backend._reopen_once()
        assert "joint 'wrist_flex' (id 4): Homing_Offset is -7, expected 0" in backend._enable_refusal


def test_a_late_reply_of_another_length_is_never_decoded_as_the_eeprom():
    """The SDKs take any status of the right id as the reply: a late 1-byte status (value 0, from a
    read that timed out before) taken for a 2-byte Homing_Offset read decodes as -512. The EEPROM is
    read in one block whose reply must have the block's length; a shorter one is read again."""
    with open_so101() as (sim, backend):
        real = backend._ph.readTxRx
        calls = []

        def late_status_first(port, sid, address, length):
            calls.append(length)
            if len(calls) == 1:
                return [0x00, 0xFA], 0, 0  # a 1-byte status's value and checksum
            return real(port, sid, address, length)

        backend._ph.readTxRx = late_status_first
        assert backend.eeprom_diffs(1) == []
        assert len(calls) == 2 and calls[0] == calls[1] == 27  # Return_Delay_Time (7) .. Operating_Mode (33)
