"""``crtk_bridge.client.paths`` is :mod:`crtk_client.paths` (the client distribution, clients/python):
the same module object, so names, patches and ``isinstance`` agree whichever name is imported."""

import sys

import crtk_client.paths as _module

sys.modules[__name__] = _module
