"""The Zenoh link lease's bounds (``transport.zenoh.lease_ms``, ``crtk-ctl --zenoh-lease-ms``;
docs/zenoh.md, "Lease"), in a module that imports nothing heavy: crtk-ctl checks its option with
them without importing the profile's models (crtk_bridge.profile re-exports them).
"""

from __future__ import annotations

from typing import Any

#: Zenoh link lease (ms, ``transport.zenoh.lease_ms``; Zenoh's ``transport/link/tx/lease``): a
#: peer that sends nothing for the lease it announced (frozen, cable pulled) is dropped. Zenoh's
#: own default is 10 s; with 2 s a frozen remote client is lost within 2 s (docs/zenoh.md, "Lease").
ZENOH_LEASE_MS_DEFAULT = 2000
#: below this a healthy link on a loaded PC or Wi-Fi (a TCP retransmission alone waits 200 ms or
#: more) would expire: a spurious client loss
ZENOH_LEASE_MS_MIN = 500
#: rmw_zenoh's router uses 60 s, the longest lease Zenoh ships; beyond it client loss takes minutes
ZENOH_LEASE_MS_MAX = 60000
#: keep-alives per lease (Zenoh's ``transport/link/tx/keep_alive``): one every lease/4 on an idle
#: link, so three may be lost before the peer expires it (Zenoh's own ratio, set explicitly)
ZENOH_KEEP_ALIVE_PER_LEASE = 4


def zenoh_lease_problem(value: Any) -> str | None:
    """Why ``value`` is not a valid Zenoh lease in ms (an integer in [ZENOH_LEASE_MS_MIN,
    ZENOH_LEASE_MS_MAX]), or ``None``. The caller names the key or option."""
    if isinstance(value, bool) or not isinstance(value, int) \
            or not ZENOH_LEASE_MS_MIN <= value <= ZENOH_LEASE_MS_MAX:
        return f"must be an integer from {ZENOH_LEASE_MS_MIN} to {ZENOH_LEASE_MS_MAX} (ms), got {value!r}"
    return None
