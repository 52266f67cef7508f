"""``crtk_bridge.client.zenoh_link`` is :mod:`crtk_client.zenoh_link` (the client distribution, clients/python):
the same module object, so names, patches and ``isinstance`` agree whichever name is imported."""

import sys

import crtk_client.zenoh_link as _module

sys.modules[__name__] = _module
