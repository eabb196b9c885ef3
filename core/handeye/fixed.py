"""Target-free pose of a camera fixed in the cell from a plate the arm shows it (issue #40).

The arm holds a flat plate, its plane ``p_f`` (``n_f·x + c_f = 0``) fixed in the flange frame, and
shows it to the camera at several orientations. At pose ``i`` the arm reads back
``F_i = T_base_flange``; the camera at ``X = T_base_camera`` sees the plate as ``p_f`` transformed by
``X⁻¹ F_i`` (:meth:`~cellcal.core.geometry.planes.Plane.transformed`): ``n_C = R_Xᵀ n_B`` with
``n_B = R_F n_f``, ``c_C = c_f - n_B·(t_F - t_X)``. It may also see the measuring plane ``p_B``, known in
the base frame with a covariance, as ``n_C = R_Xᵀ n_B``, ``c_C = c_B + n_B·t_X``.

The parameters (:data:`~cellcal.core.handeye.fixed_plan.FIXED_PARAMETERS`) are small steps from the
configured values: the camera's turn about the base axes (a rotation vector, rad, applied on the
left: ``R_X = exp(δθ) R_X0``), its translation along them (m, base frame: ``t_X = t_X0 + δt``), and,
when the plate is estimated, its normal's tilts about the two axes across the configured normal in
the flange frame (rad) and its offset (m), as the hand-eye model's plane
(:class:`~cellcal.core.handeye.model.PlaneModel`). The residuals are whitened as in :mod:`.estimator`
(a pose's covariance, plus the arm's random error per pose, plus the measuring plane's own
uncertainty in its view); the observability check runs before the fit; the chi2 test of
:mod:`.noise` scales or refuses the intervals.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cellcal.core.geometry.planes import Plane, tangent_basis
from cellcal.core.geometry.relative import cross_matrix
from cellcal.core.handeye.estimator import ArmAccuracy, jacobian, rpy_with_sigma_deg
from cellcal.core.handeye.fixed_plan import (
    CAMERA_ROTATION,
    FIXED_PARAMETERS,
    FixedModel,
    FixedObservability,
    MeasuringPlaneView,
    analyse_fixed,
    arm_plate_covariance,
    measuring_covariance,
    whiten_view,
)
from cellcal.core.handeye.fixed_systematic import systematic_columns, systematic_response
from cellcal.core.handeye.model import PlaneObservation, PlaneResiduals, stack_poses
from cellcal.core.handeye.noise import MAX_INTERVAL_SCALE, NOISE_TEST_LEVEL, NoiseCheck, check_noise, scaled_covariance
from cellcal.devices.errors import CalibrationError, CalibrationQualityError
from cellcal.devices.pose import Pose

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class ViewResidual:
    """How far one view's measured plane is from the fitted model.

    Attributes:
        normal_rad: Angle between the measured and predicted normals, rad.
        offset_m: Measured minus predicted offset (camera distance), m.
        whitened: The whitened residual (two tangent components of the normal's error, the offset's).
    """

    normal_rad: float
    offset_m: float
    whitened: tuple[float, float, float]

    @property
    def chi2(self) -> float:
        """Squared norm of the whitened residual (about 3 on average when the noise model holds)."""
        return float(np.dot(self.whitened, self.whitened))


@dataclass(frozen=True)
class FixedCameraEstimate:
    """A fixed camera's pose in the base frame and the plate's plane in the flange, with uncertainty.

    Attributes:
        camera_base: Estimated ``T_base_camera``.
        covariance: 6x6 covariance of the camera's pose as (turn about base x, y, z, rad; translation along
            them, m), the first six :data:`FIXED_PARAMETERS`: scaled by chi2/dof when ``noise.verdict``
            is ``scaled``.
        plate_flange: The plate's plane in the flange frame (estimated, or the configured one given), its
            normal on the face the camera sees.
        plate_covariance: 3x3 covariance of its (tilt a, tilt b about the axes of
            :func:`~cellcal.core.geometry.planes.tangent_basis` of the configured normal so turned, rad;
            offset, m); None when held exact.
        parameters: The 9 steps from the configured values (plate ones 0 when held exact).
        half_widths: Half-width of each fitted parameter's interval at ``confidence``, rad or m.
        residuals: Per plate pose.
        measuring_residual: The measuring plane's view (None without it).
        chi2: Sum of the views' chi2 plus the plate prior's terms; dof: residuals minus fitted parameters.
        noise: The chi2 test of the stated noise and the interval scale it implies.
        observability: Rank, condition and unseen directions at the configured values.
        confidence: Level of the intervals.
        plate: ``estimated``, ``prior`` (given, fitted with ``plate_sigma``) or ``exact`` (given).
        arm_accuracy: The arm's stated accuracy whose random part per pose is in the weights (None: none).
        arm_common_covariance: 6x6 the arm's error common to the poses would add to ``covariance`` for the
            camera's pose in the true base frame (None without an arm accuracy); not in ``covariance``.
        systematic_terms: The camera's systematic terms taken as common to the views (:mod:`.fixed_systematic`).
        systematic_covariance: 6x6: their part of ``covariance`` (the floor no number of views lowers).
    """

    camera_base: Pose
    covariance: FloatArray
    plate_flange: Plane
    plate_covariance: FloatArray | None
    parameters: FloatArray
    half_widths: Mapping[str, float]
    residuals: tuple[ViewResidual, ...]
    measuring_residual: ViewResidual | None
    chi2: float
    dof: int
    noise: NoiseCheck
    observability: FixedObservability
    confidence: float
    plate: str
    arm_accuracy: ArmAccuracy | None = None
    arm_common_covariance: FloatArray | None = None
    systematic_terms: tuple[str, ...] = ()
    systematic_covariance: FloatArray | None = None

    @property
    def z(self) -> float:
        """Half-width of the intervals in sigmas (Student-t when the scale came from the data)."""
        return float(self.noise.interval_z)

    @property
    def chi2_per_dof(self) -> float:
        """chi2/dof (NaN without dof)."""
        return float(self.noise.chi2_per_dof)

    @property
    def sigma(self) -> FloatArray:
        """1-sigma of the camera's turn about the base axes (rad) and translation (m), (6,)."""
        return np.sqrt(np.diag(self.covariance))

    def rpy_and_sigma_deg(self) -> tuple[FloatArray, FloatArray]:
        """The camera's fixed-axis roll, pitch, yaw in the base frame and their 1-sigma, degrees."""
        rpy, sigma = rpy_with_sigma_deg(self.camera_base, self.covariance[CAMERA_ROTATION, CAMERA_ROTATION])
        return np.asarray(rpy, dtype=np.float64), np.asarray(sigma, dtype=np.float64)

    @property
    def notes(self) -> tuple[str, ...]:
        """What the intervals rest on, in words: the noise test, the plate, the arm and the measuring plane."""
        out = [] if self.noise.note() is None else [str(self.noise.note())]
        if self.noise.verdict == "too_good":
            out.append("residuals this small are suspect: check that the poses' covariances are not overstated "
                       "and that the views are independent frames")
        if self.plate == "exact":
            out.append("the plate's plane in the flange held exact at the configured one: the intervals are "
                       "conditional on it (give plate_sigma to include its uncertainty)")
        elif self.plate == "prior":
            out.append("the plate's plane in the flange fitted with the prior plate_sigma: its uncertainty is in "
                       "the intervals")
        if self.arm_accuracy is not None:
            a = self.arm_accuracy
            trend = "; its trend over the poses is not modelled" if a.trend > 0 else ""
            out.append(f"the arm's accuracy ({1000 * a.position_m:.3g} mm, {math.degrees(a.rotation_rad):.3g} deg "
                       f"RMS, stated by {a.source}): {100 * a.varying:.3g} % of it at random per pose is in the "
                       "weights; its part common to the poses moves the base frame the camera is found in with the "
                       f"arm's own and is not in the intervals (arm_common_covariance){trend}")
        if self.systematic_terms:
            out.append(f"the camera's systematic allowance ({', '.join(self.systematic_terms)}) is common to the "
                       "views: weighed by the fits' noise alone, each term's response is in the intervals, unscaled")
        if self.measuring_residual is not None:
            out.append("the measuring plane's view is weighted with its base-frame uncertainty")
        return tuple(out)

    def to_dict(self) -> dict[str, Any]:
        """JSON form (SI units)."""
        return {"camera_base": self.camera_base.to_dict(), "plate_flange": self.plate_flange.to_dict(),
                "parameters": list(FIXED_PARAMETERS), "steps": self.parameters.tolist(),
                "covariance": self.covariance.tolist(),
                "plate_covariance": None if self.plate_covariance is None else self.plate_covariance.tolist(),
                "half_widths": dict(self.half_widths), "confidence": self.confidence, "chi2": self.chi2,
                "dof": self.dof, "plate": self.plate, "noise_model": self.noise.to_dict(),
                "observability": self.observability.to_dict(), "notes": list(self.notes)}


