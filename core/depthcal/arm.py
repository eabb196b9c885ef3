"""What the arm's stated accuracy does to a depth calibration: its share of the fit's covariance (ADR 0056).

The depth calibration takes the flange poses the arm reports as the camera's motion: the arm's
known relative motion is what fixes the depth scale. An uncalibrated arm errs by tenths of a
millimetre, smoothly with the pose, and over a plan that spans 0.3 m of height that is a
depth-scale error of the order of 0.1 %, the size of the scale's own interval. The error is
split as the hand-eye fit splits it (:class:`~cellcal.core.handeye.estimator.ArmAccuracy`,
ADR 0055): common to the poses in the flange frame (a mount error: the camera shifted along its
axis is a depth offset) and in the base frame (a plane error), in step with the pose (linear in
the plan's pose coordinates, :func:`~cellcal.core.handeye.arm_trend.pose_coordinates`) and at
random per pose. Each part is propagated to first order through the fit at its solution,
``dx = H⁻¹ Jᵀ W dpredicted``, from one evaluation of the true values per unit flange error and
frame (twelve in all), and enters the intervals unscaled (the data cannot tell it from the truth).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from cellcal.core.handeye.arm_trend import pose_coordinates
from cellcal.devices.pose import Pose

if TYPE_CHECKING:
    from cellcal.core.handeye.estimator import ArmAccuracy

__all__ = ["arm_covariance"]

FloatArray = NDArray[np.float64]

#: Size of the unit flange errors the predictions are differenced over (rad, m): small enough to be linear.
_STEP = 1e-5


def _turned(flange: Pose, axis: int, step: float, in_flange: bool) -> Pose:
    """``flange`` erring by ``step`` along one of six components (turn about x, y, z; shift along x, y, z)."""
    delta = np.zeros(6)
    delta[axis] = step
    d = Pose.from_xyz_rotvec(delta[3:], delta[:3])
    if in_flange:
        return flange @ d  # a mount error: the camera moves with the flange's axes
    # about the base axes, at the flange's origin (as the hand-eye fit's arm_error_jacobian)
    return Pose.from_rotation_matrix(d.rotation_matrix @ flange.rotation_matrix,
                                     np.asarray(flange.translation) + delta[3:])


def arm_covariance(prob: Any, fit: Any, accuracy: ArmAccuracy, jw: FloatArray, pred: FloatArray,
                   h_inv: FloatArray) -> FloatArray:
    """(p, p) covariance the arm's stated accuracy puts on the fit's parameters (geometry, then the free terms).

    Args:
        prob: The final fit's problem (its views' reported flanges, the mount, the terms fitted).
        fit: Its solution (``x``, the inlier points and their noise).
        accuracy: The arm's stated accuracy and its split (common, ``trend``, ``varying``).
        jw: (p, N) the whitened d(predicted)/d(parameters) at the solution.
        pred: (N,) the predicted values at the solution.
        h_inv: (p, p) the inverse of the fit's normal matrix, priors included.
    """
    x, pts = fit.x, fit.pts
    inv_sigma = 1.0 / fit.sigma
    # a flange error changes the true values only: d(predicted) = slope * d(true), the slope once
    # (1 + scale, plus the wiggle's derivative), so that no evaluation below recomputes the wiggle
    ng = prob.n_geometry
    true0 = prob.true_values(x[:ng], pts)[0]
    step_true = 1e-6 * max(1.0, float(np.max(np.abs(true0))))
    slope = (prob.predicted(x, pts, true0 + step_true) - pred) / step_true
    unit = np.array([accuracy.rotation_rad] * 3 + [accuracy.position_m] * 3) / math.sqrt(3.0)  # per axis

    def per_view(move: Callable[[Pose, int], Pose]) -> FloatArray:
        """(n_views, 6, p): each view's gradient change per unit flange error along each component."""
        out = np.zeros((len(prob.flanges), 6, jw.shape[0]))
        for c in range(6):
            moved = dataclasses.replace(prob, flanges=[move(f, c) for f in prob.flanges])
            dpred = slope * (moved.true_values(x[:ng], pts)[0] - true0) * inv_sigma / _STEP
            for k, s in enumerate(pts.slices):
                out[k, c] = jw[:, s] @ dpred[s]
        return out

    base = per_view(lambda f, c: _turned(f, c, _STEP, in_flange=False))
    flange = per_view(lambda f, c: _turned(f, c, _STEP, in_flange=True))
    responses = []
    for c in range(6):
        if unit[c] <= 0.0:
            continue
        responses.append(h_inv @ base[:, c].sum(axis=0) * unit[c])     # common in the base frame
        responses.append(h_inv @ flange[:, c].sum(axis=0) * unit[c])   # common in the flange frame
        for k in range(base.shape[0]):                                 # at random, pose by pose
            responses.append(h_inv @ base[k, c] * (accuracy.varying * unit[c]))
    coords, names = pose_coordinates(prob.flanges)
    if names and accuracy.trend > 0.0:                                 # in step with the pose
        share = accuracy.trend / math.sqrt(len(names))
        for c in range(6):
            for j in range(coords.shape[1]):
                responses.append(h_inv @ np.tensordot(coords[:, j], base[:, c], axes=1) * (share * unit[c]))
    p = jw.shape[0]
    cov = np.zeros((p, p))
    for d in responses:
        cov += np.outer(d, d)
    return cov
