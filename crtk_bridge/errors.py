"""The project's error tree: :mod:`crtk_client.errors` (the client distribution holds it, so that a
client installed alone raises the same classes). This name is that same module."""

import sys

import crtk_client.errors as _module

sys.modules[__name__] = _module
