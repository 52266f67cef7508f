"""The vendor SDKs' own PortHandlers, patient with a simulator that runs in the test's process.

A simulator thread in this process may not run, on a loaded host, for longer than the SDKs'
~34 ms packet timeout: a real-time budget, not what a simulator test checks. So a request that
must be answered waits up to REPLY_PATIENCE_MS for its reply (it returns as soon as the reply is
there: only a failure waits it out), and where silence is the expected answer
(:func:`silence_expected`) the SDK's own timeout runs, then the test waits until the simulator
has handled every byte sent (``handled_bytes``), so what it did with them -- or that it did not
reply -- is settled before the test looks.
"""

from __future__ import annotations

import contextlib

from .conftest import wait_until

REPLY_PATIENCE_MS = 5000.0


def patient_port(sdk_port_class: type) -> type:
    """A subclass of an SDK's ``PortHandler`` (scservo_sdk or dynamixel_sdk): REPLY_PATIENCE_MS
    more for a reply unless ``patient`` is off; ``sent`` counts the bytes written."""

    class PatientPort(sdk_port_class):
        def __init__(self, port_name: str):
            super().__init__(port_name)
            self.patient = True
            self.sent = 0

        def setPacketTimeout(self, packet_length):  # noqa: N802 (SDK name)
            super().setPacketTimeout(packet_length)
            if self.patient:
                self.packet_timeout += REPLY_PATIENCE_MS

        def writePort(self, packet):  # noqa: N802
            n = super().writePort(packet)
            self.sent += n
            return n

    PatientPort.__name__ = PatientPort.__qualname__ = f"Patient{sdk_port_class.__name__}"
    return PatientPort


def caught_up(sim, sent: int) -> None:
    """Wait until the bus simulator has handled ``sent`` bytes (all that its sole client sent):
    any reply is out, any write applied or ignored."""
    wait_until(lambda: sim.handled_bytes >= sent, 10.0, interval=0.001,
               what=f"the simulator handling {sent} bytes")


@contextlib.contextmanager
def silence_expected(sim, port):
    """Requests that get no reply (on a :func:`patient_port`, the simulator's sole client): the
    SDK's own packet timeout, then the simulator caught up and late replies dropped."""
    port.patient = False
    try:
        yield
    finally:
        port.patient = True
    caught_up(sim, port.sent)
    port.ser.reset_input_buffer()  # replies the SDK gave up waiting for (all out by now)
