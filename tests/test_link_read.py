"""The front's reads of the snapshot (server/link.py, issue 23): a stream tick or a query copies
the state and counters only, never the statistics rings (eight times the state of a 6-joint arm,
copied in every tick of every stream before); period_statistics still reads the rings."""

from __future__ import annotations

import socket

import numpy as np
import pytest

from crtk_bridge.core.snapshot import RING, Layout, SnapshotBuffer
from crtk_bridge.server.link import ControlLink

from .test_controller import PROFILE


@pytest.fixture
def link():
    front, back = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    snap = SnapshotBuffer(Layout(len(PROFILE.joints), len(PROFILE.namespaces)), create=True)
    try:
        yield ControlLink(PROFILE, front, snap, lambda msg: None), snap
    finally:
        front.close()
        back.close()
        snap.close(unlink=True)


def test_a_joint_state_read_copies_the_state_not_the_statistics_rings(link):
    link, snap = link
    v = snap.views
    ns = PROFILE.namespaces[0]
    n = len(ns.joints)
    v["measured_stamp"][0] = 12.5
    v["measured_p"][:n] = np.arange(n) * 0.1
    v["lateness"][:] = 0.25
    v["compute"][:] = 0.5
    js = link.joint_state("measured_js", ns.name)
    assert js["stamp"] == 12.5 and js["position"] == pytest.approx((np.arange(n) * 0.1).tolist())
    s = snap.layout.slices
    # the rings were not copied into the front's buffer (it holds whatever it held: not the rings)
    assert not np.any(link._buf[s["lateness"]] == 0.25) and not np.any(link._buf[s["compute"]] == 0.5)


def test_period_statistics_reads_the_rings(link):
    link, snap = link
    v = snap.views
    link.joint_state("measured_js", PROFILE.namespaces[0].name)  # a state-only read first
    v["cycles"][0] = 2 * RING
    v["lateness"][:] = 0.001
    v["compute"][:] = 0.002
    stats = link.period_statistics()
    assert stats["samples"] == RING
    assert stats["lateness_p50_s"] == pytest.approx(0.001) and stats["compute_p99_s"] == pytest.approx(0.002)
