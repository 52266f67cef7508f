"""``crtk_bridge.client.pacing`` is :mod:`crtk_client.pacing` (the client distribution, clients/python):
the same module object, so names, patches and ``isinstance`` agree whichever name is imported."""

import sys

import crtk_client.pacing as _module

sys.modules[__name__] = _module
