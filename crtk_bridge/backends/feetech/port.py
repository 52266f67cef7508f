"""A ``scservo_sdk.PortHandler`` with the serial-port fixes shared by every serial-servo backend.

The fixes themselves (stale input discarded before each request, reads that sleep in ``select``
instead of busy-polling, packet timeout = wire time + ``margin_ms``, monotonic deadlines,
exclusive open, OS errors as SDK results) live in
:class:`crtk_bridge.backends.serial_servo.SerialPortFixes`; see its docstring for why.
"""

from __future__ import annotations

from scservo_sdk import PortHandler

from ..serial_servo import DEFAULT_MARGIN_MS, SerialPortFixes

__all__ = ["DEFAULT_MARGIN_MS", "FastPortHandler"]


class FastPortHandler(SerialPortFixes, PortHandler):
    """scservo_sdk PortHandler with input flushing, sleeping reads and short packet timeouts.

    ``margin_ms``: time allowed beyond the wire time of the expected reply bytes (USB latency,
    servo return delay, scheduling). Milliseconds, as everywhere in the SDK's port API.
    Not thread-safe.
    """
