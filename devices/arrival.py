"""Arrival of a move: the read-back pose at rest must be steady and at the target (ADR 0016)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from .errors import CellcalError
from .pose import Pose

#: Largest tolerances accepted: beyond them "arrived" would mean nothing for a calibration.
MAX_POSITION_TOLERANCE_M = 0.1
MAX_ANGLE_TOLERANCE_RAD = math.radians(10.0)


def format_pose(pose: Pose) -> str:
    """``xyz=(x, y, z) m rpy=(r, p, y) deg`` of a flange pose, for messages."""
    x, y, z = pose.translation
    r = np.degrees(pose.as_xyz_rpy()[3:])  # at pitch +-90 deg any split of roll and yaw names the pose
    return f"xyz=({x:.4f}, {y:.4f}, {z:.4f}) m rpy=({r[0]:.2f}, {r[1]:.2f}, {r[2]:.2f}) deg"


@dataclass(frozen=True)
class ArrivalTolerance:
    """How close a finished move must read back, and how many reads must agree.

    Attributes:
        position_m: Largest distance of each read from the target, and between
            consecutive reads, metres (default 1 mm: an industrial arm repeats to
            0.02-0.1 mm).
        angle_rad: Same for the orientation, radians (default 0.1 deg).
        reads: Pose reads taken at rest after the move reports done (>= 2, so a
            jumping read-back is seen).
    """

    position_m: float = 1e-3
    angle_rad: float = math.radians(0.1)
    reads: int = 2

    def __post_init__(self) -> None:
        for name, top in (("position_m", MAX_POSITION_TOLERANCE_M), ("angle_rad", MAX_ANGLE_TOLERANCE_RAD)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value <= top:
                raise CellcalError(f"ArrivalTolerance.{name} must be in (0, {top:.4g}], got {value!r}")
        if isinstance(self.reads, bool) or not isinstance(self.reads, int) or not 2 <= self.reads <= 10:
            raise CellcalError(f"ArrivalTolerance.reads must be an integer in [2, 10], got {self.reads!r}")

    def with_overrides(self, position_m: float | None = None, angle_rad: float | None = None) -> ArrivalTolerance:
        """This tolerance with the given fields replaced (None keeps the current value)."""
        return replace(self, position_m=self.position_m if position_m is None else position_m,
                       angle_rad=self.angle_rad if angle_rad is None else angle_rad)

    def describe(self) -> str:
        """``1 mm / 0.1 deg`` for messages."""
        return f"{self.position_m * 1e3:.3g} mm / {math.degrees(self.angle_rad):.3g} deg"


def _apart(a: Pose, b: Pose) -> str:
    return f"{a.distance_to(b) * 1e3:.3f} mm and {math.degrees(a.angle_to(b)):.4f} deg"


def _outside(a: Pose, b: Pose, tol: ArrivalTolerance) -> bool:
    return not (a.distance_to(b) <= tol.position_m and a.angle_to(b) <= tol.angle_rad)


def arrival_problem(target: Pose, readings: Sequence[Pose], tol: ArrivalTolerance) -> str | None:
    """Why ``readings`` (pose reads at rest, in order) do not show an arrival at ``target``.

    Consecutive reads are compared first (a jumping read-back says nothing about where
    the arm is), then each read against the target.

    Returns:
        None when every read is within ``tol`` of the target and of the read before it,
        else one line naming the first offending read and the distances.
    """
    n = len(readings)
    for i in range(1, n):
        if _outside(readings[i - 1], readings[i], tol):
            return (f"pose reads {i} and {i + 1} of {n} at rest differ by {_apart(readings[i - 1], readings[i])} "
                    f"(tolerance {tol.describe()}): the reported pose is not steady")
    for i, reading in enumerate(readings, 1):
        if _outside(reading, target, tol):
            return (f"pose read {i} of {n} is {_apart(reading, target)} from the target "
                    f"(tolerance {tol.describe()}), at {format_pose(reading)}")
    return None
