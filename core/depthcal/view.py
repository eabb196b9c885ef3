"""One view of the measuring plane for ``cellcal depthcal``: a frame as captured and the flange pose it was taken at."""

from __future__ import annotations

from dataclasses import dataclass

from cellcal.devices.pose import Pose
from cellcal.devices.types import Frame

__all__ = ["DepthcalView"]


@dataclass(frozen=True)
class DepthcalView:
    """A frame of the plane and where the arm says the flange was.

    Attributes:
        frame: The frame as captured, uncorrected (camera optical frame, metres).
        flange_pose: ``T_base_flange`` the arm reported for it.
        name: A label for reports, e.g. ``"pose 3"``.
    """

    frame: Frame
    flange_pose: Pose
    name: str = ""
