"""The protocol's words: :mod:`crtk_client.vocabulary` (the client distribution holds it). This
name is that same module."""

import sys

import crtk_client.vocabulary as _module

sys.modules[__name__] = _module
