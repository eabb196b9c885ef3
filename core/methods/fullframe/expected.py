"""Where the fit should look: the plane the user means (:class:`ExpectedPlane`) and a pixel region.

The calibration layer builds both from ``[reference]``, ``[mount]``, the arm pose and the
region of interest; the fit only takes them (ADR 0027, "The plane the user means").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cellcal.core.geometry.planes import Plane
from cellcal.devices.errors import CalibrationError

__all__ = ["DEFAULT_SEARCH_TOLERANCE_DEG", "DEFAULT_SEARCH_TOLERANCE_M", "ExpectedPlane", "check_region"]

#: How far the fitted normal may be from the expected one by default (``[reference] search_tolerance_deg``), deg.
DEFAULT_SEARCH_TOLERANCE_DEG = 15.0
#: How far the camera's distance to the two planes may differ by default (``[reference] search_tolerance_m``), m.
DEFAULT_SEARCH_TOLERANCE_M = 0.1


@dataclass(frozen=True)
class ExpectedPlane:
    """The plane the fit should find, in the camera frame, and how far the found one may be from it.

    Attributes:
        plane: Expected plane, camera frame (OpenCV), normal toward the camera, metres.
        angle_tolerance_rad: Largest angle between the expected and the fitted normal, rad.
        offset_tolerance_m: Largest difference of the camera's distance to the two planes, metres.
    """

    plane: Plane
    angle_tolerance_rad: float
    offset_tolerance_m: float

    def __post_init__(self) -> None:
        if not (0.0 < self.angle_tolerance_rad <= math.pi / 2):
            raise CalibrationError(f"ExpectedPlane.angle_tolerance_rad must be in (0, pi/2], got "
                                   f"{self.angle_tolerance_rad!r}")
        if not (self.offset_tolerance_m > 0.0 and math.isfinite(self.offset_tolerance_m)):
            raise CalibrationError(f"ExpectedPlane.offset_tolerance_m must be > 0, got {self.offset_tolerance_m!r}")

    def departure(self, plane: Plane) -> tuple[float, float]:
        """Angle (rad) between the normals and offset difference (m) of ``plane`` from the expected one."""
        n0, n1 = np.asarray(self.plane.normal, float), np.asarray(plane.normal, float)
        sign = 1.0 if float(n0 @ n1) >= 0 else -1.0            # either orientation of the found normal
        angle = math.atan2(float(np.linalg.norm(np.cross(n0, sign * n1))), abs(float(n0 @ n1)))
        return angle, abs(abs(plane.offset_m) - abs(self.plane.offset_m))

    def accepts(self, plane: Plane) -> bool:
        """Whether ``plane`` lies within both tolerances."""
        angle, offset = self.departure(plane)
        return angle <= self.angle_tolerance_rad and offset <= self.offset_tolerance_m


def check_region(region: NDArray[np.bool_] | None, shape: tuple[int, int]) -> NDArray[np.bool_] | None:
    """A region of interest as an (H, W) bool mask of the frame's shape, or None for the whole image.

    Raises:
        CalibrationError: A mask of another shape or type, or an empty one.
    """
    if region is None:
        return None
    mask = np.asarray(region)
    if mask.dtype != np.bool_ or mask.shape != shape:
        raise CalibrationError(f"the region of interest must be a bool mask of shape {shape}, got "
                               f"{mask.dtype} of shape {mask.shape}")
    if not mask.any():
        raise CalibrationError("the region of interest holds no pixel")
    return mask
