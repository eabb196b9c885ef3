"""ifm O3R over XML-RPC + PCIC/TCP: backend class :class:`O3RCamera`, entry point ``cameras: o3r``."""

from cellcal.drivers.o3r.camera import O3RCamera, O3RConfig

__all__ = ["O3RCamera", "O3RConfig"]
