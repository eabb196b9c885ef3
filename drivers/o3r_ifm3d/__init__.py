"""ifm O3R through ifm's ifm3dpy: backend class :class:`O3RIfm3dCamera`, entry point ``cameras: o3r-ifm3d``."""

from cellcal.drivers.o3r_ifm3d.camera import O3RIfm3dCamera, O3RIfm3dConfig

__all__ = ["O3RIfm3dCamera", "O3RIfm3dConfig"]
