"""``crtk_bridge.client.device`` is :mod:`crtk_client.device` (the client distribution, clients/python):
the same module object, so names, patches and ``isinstance`` agree whichever name is imported."""

import sys

import crtk_client.device as _module

sys.modules[__name__] = _module
