"""Weighted least squares of the plane constraints: the mount and the base-frame plane with uncertainty.

Residuals are whitened by each pose's full-frame covariance plus the arm's read-back
noise (:func:`~cellcal.core.handeye.model.whitening`); ``scipy.optimize.least_squares``
finds the nine (minus the given) parameters, the inverse of ``JᵀJ`` at the solution is
their covariance, and intervals on ``translation_m`` / ``rpy_deg`` are propagated from it.
The observability check runs before the fit: an unobservable plan raises (ADR 0018).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cellcal.core.geometry.planes import Plane
from cellcal.core.handeye.model import (
    MOUNT_ROTATION,
    MOUNT_TRANSLATION,
    PARAMETERS,
    PlaneModel,
    PlaneObservation,
    stack_poses,
    whitening,
)
from cellcal.core.handeye.observability import Observability, analyse
from cellcal.devices.errors import CalibrationError, CalibrationQualityError
from cellcal.devices.pose import Pose

FloatArray = NDArray[np.float64]
#: Central-difference step of the Jacobian (rad or m).
JACOBIAN_STEP = 1e-6


@dataclass(frozen=True)
class PoseResidual:
    """How far one pose's measured plane is from the fitted model.

    Attributes:
        normal_deg: Angle between the measured and predicted normals, degrees.
        offset_m: Measured minus predicted offset (camera distance), metres.
        chi2: Squared norm of the whitened residual (about 3 on average when the noise model holds).
    """

    normal_deg: float
    offset_m: float
    chi2: float


@dataclass(frozen=True)
class HandEyeEstimate:
    """The estimated mount and plane with covariance.

    Attributes:
        mount: Estimated ``T_flange_camera``.
        plane: Estimated plane in the base frame.
        parameters: The 9 parameter steps from the configured values (given ones 0).
        covariance: 9x9 covariance of ``parameters`` (rows/columns of given ones 0).
        given: Names of the parameters held at their configured values.
        residuals: Per pose.
        chi2: Sum of the poses' chi2; dof: residuals minus free parameters.
        observability: Rank, condition and unseen directions.
        confidence: Level of the intervals.
    """

    mount: Pose
    plane: Plane
    parameters: FloatArray
    covariance: FloatArray
    given: tuple[str, ...]
    residuals: tuple[PoseResidual, ...]
    chi2: float
    dof: int
    observability: Observability
    confidence: float

    @property
    def z(self) -> float:
        """Half-width of the intervals in sigmas."""
        from scipy.stats import norm

        return float(norm.ppf(0.5 + self.confidence / 2.0))

    @property
    def translation_sigma_m(self) -> FloatArray:
        """1-sigma of the mount translation (flange frame), metres."""
        return np.sqrt(np.diag(self.covariance)[MOUNT_TRANSLATION])

    @property
    def rotation_sigma_rad(self) -> FloatArray:
        """1-sigma of the mount's rotation about the flange x, y, z axes, rad."""
        return np.sqrt(np.diag(self.covariance)[MOUNT_ROTATION])

    def rpy_and_sigma_deg(self) -> tuple[FloatArray, FloatArray]:
        """The mount's ``rpy_deg`` (as in ``[mount]``) and their 1-sigma, degrees."""
        return rpy_with_sigma_deg(self.mount, self.covariance[MOUNT_ROTATION, MOUNT_ROTATION])

    @property
    def p_value(self) -> float:
        """Probability of a chi2 at least this large if the noise model holds."""
        from scipy.stats import chi2

        return float(chi2.sf(self.chi2, self.dof)) if self.dof > 0 else math.nan

    def to_dict(self) -> dict[str, Any]:
        """The fit's figures (JSON form; the document adds the mount and the plane)."""
        return {"chi2": self.chi2, "dof": self.dof, "chi2_per_dof": self.chi2 / self.dof if self.dof else None,
                "p_value": self.p_value, "given": list(self.given), "parameters": list(PARAMETERS),
                "covariance": self.covariance.tolist()}


