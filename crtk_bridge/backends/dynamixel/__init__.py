"""Dynamixel X-series (Protocol 2.0) backend: see :mod:`.backend`; tables in :mod:`.tables`."""
