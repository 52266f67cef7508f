"""Vectors, poses and quaternions as crtk-bridge reads them: :mod:`crtk_client.vectors` (a leaf
the client distribution carries, so the client, the front and core share one reader). This name
is that same module."""

import sys

import crtk_client.vectors as _module

sys.modules[__name__] = _module