class _Views(PlaneResiduals):
    """The whitened residual function of the plate views (and the measuring plane's) over the fitted parameters."""

    def __init__(self, model: FixedModel, observations: Sequence[PlaneObservation],
                 measuring: MeasuringPlaneView | None, fitted: Sequence[int], arm: ArmAccuracy | None) -> None:
        self.model, self.free = model, list(fitted)
        self.flanges = stack_poses([o.flange for o in observations])
        camera = model.nominal_camera
        rms = (0.0, 0.0) if arm is None else (arm.varying * arm.position_m, arm.varying * arm.rotation_rad)
        # weighed by the fits' noise alone when they state it: their systematic allowance is common to the views
        # (fixed_systematic), not per-view noise
        whiten = [whiten_view(o.normal, o.covariance if o.noise_covariance is None else o.noise_covariance,
                              arm_plate_covariance(o, camera, *rms)) for o in observations]
        normals, offsets = [o.normal for o in observations], [o.offset_m for o in observations]
        if measuring is not None and model.measuring is not None:
            whiten.append(whiten_view(measuring.normal, measuring.covariance,
                                  measuring_covariance(measuring, model.measuring, camera)))
            normals.append(measuring.normal)
            offsets.append(measuring.offset_m)
        self.whiten = np.stack(whiten)  # (V, 3, 3) inverse Cholesky factors
        self.normals, self.offsets = np.stack(normals), np.array(offsets)
        self.bases = np.stack([tangent_basis(n) for n in self.normals])  # (V, 3, 2) across the measured normals

    def residuals(self, x: FloatArray) -> tuple[ViewResidual, ...]:
        """Per view at ``x``: the angle between the normals, the offset's error and the whitened residual."""
        normals, offsets = self.model.predict(self.full(x), self.flanges)
        white = self(x).reshape(-1, 3)
        out = []
        for k, (n, measured) in enumerate(zip(normals, self.normals, strict=True)):
            angle = math.atan2(float(np.linalg.norm(np.cross(n, measured))), float(n @ measured))  # precise near 0
            out.append(ViewResidual(angle, float(self.offsets[k] - offsets[k]),
                                    (float(white[k, 0]), float(white[k, 1]), float(white[k, 2]))))
        return tuple(out)


