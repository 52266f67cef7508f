"""The object dictionary of a drive without an EDS file: the standard CiA 301 / CiA 402 objects
this backend uses, and nothing else (a real drive's EDS, ``eds:`` in the profile, replaces it).

canopen needs an object dictionary to encode SDO values and to place PDO variables; the objects
and their types are the standards' (CiA 301 7.5 "Object dictionary", CiA 402-2 section 6..8).
"""

from __future__ import annotations

from canopen import objectdictionary as od
from canopen.objectdictionary import ODArray, ODRecord, ODVariable

from . import tables as t

_RO, _RW = "ro", "rw"


def _var(name: str, index: int, data_type: int, access: str = _RW, sub: int = 0, default: int = 0) -> ODVariable:
    v = ODVariable(name, index, sub)
    v.data_type = data_type
    v.access_type = access
    v.default = default
    return v


def _pdo_comm(name: str, index: int) -> ODRecord:
    """PDO communication parameter record (CiA 301 7.5.2.35 / 7.5.2.37)."""
    rec = ODRecord(name, index)
    rec.add_member(_var("Highest sub-index supported", index, od.UNSIGNED8, _RO, 0, 5))
    rec.add_member(_var("COB-ID", index, od.UNSIGNED32, _RW, 1))
    rec.add_member(_var("Transmission type", index, od.UNSIGNED8, _RW, 2))
    rec.add_member(_var("Inhibit time", index, od.UNSIGNED16, _RW, 3))
    rec.add_member(_var("Event timer", index, od.UNSIGNED16, _RW, 5))
    return rec


def _pdo_map(name: str, index: int) -> ODRecord:
    """PDO mapping parameter record: sub 0 = number of entries, 1..8 = index<<16 | sub<<8 | bits."""
    rec = ODRecord(name, index)
    rec.add_member(_var("Number of mapped objects", index, od.UNSIGNED8, _RW, 0))
    for sub in range(1, 9):
        rec.add_member(_var(f"Mapped object {sub}", index, od.UNSIGNED32, _RW, sub))
    return rec


def standard_402() -> od.ObjectDictionary:
    """A fresh object dictionary of the standard objects (one per node: canopen binds it)."""
    d = od.ObjectDictionary()
    for args in (
        ("Device type", t.DEVICE_TYPE, od.UNSIGNED32, _RO),
        ("Error register", t.ERROR_REGISTER, od.UNSIGNED8, _RO),
        ("Producer heartbeat time", t.HEARTBEAT_PRODUCER, od.UNSIGNED16),
        ("Error code", t.ERROR_CODE, od.UNSIGNED16, _RO),
        ("Controlword", t.CONTROLWORD, od.UNSIGNED16),
        ("Statusword", t.STATUSWORD, od.UNSIGNED16, _RO),
        ("Modes of operation", t.MODES_OF_OPERATION, od.INTEGER8),
        ("Modes of operation display", t.MODES_DISPLAY, od.INTEGER8, _RO),
        ("Position actual value", t.POSITION_ACTUAL, od.INTEGER32, _RO),
        ("Velocity actual value", t.VELOCITY_ACTUAL, od.INTEGER32, _RO),
        ("Following error window", t.FOLLOWING_ERROR_WINDOW, od.UNSIGNED32),
        ("Abort connection option code", t.ABORT_CONNECTION_OPTION, od.INTEGER16),
        ("Target torque", t.TARGET_TORQUE, od.INTEGER16),
        ("Motor rated torque", t.RATED_TORQUE, od.UNSIGNED32),
        ("Torque actual value", t.TORQUE_ACTUAL, od.INTEGER16, _RO),
        ("Target position", t.TARGET_POSITION, od.INTEGER32),
        ("Home offset", t.HOME_OFFSET, od.INTEGER32),
        ("Homing method", t.HOMING_METHOD, od.INTEGER8),
        ("Homing acceleration", t.HOMING_ACCELERATION, od.UNSIGNED32),
        ("Target velocity", t.TARGET_VELOCITY, od.INTEGER32),
        ("Supported drive modes", t.SUPPORTED_MODES, od.UNSIGNED32, _RO),
    ):
        d.add_object(_var(*args))
    identity = ODRecord("Identity object", t.IDENTITY)
    identity.add_member(_var("Number of entries", t.IDENTITY, od.UNSIGNED8, _RO, 0, 4))
    for sub, name in enumerate(("Vendor-ID", "Product code", "Revision number", "Serial number"), 1):
        identity.add_member(_var(name, t.IDENTITY, od.UNSIGNED32, _RO, sub))
    d.add_object(identity)
    consumer = ODRecord("Consumer heartbeat time", t.HEARTBEAT_CONSUMER)
    consumer.add_member(_var("Highest sub-index supported", t.HEARTBEAT_CONSUMER, od.UNSIGNED8, _RO, 0, 1))
    consumer.add_member(_var("Consumer heartbeat time 1", t.HEARTBEAT_CONSUMER, od.UNSIGNED32, _RW, 1))
    d.add_object(consumer)
    speeds = ODArray("Homing speeds", t.HOMING_SPEEDS)
    speeds.add_member(_var("Number of entries", t.HOMING_SPEEDS, od.UNSIGNED8, _RO, 0, 2))
    speeds.add_member(_var("Speed during search for switch", t.HOMING_SPEEDS, od.UNSIGNED32, _RW, 1))
    speeds.add_member(_var("Speed during search for zero", t.HOMING_SPEEDS, od.UNSIGNED32, _RW, 2))
    d.add_object(speeds)
    for n in range(4):
        d.add_object(_pdo_comm(f"Receive PDO {n + 1} communication parameter", 0x1400 + n))
        d.add_object(_pdo_map(f"Receive PDO {n + 1} mapping parameter", 0x1600 + n))
        d.add_object(_pdo_comm(f"Transmit PDO {n + 1} communication parameter", 0x1800 + n))
        d.add_object(_pdo_map(f"Transmit PDO {n + 1} mapping parameter", 0x1A00 + n))
    return d
