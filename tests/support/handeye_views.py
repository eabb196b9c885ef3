"""Synthetic plane (and board) views for the hand-eye tests, independent of the simulator.

A true mount and a true plane give each flange pose its camera-frame plane exactly;
Gaussian noise of a stated covariance (normal across itself, offset, and the arm's
read-back) is then added, and the observation carries that covariance.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from cellcal.core.geometry.planes import Plane
from cellcal.core.handeye import PlaneObservation
from cellcal.core.handeye.model import tangent_basis
from cellcal.devices.pose import Pose

NOMINAL_MOUNT = Pose.from_xyz_rpy([0.0, 0.04, 0.06], np.radians([0.0, 0.0, 90.0]))
TRUE_MOUNT = Pose.from_xyz_rpy([0.003, 0.036, 0.063], np.radians([0.6, -0.5, 90.6]))
TABLE = Plane.from_point_normal([0.0, 0.0, 0.0], [0.0, 0.0, 1.0])
#: The true table's tilt about the base x and y axes (rad) and its plane.
TRUE_TABLE_TILT = np.array([3e-4, -2e-4])
TRUE_TABLE = Plane.from_point_normal([0.0, 0.0, 0.0012], Rotation.from_rotvec([*TRUE_TABLE_TILT, 0.0]).apply([0, 0, 1]))
NORMAL_SIGMA_RAD = 5e-5
OFFSET_SIGMA_M = 2e-5
ARM_SIGMA_M = 2.5e-5


def plane_views(flanges: Sequence[Pose], rng: np.random.Generator | None, *, mount: Pose = TRUE_MOUNT,
                plane: Plane = TRUE_TABLE, correlation: float = 0.3) -> list[PlaneObservation]:
    """One observation per flange pose; ``rng=None`` adds no noise (the covariance is still stated)."""
    out = []
    for flange in flanges:
        camera = flange @ mount
        n = camera.rotation.inv().apply(np.array(plane.normal))  # the true normal in the camera frame
        offset = plane.offset_m + float(np.array(plane.normal) @ camera.translation)
        across = tangent_basis(n)  # two axes across the normal (an SVD's would change with the BLAS kernel)
        # covariance of (normal, offset): tangent noise, offset noise, and a correlation between the first two
        c2 = np.diag([NORMAL_SIGMA_RAD**2, NORMAL_SIGMA_RAD**2, OFFSET_SIGMA_M**2])
        c2[0, 2] = c2[2, 0] = correlation * NORMAL_SIGMA_RAD * OFFSET_SIGMA_M
        m = np.zeros((4, 3))
        m[:3, :2] = across
        m[3, 2] = 1.0
        cov = m @ c2 @ m.T
        read = flange
        if rng is not None:
            step = rng.multivariate_normal(np.zeros(3), c2, method="cholesky")  # unique factor: the same on any BLAS
            n = n + across @ step[:2]
            n /= np.linalg.norm(n)
            offset += step[2]
            read = Pose(flange.rotation, flange.translation + rng.normal(0.0, ARM_SIGMA_M, 3))  # read-back noise
        out.append(PlaneObservation(read, n, offset, cov))
    return out


def board_views(flanges: Sequence[Pose], board: Pose, rng: np.random.Generator | None, *, mount: Pose = TRUE_MOUNT,
                rotation_sigma_rad: float = 0.0, translation_sigma_m: float = 0.0) -> list[Pose]:
    """``T_camera_board`` per flange pose, with optional Gaussian noise."""
    out = []
    for flange in flanges:
        view = (flange @ mount).inv() @ board
        if rng is not None:
            turn = Rotation.from_rotvec(rng.normal(0.0, rotation_sigma_rad, 3))
            view = Pose(turn * view.rotation, view.translation + rng.normal(0.0, translation_sigma_m, 3))
        out.append(view)
    return out
