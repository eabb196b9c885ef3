"""Luxonis OAK over depthai v3: backend class :class:`OakCamera`, entry point ``cameras: oak`` (extra ``oak``)."""

from cellcal.drivers.oak.camera import OakCamera, OakConfig

__all__ = ["OakCamera", "OakConfig"]