def estimate_fixed_camera(plate_observations: Sequence[PlaneObservation], nominal_camera: Pose, nominal_plate: Plane,
                          *, measuring_plane: MeasuringPlaneView | None = None, estimate_plate: bool = True,
                          plate_sigma: Sequence[float] | None = None, arm_accuracy: ArmAccuracy | None = None,
                          confidence: float = 0.95, noise_test_level: float = NOISE_TEST_LEVEL,
                          max_interval_scale: float = MAX_INTERVAL_SCALE) -> FixedCameraEstimate:
    """Estimate a fixed camera's ``T_base_camera`` (and the plate's plane in the flange) from plate views.

    Args:
        plate_observations: The plate as the camera saw it, one per flange pose (``flange``: the pose the
            arm read back; ``covariance``: the fit's total, taken as the pose's noise).
        nominal_camera: The configured ``T_base_camera`` (start, and zero of the parameters).
        nominal_plate: The configured plate plane in the flange frame (turned toward the camera if need be).
        measuring_plane: The measuring plane as the camera saw it, with its base-frame plane and covariance.
        estimate_plate: Whether the plate's plane is estimated (3 more parameters) or given.
        plate_sigma: With ``estimate_plate=False``: 1-sigma of the given plate's (tilt a, tilt b, rad;
            offset, m), fitted with that prior; None: held exact.
        arm_accuracy: The arm's stated accuracy: its ``varying`` share errs at random per pose, in the weights.
        confidence: Level of the intervals.
        noise_test_level: Level of each tail of the chi2 test of the stated noise.
        max_interval_scale: Largest factor the residuals may put on the stated noise's 1-sigma.

    Raises:
        CalibrationError: No plate view, a malformed view, covariance or option, or a view of the plate's
            other face.
        CalibrationQualityError: Gate ``observability``: the views leave a parameter unseen (the message
            names it and what would fix it). Gate ``noise_model``: the residuals are more than
            ``max_interval_scale`` times the stated noise.
    """
    observations = list(plate_observations)
    prior_sigma = _check_inputs(observations, measuring_plane, estimate_plate, plate_sigma, confidence)
    arm = _accuracy(arm_accuracy)
    model = _oriented_model(observations, nominal_camera, nominal_plate, measuring_plane)
    free = [*range(6), *((6, 7, 8) if estimate_plate else ())]
    fitted = free if prior_sigma is None else list(range(9))
    data = _Views(model, observations, measuring_plane, fitted, arm)
    seen = _structural(data, model, free)
    if not seen.observable:
        raise CalibrationQualityError("observability", seen.rank, seen.n_parameters, seen.message())
    prior_info = np.zeros(len(fitted)) if prior_sigma is None else np.concatenate([np.zeros(6), prior_sigma**-2.0])
    x, fun = _solve(data, prior_info)
    u = _uncertainty(data, observations, x, fun, prior_info, confidence, noise_test_level, max_interval_scale)
    params = data.full(x)
    camera = model.camera(params)
    n_plate, cov = len(observations), u.covariance
    return FixedCameraEstimate(
        camera, cov[:6, :6], model.plate(params), cov[6:, 6:] if len(fitted) == 9 else None, params,
        {FIXED_PARAMETERS[i]: u.noise.interval_z * math.sqrt(cov[i, i]) for i in fitted}, u.views[:n_plate],
        u.views[n_plate] if measuring_plane is not None else None, u.chi2, u.dof, u.noise, seen, confidence,
        "estimated" if estimate_plate else ("exact" if prior_sigma is None else "prior"), arm,
        None if arm is None else _arm_common_covariance(arm, camera, data.flanges[1]), u.terms,
        _camera_block(u.systematic, fitted))


