"""Transports of the front process beyond the Unix socket (docs/zenoh.md).

``zenoh_session``: the Zenoh session's configuration and opening (safe defaults, the TLS + access
control rule for anything beyond loopback). ``tunnel``: the socket protocol carried over Zenoh,
served by the same :class:`~crtk_bridge.server.server.Server` sessions. ``ros``: the ROS 2 graph
(rmw_zenoh's key layout, CDR). All of them run in the front process only, started by the daemon
once the control process exists (daemon.py, ``zenoh_services``).
"""
