"""A camera pose looking at a point, for the fixed-camera tests and benchmark."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from cellcal.devices.pose import Pose


def look_at(eye: Sequence[float], target: Sequence[float]) -> Pose:
    """``T_base_camera`` at ``eye`` (m) with its optical axis (z) toward ``target`` (m), its x horizontal."""
    e = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - e
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    return Pose.from_rotation_matrix(np.column_stack([x, np.cross(z, x), z]), e)
