"""Where the fit should look: the plane the user means (:class:`ExpectedPlane`).

The calibration layer builds it from ``[reference]``, ``[mount]`` and the arm pose; the fit
only takes it (ADR 0027, "The plane the user means"). The pixel region is checked where the
frames become points (``points.check_region``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cellcal.core.geometry.planes import Plane
from cellcal.devices.errors import CalibrationError

__all__ = ["DEFAULT_SEARCH_TOLERANCE_DEG", "DEFAULT_SEARCH_TOLERANCE_M", "ExpectedPlane"]

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
