"""Playback of a ``cellcal record`` session: :class:`ReplayCamera` and :class:`ReplayArm`, entry points
``cameras: replay`` and ``arms: replay`` (extra ``record``)."""

from cellcal.drivers.replay.arm import ReplayArm
from cellcal.drivers.replay.camera import ReplayCamera

__all__ = ["ReplayArm", "ReplayCamera"]