@dataclass(frozen=True)
class _Uncertainty:
    """What the solution's residuals and Jacobian say of it (:func:`_uncertainty`)."""

    covariance: FloatArray  # 9x9, zero outside the fitted parameters
    systematic: FloatArray  # the systematic terms' share, over the fitted parameters
    terms: tuple[str, ...]
    chi2: float
    dof: int
    noise: NoiseCheck
    views: tuple[ViewResidual, ...]


def _uncertainty(data: _Views, observations: Sequence[PlaneObservation], x: FloatArray, fun: FloatArray,
                 prior_info: FloatArray, confidence: float, noise_test_level: float, max_interval_scale: float
                 ) -> _Uncertainty:
    """The solution's covariance: the noise's (Birge-scaled by the chi2 test) plus the common systematic terms'.

    Raises:
        CalibrationQualityError: Gate ``noise_model`` (:func:`check_noise`).
    """
    jac = jacobian(data, x)
    info_data, info_prior = jac.T @ jac, np.diag(prior_info)
    n_plate = len(observations)
    terms, cols = systematic_columns(observations, data.bases[:n_plate], data.whiten[:n_plate], len(fun))
    sys_cov, chi2 = systematic_response(jac, info_data + info_prior, fun, cols)
    dof = len(fun) - len(x)
    views = data.residuals(x)
    worst = int(np.argmax([v.chi2 for v in views]))
    noise = check_noise(chi2, dof, confidence=confidence, level=noise_test_level,
                        max_interval_scale=max_interval_scale,
                        detail=f"largest residual at view {worst + 1} (chi2 {views[worst].chi2:.4g})")
    cov = np.zeros((9, 9))
    fitted = data.free
    # Birge-scaled noise part, plus the common systematic terms' (never scaled: the data cannot tell them)
    cov[np.ix_(fitted, fitted)] = scaled_covariance(info_data, info_prior, noise.interval_scale) + sys_cov
    return _Uncertainty(cov, sys_cov, tuple(terms), chi2, dof, noise, views)


