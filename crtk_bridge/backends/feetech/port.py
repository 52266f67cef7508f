"""A ``scservo_sdk.PortHandler`` with the serial-port fixes shared by every serial-servo backend.

The fixes themselves (stale input discarded before each request, reads that sleep in ``select``
instead of busy-polling, packet timeout = wire time + ``margin_ms``, monotonic deadlines,
exclusive open, OS errors as SDK results) live in
:class:`crtk_bridge.backends.serial_servo.SerialPortFixes`; see its docstring for why.
"""

from __future__ import annotations

from scservo_sdk import PortHandler
from scservo_sdk.protocol_packet_handler import protocol_packet_handler
from scservo_sdk.scservo_def import SCS_SETEND

from ..serial_servo import DEFAULT_MARGIN_MS, LastStatus, SerialPortFixes

__all__ = ["DEFAULT_MARGIN_MS", "FastPortHandler", "StsPacketHandler"]


class StsPacketHandler(LastStatus, protocol_packet_handler):
    """scservo_sdk's packet handler, keeping the last status packet (:class:`LastStatus`).
    Constructing it sets the SDK's module-global byte order to little-endian (STS), as
    ``scservo_sdk.PacketHandler(0)`` does."""

    def __init__(self):
        SCS_SETEND(0)
        super().__init__()

    def status_params(self) -> int:
        s = self.last_status  # FF FF ID LEN ERR params.. CHK; LEN counts ERR, params, CHK
        return s[3] - 2 if len(s) > 3 else -1


class FastPortHandler(SerialPortFixes, PortHandler):
    """scservo_sdk PortHandler with input flushing, sleeping reads and short packet timeouts.

    ``margin_ms``: time allowed beyond the wire time of the expected reply bytes (USB latency,
    servo return delay, scheduling). Milliseconds, as everywhere in the SDK's port API.
    Not thread-safe.
    """
