"""Moved to the public :mod:`cellcal.devices.blocking`; re-exported here for the drivers."""

from cellcal.devices.blocking import BoundedCaller

__all__ = ["BoundedCaller"]