def _camera_block(cov: FloatArray, fitted: Sequence[int]) -> FloatArray:
    """The camera pose's 6x6 block of a covariance over the ``fitted`` parameters (the first six are the pose's)."""
    full = np.zeros((9, 9))
    full[np.ix_(fitted, fitted)] = cov
    return full[:6, :6]


def _structural(data: _Views, model: FixedModel, free: Sequence[int]) -> FixedObservability:
    """What the views can see, from the whitened Jacobian at the configured values (before any fit)."""
    normals_base = np.einsum("nij,j->ni", data.flanges[0], model.nominal_plate.normal)  # plate normals, base frame
    return analyse_fixed(jacobian(data, np.zeros(len(data.free)))[:, :len(free)], free, normals_base,
                         len(data.offsets))


def fixed_observability(plate_observations: Sequence[PlaneObservation], nominal_camera: Pose, nominal_plate: Plane,
                        *, estimate_plate: bool = True, measuring_plane: MeasuringPlaneView | None = None
                        ) -> FixedObservability:
    """What a plan's plate views can see (a dry run's check, before the arm moves): no fit, no noise test.

    Args:
        plate_observations: The views the plan predicts (their covariances as expected).
        nominal_camera: The configured ``T_base_camera``.
        nominal_plate: The configured plate plane in the flange frame.
        estimate_plate: Whether the plate's plane would be estimated.
        measuring_plane: The measuring plane's predicted view, if the camera sees it.

    Raises:
        CalibrationError: As :func:`estimate_fixed_camera`'s bad inputs.
    """
    observations = list(plate_observations)
    _check_inputs(observations, measuring_plane, estimate_plate, None, 0.95)
    model = _oriented_model(observations, nominal_camera, nominal_plate, measuring_plane)
    free = [*range(6), *((6, 7, 8) if estimate_plate else ())]
    return _structural(_Views(model, observations, measuring_plane, free, None), model, free)


def _check_inputs(observations: Sequence[PlaneObservation], measuring: MeasuringPlaneView | None,
                  estimate_plate: bool, plate_sigma: Sequence[float] | None, confidence: float) -> FloatArray | None:
    """Check the views and options; the given plate's prior sigma (3,), or None when none.

    Raises:
        CalibrationError: Naming what is wrong.
    """
    if not observations:
        raise CalibrationError("no plate views: show the plate to the fixed camera at 3 or more orientations")
    views: list[tuple[str, Any, Any, Any]] = [(f"plate view {k + 1}", o.normal, o.offset_m, o.covariance)
                                              for k, o in enumerate(observations)]
    if measuring is not None:
        views.append(("the measuring plane's view", measuring.normal, measuring.offset_m, measuring.covariance))
        pc = np.asarray(measuring.plane_covariance, dtype=np.float64)
        if pc.shape != (3, 3) or not np.all(np.isfinite(pc)) or np.linalg.eigvalsh((pc + pc.T) / 2)[0] < -1e-18:
            raise CalibrationError("the measuring plane's base-frame covariance must be a finite 3x3 positive "
                                   "semi-definite matrix (tilt a, tilt b, rad; offset, m)")
    for what, normal, offset, cov in views:
        n, c = np.asarray(normal, dtype=np.float64), np.asarray(cov, dtype=np.float64)
        if n.shape != (3,) or not np.all(np.isfinite(n)) or abs(float(np.linalg.norm(n)) - 1.0) > 1e-6:
            raise CalibrationError(f"{what}: the normal must be a finite unit 3-vector, got {n}")
        if not math.isfinite(offset) or c.shape != (4, 4) or not np.all(np.isfinite(c)):
            raise CalibrationError(f"{what}: needs a finite offset and a finite 4x4 (normal, offset) covariance")
    if not 0.0 < confidence < 1.0:
        raise CalibrationError(f"confidence must be in (0, 1), got {confidence}")
    if plate_sigma is None:
        return None
    sigma = np.asarray(plate_sigma, dtype=np.float64)
    if estimate_plate:
        raise CalibrationError("plate_sigma is the prior of a given plate: pass it with estimate_plate=False")
    if sigma.shape != (3,) or not np.all(np.isfinite(sigma)) or np.any(sigma <= 0):
        raise CalibrationError(f"plate_sigma must be 3 finite numbers > 0 (tilt a, tilt b, rad; offset, m), "
                               f"got {list(np.atleast_1d(sigma))}")
    return sigma


