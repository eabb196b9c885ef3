"""The arm's smooth error over a plan as common coefficients: its flange error linear in the pose (ADR 0055).

An uncalibrated arm's flange error comes from its kinematic parameters (joint zeros, link
lengths): it is smooth in the joints, so over one plan it is a constant (a mount and plane
error, :meth:`~cellcal.core.handeye.estimator.ArmAccuracy.common_covariance`) plus a part that
changes with the pose *in step with it*. That part does not average out as random per-pose
noise would: a wrist-zero error moves the flange along the optical axis by an amount that
follows the tilt, and the mount's translation along the optical axis, which only the tilts
show, takes it amplified (20-30x on the hand-eye plans: 0.1-0.3 mm of flange error, 2-7 mm of
mount). So the part of the stated accuracy that varies over the plan is modelled as a flange
error linear in the pose: each of its six components (a turn about the base axes, a shift)
times each of the plan's pose coordinates (the entries of the flange's rotation matrix and its
position, about their means over the plan, each scaled to unit RMS), one coefficient each,
common to the poses, with a Gaussian prior. The estimate's answer to each coefficient goes
into the intervals as the camera's systematic terms do (ADR 0059); the noise test takes them
out before it judges the residuals.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from cellcal.core.geometry.planes import tangent_basis
from cellcal.core.handeye.model import PlaneObservation, arm_error_jacobian
from cellcal.devices.pose import Pose

__all__ = ["TREND_PREFIX", "arm_trend_terms", "pose_coordinates"]

FloatArray = NDArray[np.float64]
Shift = tuple[FloatArray, float]

#: Keys of the trend terms start with this (``arm_trend_<component>_<coordinate>``).
TREND_PREFIX = "arm_trend_"
_COMPONENTS = ("rx", "ry", "rz", "x", "y", "z")
#: Pose coordinates whose spread over the plan is below these (rotation-matrix entries, m) carry no trend.
_MIN_SPREAD = (1e-4, 1e-4)


def pose_coordinates(flanges: Sequence[Pose]) -> tuple[FloatArray, list[str]]:
    """(N, k) the flange poses' coordinates about the plan's mean, each scaled to unit RMS, and their names.

    The coordinates are the entries of each flange's rotation matrix (base frame; ``r<row><col>``)
    and its position (m; ``p<axis>``), each minus its mean over the plan: smooth in the pose and
    unique, however far the plan turns the tool (a rotation vector about a mean orientation wraps
    at 180 degrees and the mean of orientations a full turn apart is not defined). One whose RMS
    over the plan is below :data:`_MIN_SPREAD` is dropped (a plan that does not move along it
    shows no trend there).
    """
    mats = np.stack([f.rotation_matrix for f in flanges]).reshape(len(flanges), 9)
    shifts = np.stack([np.asarray(f.translation, dtype=np.float64) for f in flanges])
    coords, names = [], []
    blocks = ((mats, [f"r{i}{j}" for i in range(1, 4) for j in range(1, 4)], _MIN_SPREAD[0]),
              (shifts, ["px", "py", "pz"], _MIN_SPREAD[1]))
    for block, labels, floor in blocks:
        for k, label in enumerate(labels):
            column = block[:, k] - block[:, k].mean()
            rms = float(np.sqrt(np.mean(column**2)))
            if rms > floor:
                coords.append(column / rms)
                names.append(label)
    out = np.column_stack(coords) if coords else np.zeros((len(flanges), 0))
    return out, names


def arm_trend_terms(observations: Sequence[PlaneObservation], mount: Pose, position_m: float,
                    rotation_rad: float) -> dict[str, list[Shift]]:
    """Per trend coefficient, every pose's 1-sigma shift of its measured plane (as the camera's terms).

    Args:
        observations: The poses' plane observations (their reported flanges).
        mount: The nominal mount (the lever of a turn).
        position_m: RMS length of the varying part of the flange's position error over the plan, m.
        rotation_rad: RMS angle of the varying part of its orientation error, rad.

    Returns:
        ``{arm_trend_<component>_<coordinate>: [(normal delta (3,), offset delta m) per pose]}``:
        the flange error ``sigma * coordinate`` along one component, its per-axis 1-sigma the stated
        RMS over sqrt(3) shared among the coordinates (its variance over the plan is the stated one).
    """
    coords, names = pose_coordinates([o.flange for o in observations])
    if not names or (position_m <= 0.0 and rotation_rad <= 0.0):
        return {}
    share = math.sqrt(3.0 * len(names))  # three axes, the coordinates' variances adding up
    sigma = np.array([rotation_rad] * 3 + [position_m] * 3) / share
    jacs = [arm_error_jacobian(o, mount) for o in observations]  # (3, 6) residual per flange error
    bases = [tangent_basis(o.normal) for o in observations]
    terms: dict[str, list[Shift]] = {}
    for c, comp in enumerate(_COMPONENTS):
        if sigma[c] <= 0.0:
            continue
        for j, name in enumerate(names):
            shifts = []
            for k, (jac, basis) in enumerate(zip(jacs, bases, strict=True)):
                dr = jac[:, c] * (sigma[c] * coords[k, j])  # the residual's change (predicted - measured)
                # the measured plane's move that changes the residual so: residual = -(basis^T dn, dc)
                shifts.append((-(basis @ dr[:2]), -float(dr[2])))
            terms[f"{TREND_PREFIX}{comp}_{name}"] = shifts
    return terms