def rpy_with_sigma_deg(mount: Pose, rotation_covariance: FloatArray) -> tuple[FloatArray, FloatArray]:
    """``rpy_deg`` of a mount and their 1-sigma (deg) from the covariance of its turn about the flange axes (rad²)."""
    from scipy.spatial.transform import Rotation

    rpy = mount.as_xyz_rpy()[3:]

    def rpy_of(step: FloatArray) -> FloatArray:
        turned = Pose(Rotation.from_rotvec(step) * mount.rotation, mount.translation)
        unwrapped: FloatArray = np.unwrap([rpy, turned.as_xyz_rpy()[3:]], axis=0)[1]  # near rpy
        return unwrapped

    # Jacobian of rpy over a turn about the flange axes (central differences)
    g = np.column_stack([(rpy_of(JACOBIAN_STEP * e) - rpy_of(-JACOBIAN_STEP * e)) / (2 * JACOBIAN_STEP)
                         for e in np.eye(3)])
    cov = g @ rotation_covariance @ g.T
    return np.degrees(rpy), np.degrees(np.sqrt(np.clip(np.diag(cov), 0.0, None)))


def jacobian(fun: Callable[[FloatArray], FloatArray], x: FloatArray) -> FloatArray:
    """Central-difference Jacobian of ``fun`` at ``x``."""
    cols = []
    for k in range(len(x)):
        step = np.zeros_like(x)
        step[k] = JACOBIAN_STEP
        cols.append((fun(x + step) - fun(x - step)) / (2 * JACOBIAN_STEP))
    return np.column_stack(cols) if cols else np.zeros((len(fun(x)), 0))


class _Problem:
    """The whitened residual function of a set of observations over the free parameters."""

    def __init__(self, model: PlaneModel, observations: Sequence[PlaneObservation], free: Sequence[int],
                 arm_translation_sigma_m: float, arm_rotation_sigma_rad: float) -> None:
        self.model = model
        self.observations = observations
        self.free = list(free)
        self.flanges = stack_poses([o.flange for o in observations])  # rotation matrices and translations
        lever = float(np.linalg.norm(model.nominal_mount.translation))
        w = [whitening(o, arm_translation_sigma_m, arm_rotation_sigma_rad, lever) for o in observations]
        self.bases = np.stack([b for b, _ in w])  # (N, 3, 2) tangent bases of the measured normals
        self.whiten = np.stack([m for _, m in w])  # (N, 3, 3) inverse Cholesky factors
        self.normals = np.stack([o.normal for o in observations])
        self.offsets = np.array([o.offset_m for o in observations])

    def full(self, x: FloatArray) -> FloatArray:
        """The 9-vector with the free parameters ``x`` and the given ones at 0."""
        p = np.zeros(len(PARAMETERS))
        p[self.free] = x
        return p

    def raw(self, x: FloatArray) -> FloatArray:
        """Unwhitened residuals (N, 3): tangent components of the normal error, offset error."""
        normals, offsets = self.model.predict(self.full(x), self.flanges)
        tangent = np.einsum("nij,ni->nj", self.bases, normals - self.normals)  # predicted - measured, across
        return np.column_stack([tangent, offsets - self.offsets])

    def __call__(self, x: FloatArray) -> FloatArray:
        """Whitened residuals, flattened (3N,)."""
        white: FloatArray = np.einsum("nij,nj->ni", self.whiten, self.raw(x)).ravel()
        return white


def _setup(observations: Sequence[PlaneObservation], nominal_mount: Pose, nominal_plane: Plane,
           given: Sequence[str], arm_translation_sigma_m: float, arm_rotation_sigma_rad: float
           ) -> tuple[PlaneModel, _Problem, FloatArray]:
    """The model, the residual function and the normals in the flange frame (N, 3) of a problem.

    Raises:
        CalibrationError: Fewer than 2 observations, or an unknown given name.
    """
    if len(observations) < 2:
        raise CalibrationError(f"hand-eye estimation needs at least 2 poses, got {len(observations)}")
    unknown = sorted(set(given) - set(PARAMETERS))
    if unknown:
        raise CalibrationError(f"unknown given parameter(s) {unknown}; expected some of {', '.join(PARAMETERS)}")
    camera = observations[0].flange @ nominal_mount
    if nominal_plane.signed_distance(camera.translation[None])[0] < 0:
        nominal_plane = Plane(-nominal_plane.normal, -nominal_plane.offset_m)  # normal toward the camera side
    model = PlaneModel(nominal_mount, nominal_plane)
    free = [i for i, name in enumerate(PARAMETERS) if name not in given]
    problem = _Problem(model, observations, free, arm_translation_sigma_m, arm_rotation_sigma_rad)
    normal = np.array(nominal_plane.normal)
    normals_flange = np.stack([o.flange.rotation.inv().apply(normal) for o in observations])  # u_i
    return model, problem, normals_flange


