"""The Zenoh lease's bounds: :mod:`crtk_client.zenoh_lease`. This name is that same module."""

import sys

import crtk_client.zenoh_lease as _module

sys.modules[__name__] = _module
