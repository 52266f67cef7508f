"""``crtk_bridge.client.connection`` is :mod:`crtk_client.connection` (the client distribution, clients/python):
the same module object, so names, patches and ``isinstance`` agree whichever name is imported."""

import sys

import crtk_client.connection as _module

sys.modules[__name__] = _module
