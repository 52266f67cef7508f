"""Loopback addresses for simulators with fixed TCP ports (a UR controller's 29999/30003/30004).

The whole 127.0.0.0/8 block reaches the loopback interface on Linux, so simulators, tests and
daemons that need the same ports run side by side, each on its own 127.0.0.N.
"""

from __future__ import annotations

import random
import socket
from collections.abc import Iterable

from . import SimulatorError


def ports_free(host: str, ports: Iterable[int]) -> bool:
    """True if every TCP port of ``ports`` can be bound on ``host`` right now."""
    for port in ports:
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                probe.bind((host, port))
            except OSError:
                return False
    return True


def free_loopback_host(ports: Iterable[int]) -> str:
    """A 127.0.0.N (N in 2..254) where every port of ``ports`` is free, tried in random order so
    concurrent callers rarely race for the same one (the caller binds it next; a loser retries).
    Raises SimulatorError naming the ports when none is free."""
    ports = tuple(ports)
    candidates = list(range(2, 255))
    random.shuffle(candidates)
    for n in candidates:
        host = f"127.0.0.{n}"
        if ports_free(host, ports):
            return host
    raise SimulatorError(f"no loopback address 127.0.0.2-254 has TCP ports {', '.join(map(str, ports))} free")
