"""Which flange orientations an arm class can take (``reach`` classes).

A 6-axis arm can point its tool any way inside its workspace. A 5-axis arm such as the
UFACTORY xArm 5 has base yaw J1, three pitch joints and a flange roll J5: its tool axis
always lies in the vertical plane through the base axis and the flange (the plane J1
turns), so it can tilt its tool toward or away from the base and roll about the tool
axis, but never tilt it sideways. Poses follow ADR 0002 (``T_base_flange``, metres).
"""

from __future__ import annotations

import math
from typing import Literal, get_args

import numpy as np

from cellcal.devices.pose import Pose

#: The arm classes: ``any`` (every orientation, a 6/7-axis arm), ``xarm5`` (5 axes).
ReachClass = Literal["any", "xarm5"]
REACH_CLASSES: tuple[str, ...] = get_args(ReachClass)
#: Largest sideways tilt of the tool axis out of the base's vertical plane a 5-axis arm accepts, rad
#: (numerical slack of a pose computed for it, far below any real arm's resolution).
SIDEWAYS_TOLERANCE_RAD = 1e-6
#: Flange positions closer than this to the base axis leave J1 free (every tool direction is radial), m.
AXIS_RADIUS_M = 1e-9


def sideways_tilt_rad(pose: Pose) -> float:
    """Angle of the tool axis (flange z) out of the vertical plane through the base axis and the flange, rad.

    Zero for every pose a 5-axis arm can take; 0 on the base axis itself.
    """
    x, y = float(pose.translation[0]), float(pose.translation[1])
    r = math.hypot(x, y)
    if r < AXIS_RADIUS_M:
        return 0.0
    tangent = np.array([-y / r, x / r, 0.0])  # horizontal direction across the J1 plane
    tool = pose.rotation.apply([0.0, 0.0, 1.0])  # the tool (approach) axis in the base frame
    return math.asin(min(1.0, abs(float(tool @ tangent))))


def orientation_violation(pose: Pose, reach: str) -> str | None:
    """Why an arm of class ``reach`` cannot take the orientation of ``pose``, or None when it can.

    Raises:
        ValueError: If ``reach`` is not one of :data:`REACH_CLASSES`.
    """
    if reach not in REACH_CLASSES:
        raise ValueError(f"unknown reach class {reach!r}; expected one of {', '.join(REACH_CLASSES)}")
    if reach == "any":
        return None
    tilt = sideways_tilt_rad(pose)
    if tilt <= SIDEWAYS_TOLERANCE_RAD:
        return None
    return (f"tool axis tilted {math.degrees(tilt):.3f} deg sideways out of the base's vertical plane "
            "(a 5-axis arm tilts its tool only toward or away from the base)")


def radial_flange_rotation(j1_rad: float, pitch_rad: float, roll_rad: float) -> Pose:
    """A flange orientation a 5-axis arm can take (translation zero).

    Tool pointing down, pitched by ``pitch_rad`` in the vertical plane at base yaw
    ``j1_rad`` (positive: the tool points back toward the base axis), then rolled by
    ``roll_rad`` about the tool axis. Any arm class can take it at a flange position
    whose base yaw is ``j1_rad``.
    """
    from scipy.spatial.transform import Rotation

    # intrinsic: base yaw, pitch in that vertical plane, tool turned down (flange z along -z), roll about the tool
    r = Rotation.from_euler("ZYX", [j1_rad, pitch_rad, math.pi]) * Rotation.from_euler("z", roll_rad)
    return Pose(r, np.zeros(3))


__all__ = [
    "REACH_CLASSES",
    "SIDEWAYS_TOLERANCE_RAD",
    "ReachClass",
    "orientation_violation",
    "radial_flange_rotation",
    "sideways_tilt_rad",
]
