"""A late status packet is never taken for the answer to the next read (serial_servo._read_register).

The SDKs match a status to its request by servo id only. A reply to an earlier request that timed
out can arrive after the input flush that precedes the next request, and was decoded as that
request's data. The simulators' ``late_reply`` fault sends a servo's previous status again just
ahead of its next one, as such a reply arrives; the backend must refuse it by its length and read
again. In process, on the Feetech and Dynamixel simulators."""

from __future__ import annotations

import pytest

from crtk_bridge.backends import create_backend
from crtk_bridge.profile import parse_profile
from crtk_bridge.sim.dynamixel import DynamixelSimulator
from crtk_bridge.sim.feetech import FeetechSimulator

from .conftest import KOCH, profile_data, so101_data


@pytest.mark.parametrize("vendor", ["feetech", "dynamixel"])
def test_a_late_reply_is_never_taken_for_the_next_reads_answer(vendor):
    sim_class, data = ((FeetechSimulator, so101_data()) if vendor == "feetech"
                       else (DynamixelSimulator, profile_data(KOCH)))
    with sim_class.from_profile(parse_profile(data)) as sim:
        data["backend"]["port"] = sim.port
        backend = create_backend(parse_profile(data))
        backend.open()
        try:
            sid = backend._ids[0]
            limit = sim.servo(sid).read("Max_Position_Limit")  # 2 bytes (STS) / 4 bytes (X series)
            assert limit & 0xFF not in (0, 1)  # its first byte cannot pass for a Torque_Enable value
            assert backend._read_register(0, "Max_Position_Limit") == limit
            sim.set_fault(sid, "late_reply")  # that status comes again, just ahead of the next one
            assert backend._read_register(0, "Torque_Enable") == 0
            assert sim.servo(sid).late_reply is False  # the late status did go out
            assert backend._read_register(0, "Max_Position_Limit") == limit  # and nothing is left behind
        finally:
            backend.close()
