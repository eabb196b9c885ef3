"""Vendor pose conventions, converted only at a driver's boundary.

* Universal Robots: ``[x, y, z, rx, ry, rz]`` — metres and a rotation vector (rad).
* UFACTORY xArm: ``[x, y, z, roll, pitch, yaw]`` — millimetres and fixed-axis
  (extrinsic) x-y-z angles in radians, i.e. ``R = Rz(yaw) Ry(pitch) Rx(roll)``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cellcal.devices.errors import CalibrationError
from cellcal.devices.pose import Pose

FloatArray = NDArray[np.float64]

__all__ = ["pose_from_ur", "pose_from_xarm", "pose_to_ur", "pose_to_xarm"]

_MM = 1e-3


def _six(values: ArrayLike, what: str) -> FloatArray:
    try:
        arr = np.asarray(values, dtype=np.float64).ravel()
    except (TypeError, ValueError) as exc:
        raise CalibrationError(f"{what} pose must be 6 numbers, got {values!r}") from exc
    if arr.size != 6:
        raise CalibrationError(f"{what} pose must be 6 numbers, got {arr.size}")
    if not np.all(np.isfinite(arr)):
        raise CalibrationError(f"{what} pose must be finite, got {arr.tolist()}")
    return arr


def pose_from_ur(xyz_rotvec: ArrayLike) -> Pose:
    """Pose from UR's ``[x, y, z, rx, ry, rz]`` (metres, rotation vector in rad)."""
    v = _six(xyz_rotvec, "UR")
    return Pose.from_xyz_rotvec(v[:3], v[3:])


def pose_to_ur(pose: Pose) -> FloatArray:
    """UR's ``[x, y, z, rx, ry, rz]`` (metres, rotation vector with angle in [0, pi])."""
    return pose.as_xyz_rotvec()


def pose_from_xarm(xyz_mm_rpy_rad: ArrayLike) -> Pose:
    """Pose from xArm's ``[x, y, z, roll, pitch, yaw]`` (mm, rad; extrinsic x-y-z)."""
    v = _six(xyz_mm_rpy_rad, "xArm")
    return Pose.from_xyz_rpy(v[:3] * _MM, v[3:])


def pose_to_xarm(pose: Pose) -> FloatArray:
    """xArm's ``[x, y, z, roll, pitch, yaw]`` (mm, rad; extrinsic x-y-z)."""
    xyz_rpy = pose.as_xyz_rpy()
    return np.concatenate([xyz_rpy[:3] / _MM, xyz_rpy[3:]])
