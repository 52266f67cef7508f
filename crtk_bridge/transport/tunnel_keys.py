"""The Zenoh tunnel's key expressions: :mod:`crtk_client.tunnel_keys` (shared by the daemon and the
client). This name is that same module."""

import sys

import crtk_client.tunnel_keys as _module

sys.modules[__name__] = _module
