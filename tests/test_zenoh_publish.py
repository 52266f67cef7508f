"""The ROS graph's publishing path in-process (transport/ros): who is subscribed, and the CDR the
graph puts on the wire. No daemon: Zenoh sessions on loopback endpoints, multicast off."""

from __future__ import annotations

import json

import pytest
import zenoh

from crtk_bridge.transport.ros import types as T
from crtk_bridge.transport.ros.rmw import Node
from tests.conftest import free_port, wait_until


def _session(listen: list[str] = (), connect: list[str] = ()) -> zenoh.Session:
    conf = zenoh.Config()
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    conf.insert_json5("timestamping/enabled", "true")  # the advanced publishers need it
    return zenoh.open(conf)


@pytest.fixture(scope="module")
def pair():
    """The graph's session (listening) and a peer joined to it (a ROS node's view)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    ours = _session(listen=[endpoint])
    theirs = _session(connect=[endpoint])
    yield ours, theirs
    theirs.close()
    ours.close()


def test_a_topic_is_wanted_only_while_somebody_subscribes(pair):
    """A periodic topic nobody subscribes to is not encoded: ``wanted`` is False until a matching
    subscriber appears (an unrelated one does not count) and False again once it leaves."""
    ours, theirs = pair
    node = Node(ours, 0, "wanted_test")
    try:
        pub = node.publisher("/so101/measured_js", T.JOINT_STATE)
        assert pub.wanted is False
        other = theirs.declare_subscriber("0/so101/setpoint_js/**", lambda s: None)
        sub = theirs.declare_subscriber("0/so101/measured_js/**", lambda s: None)
        wait_until(lambda: pub.wanted is True, 5, what="measured_js wanted once subscribed")
        sub.undeclare()
        wait_until(lambda: pub.wanted is False, 5, what="measured_js not wanted once unsubscribed")
        other.undeclare()
    finally:
        node.close()
