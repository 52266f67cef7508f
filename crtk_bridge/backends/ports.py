"""Which serial port is which adapter: ``crtk-bridge find-port`` and ``backend.port`` by USB serial.

A USB adapter's ``/dev/ttyACM<n>`` number follows plug order, so two arms can swap. Two stable
names exist: the udev link in ``/dev/serial/by-id`` (a plain path, usable as ``backend.port``
as is) and the adapter's USB serial number (``backend.port: {serial_number: ...}``), resolved
to the device when the bus opens. The port list comes from pyserial's
``serial.tools.list_ports`` (device, USB vendor / product ids, serial number, strings); this
module adds the by-id links pointing at each device. Lifecycle and command-line only.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Callable, Iterable, TextIO

from ..errors import BackendError
from .port_errors import BY_ID


@dataclass(frozen=True)
class SerialPort:
    """One serial port as pyserial lists it, with its ``/dev/serial/by-id`` links."""

    device: str
    by_id: tuple[str, ...] = ()
    vid: int | None = None
    pid: int | None = None
    serial_number: str | None = None
    manufacturer: str | None = None
    product: str | None = None
    description: str | None = None

    def describe(self) -> str:
        """One line: device, by-id links, vendor:product, serial number, strings."""
        parts = [self.device]
        parts += [f"{BY_ID}/{name}" for name in self.by_id]
        if self.vid is not None:
            parts.append(f"usb {self.vid:04x}:{self.pid or 0:04x}")
        parts.append(f"serial_number {self.serial_number!r}" if self.serial_number else "no serial number")
        text = " ".join(s for s in (self.manufacturer, self.product) if s) or (
            self.description if self.description and self.description != "n/a" else "")
        if text:
            parts.append(f"({text})")
        return "  ".join(parts)


def _by_id_links(by_id_dir: str) -> dict[str, list[str]]:
    """Real device path -> names of the links in ``by_id_dir`` pointing at it."""
    links: dict[str, list[str]] = {}
    try:
        names = sorted(os.listdir(by_id_dir))
    except OSError:
        return links
    for name in names:
        links.setdefault(os.path.realpath(os.path.join(by_id_dir, name)), []).append(name)
    return links


def list_serial_ports(comports: Callable[[], Iterable] | None = None, by_id_dir: str = BY_ID) -> list[SerialPort]:
    """Every serial port pyserial finds (``comports()``), USB ones first, with their by-id links."""
    if comports is None:
        from serial.tools.list_ports import comports
    links = _by_id_links(by_id_dir)
    ports = [SerialPort(device=p.device, by_id=tuple(links.get(os.path.realpath(p.device), ())),
                        vid=p.vid, pid=p.pid, serial_number=p.serial_number,
                        manufacturer=p.manufacturer, product=p.product, description=p.description)
             for p in comports()]
    return sorted(ports, key=lambda p: (p.vid is None, p.device))


def _plugged(ports: list[SerialPort]) -> str:
    usb = [p for p in ports if p.vid is not None]
    if not usb:
        return "no USB serial adapter is plugged in"
    return "plugged in: " + "; ".join(p.describe() for p in usb)


def resolve_port(port, robot: str, source: str,
                 lister: Callable[[], list[SerialPort]] | None = None) -> str:
    """The device path of ``backend.port``: a path as is; ``{serial_number: S}`` the one adapter
    with USB serial number S. Raises BackendError naming the profile key and listing what is
    plugged in when none (or more than one) matches, so two arms never swap silently."""
    if isinstance(port, str):
        return port
    wanted = port.serial_number
    ports = (lister or list_serial_ports)()
    found = [p for p in ports if p.serial_number == wanted]
    if len(found) == 1:
        return found[0].device
    what = ("no USB serial adapter has" if not found
            else f"{len(found)} adapters ({', '.join(p.device for p in found)}) have")
    raise BackendError(f"{robot}: {source}: backend.port.serial_number: {what} serial number "
                       f"{wanted!r}; {_plugged(ports)} (crtk-bridge find-port lists them)")


def find_replugged(lister: Callable[[], list[SerialPort]], ask: Callable[[str], object],
                   out: TextIO) -> SerialPort | None:
    """``find-port --replug``: list, ask the user to unplug the adapter, list again, ask to plug
    it back, list again; print and return the port that went away and came back (its new
    listing, whose device number may differ), or None, saying why."""
    before = {p.device: p for p in lister()}
    ask("Unplug the arm's USB adapter, then press Enter. ")
    after = {p.device: p for p in lister()}
    gone = [before[d] for d in before if d not in after]
    if not gone:
        print("No port went away: was the adapter plugged in before? Ports now: "
              + (", ".join(sorted(after)) or "none"), file=out)
        return None
    if len(gone) > 1:
        print("More than one port went away (" + ", ".join(p.device for p in gone)
              + "): unplug one adapter only, then run this again.", file=out)
        return None
    ask("Plug it back in, then press Enter. ")
    again = lister()
    back = [p for p in again if p.device not in after]
    if len(back) != 1:
        print(f"The adapter at {gone[0].device} went away but "
              + ("did not come back" if not back else "more than one port appeared: "
                 + ", ".join(p.device for p in back)) + ".", file=out)
        return None
    port = back[0]
    print(f"The arm's adapter is {port.device}" + (f" (was {gone[0].device})" if port.device != gone[0].device else ""),
          file=out)
    print("  " + port.describe(), file=out)
    stable = [f"port: {BY_ID}/{port.by_id[0]}"] if port.by_id else []
    if port.serial_number:
        stable.append(f"port: {{serial_number: {port.serial_number!r}}}")
    if stable:
        print("In the profile's backend section, name it by a stable name: " + "  or  ".join(stable), file=out)
    else:
        print(f"It has no stable name (no by-id link, no USB serial number): use port: {port.device}", file=out)
    return port