def observability(observations: Sequence[PlaneObservation], nominal_mount: Pose, nominal_plane: Plane, *,
                  given: Sequence[str] = (), arm_translation_sigma_m: float = 2.5e-5,
                  arm_rotation_sigma_rad: float = 0.0) -> Observability:
    """What the observations can determine, at the configured values (no fit).

    Raises:
        CalibrationError: Fewer than 2 observations, or an unknown given name.
    """
    _, problem, normals_flange = _setup(observations, nominal_mount, nominal_plane, given,
                                        arm_translation_sigma_m, arm_rotation_sigma_rad)
    return analyse(jacobian(problem, np.zeros(len(problem.free))), problem.free, normals_flange)


def estimate_mount(observations: Sequence[PlaneObservation], nominal_mount: Pose, nominal_plane: Plane, *,
                   given: Sequence[str] = (), arm_translation_sigma_m: float = 2.5e-5,
                   arm_rotation_sigma_rad: float = 0.0, confidence: float = 0.95) -> HandEyeEstimate:
    """Estimate the mount and the base-frame plane from plane observations.

    Args:
        observations: One per pose (:func:`~cellcal.core.handeye.model.observation_from_pose`).
        nominal_mount: The configured ``T_flange_camera`` (start, and value of given mount parameters).
        nominal_plane: The configured base-frame plane (likewise); its normal is turned toward the cameras.
        given: Parameter names (:data:`PARAMETERS`) held at their configured values.
        arm_translation_sigma_m: 1-sigma of the arm's position read-back per axis, m.
        arm_rotation_sigma_rad: 1-sigma of its orientation read-back per axis, rad.
        confidence: Level of the intervals.

    Raises:
        CalibrationError: Fewer than 2 observations, or an unknown given name.
        CalibrationQualityError: Gate ``observability``: the plan leaves a parameter unobservable;
            the message names it and the poses that would fix it.
    """
    from scipy.optimize import least_squares

    model, problem, normals_flange = _setup(observations, nominal_mount, nominal_plane, given,
                                            arm_translation_sigma_m, arm_rotation_sigma_rad)
    free = problem.free
    x0 = np.zeros(len(free))
    seen = analyse(jacobian(problem, x0), free, normals_flange)  # structural: before trusting any fit
    if not seen.observable:
        raise CalibrationQualityError("observability", seen.rank, seen.n_parameters, seen.message())
    fit = least_squares(problem, x0, jac=lambda x: jacobian(problem, x), method="lm", xtol=1e-15, ftol=1e-15)
    jac = jacobian(problem, fit.x)
    cov_free = np.linalg.inv(jac.T @ jac)  # absolute weights: no rescaling by the residual variance
    cov = np.zeros((len(PARAMETERS), len(PARAMETERS)))
    cov[np.ix_(free, free)] = cov_free
    params = problem.full(fit.x)
    return HandEyeEstimate(model.mount(params), model.plane(params), params, cov, tuple(given),
                           _residuals(problem, fit.x), float(fit.fun @ fit.fun), len(fit.fun) - len(free),
                           analyse(jac, free, normals_flange), confidence)


def _residuals(problem: _Problem, x: FloatArray) -> tuple[PoseResidual, ...]:
    """Per-pose residuals at the solution."""
    normals, offsets = problem.model.predict(problem.full(x), problem.flanges)
    white = problem(x).reshape(-1, 3)
    out = []
    for i in range(len(problem.observations)):
        # angle between the normals (atan2 keeps its precision near 0, unlike acos)
        angle = math.atan2(float(np.linalg.norm(np.cross(normals[i], problem.normals[i]))),
                           float(normals[i] @ problem.normals[i]))
        out.append(PoseResidual(math.degrees(angle), float(problem.offsets[i] - offsets[i]),
                                float(white[i] @ white[i])))
    return tuple(out)


__all__ = ["HandEyeEstimate", "PoseResidual", "estimate_mount", "jacobian", "observability", "rpy_with_sigma_deg"]