def _accuracy(arm_accuracy: ArmAccuracy | None) -> ArmAccuracy | None:
    """``arm_accuracy`` checked (finite, >= 0), None when it states no error."""
    if arm_accuracy is None:
        return None
    values = (arm_accuracy.position_m, arm_accuracy.rotation_rad, arm_accuracy.varying)
    if not all(isinstance(v, (int, float)) and math.isfinite(v) and v >= 0 for v in values):
        raise CalibrationError(f"the arm's accuracy and its varying share must be finite and >= 0, got {values}")
    return arm_accuracy if any(values[:2]) else None


def _oriented_model(observations: Sequence[PlaneObservation], camera: Pose, plate: Plane,
                    measuring: MeasuringPlaneView | None) -> FixedModel:
    """The model with the plate's and the measuring plane's normals toward the camera (as the views measure them).

    Raises:
        CalibrationError: A view whose measured normal opposes the prediction: the plate's other face.
    """
    r_x = camera.rotation_matrix

    def facing(obs: PlaneObservation, normal: FloatArray) -> float:
        return float((r_x.T @ obs.flange.rotation_matrix @ normal) @ obs.normal)  # predicted . measured

    if facing(observations[0], plate.normal) < 0:  # the residuals cannot tell a normal from its opposite
        plate = Plane(-plate.normal, -plate.offset_m)
    for k, obs in enumerate(observations):
        if facing(obs, plate.normal) < 0:
            raise CalibrationError(f"plate view {k + 1} sees the plate's other face (or the configured camera "
                                   "pose is far off): its two faces are different planes, show one face only")
    base = None
    if measuring is not None:
        base = measuring.plane_base
        if float((r_x @ measuring.normal) @ base.normal) < 0:
            base = Plane(-base.normal, -base.offset_m)
    return FixedModel(camera, plate, base)


def _solve(data: _Views, prior_info: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Levenberg-Marquardt from the configured values; the solution and every residual (data, then priors).

    ``prior_info``: per fitted parameter, ``1/sigma²`` of its prior at the configured value (0: none).
    """
    from scipy.optimize import least_squares

    has_prior = prior_info > 0
    root = np.sqrt(prior_info)

    def residuals(x: FloatArray) -> FloatArray:
        return np.concatenate([data(x), (x * root)[has_prior]])  # the priors' (value - configured) / sigma

    def residual_jacobian(x: FloatArray) -> FloatArray:
        return np.vstack([jacobian(data, x), np.diag(root)[has_prior]])

    fit = least_squares(residuals, np.zeros(len(prior_info)), jac=residual_jacobian, method="lm", xtol=1e-15,
                        ftol=1e-15)
    return np.asarray(fit.x, dtype=np.float64), np.asarray(fit.fun, dtype=np.float64)


def _arm_common_covariance(arm: ArmAccuracy, camera: Pose, flange_positions: FloatArray) -> FloatArray:
    """6x6 the arm's error common to the poses (a rigid turn about the poses' centre and a shift) puts on the camera.

    Seen through an arm that errs by ``D`` at every pose the camera is found at ``D⁻¹ X``: turned back by
    the turn, and moved by the turn times the lever from the poses' centre and back by the shift.
    """
    lever = camera.translation - flange_positions.mean(axis=0)  # from the poses' centre to the camera, m
    jac = np.zeros((6, 6))
    jac[:3, :3] = -np.eye(3)  # the camera turns back
    jac[3:, :3] = cross_matrix(lever)  # its translation moves by -dtheta x lever
    jac[3:, 3:] = -np.eye(3)  # and back by the shift
    var = np.concatenate([np.full(3, arm.rotation_rad**2 / 3.0), np.full(3, arm.position_m**2 / 3.0)])
    cov: FloatArray = (jac * var) @ jac.T
    return cov


__all__ = ["FIXED_PARAMETERS", "FixedCameraEstimate", "MeasuringPlaneView", "ViewResidual", "estimate_fixed_camera",
           "fixed_observability"]
