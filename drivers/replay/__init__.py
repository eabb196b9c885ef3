"""Playback of a ``cellcal record`` session: :class:`ReplayCamera` and :class:`ReplayArm`, entry points
``cameras: replay`` and ``arms: replay`` (extra ``record``)."""

from cellcal.drivers.replay.backends import ReplayArm, ReplayCamera

__all__ = ["ReplayArm", "ReplayCamera"]
