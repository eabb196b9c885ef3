"""Weighted least squares of the plane constraints: the mount and the base-frame plane with uncertainty.

Residuals are whitened by each pose's full-frame covariance plus the arm's read-back
noise (:func:`~cellcal.core.handeye.model.whitening`); ``scipy.optimize.least_squares``
finds the nine parameters minus the given ones held exact (given ones with a sigma are
fitted with that prior); the inverse of ``JᵀJ`` at the solution is their covariance,
scaled by chi2/dof when the residuals exceed the stated noise (:mod:`.noise`), and
intervals on ``translation_m`` / ``rpy_deg`` are propagated from it. The observability
check runs before the fit: an unobservable plan raises (ADR 0018, ADR 0030).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cellcal.core.geometry.planes import Plane
from cellcal.core.handeye.arm_trend import arm_trend_terms
from cellcal.core.handeye.given import check_given_sigma, given_notes
from cellcal.core.handeye.model import (
    MOUNT_ROTATION,
    MOUNT_TRANSLATION,
    PARAMETERS,
    PLANE_OFFSET,
    PLANE_TILT,
    PlaneModel,
    PlaneObservation,
    PlaneResiduals,
    arm_accuracy_covariance,
    stack_poses,
    whitening,
)
from cellcal.core.handeye.noise import MAX_INTERVAL_SCALE, NOISE_TEST_LEVEL, NoiseCheck, check_noise, scaled_covariance
from cellcal.core.handeye.observability import Observability, analyse
from cellcal.core.handeye.systematic import (
    GROUPS,
    Linearised,
    Shift,
    error_budget,
    pattern,
    systematic_note,
    systematic_terms,
)
from cellcal.devices.arm_model import UNSTATED_ARM_MODEL
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
        parameters: The 9 parameter steps from the configured values (given ones held exact 0).
        covariance: 9x9 covariance of ``parameters`` the intervals use: scaled by chi2/dof when
            ``noise.verdict`` is ``scaled``, with the given values' priors (rows/columns of
            given ones held exact 0).
        given: Names of the given parameters (held exact, or fitted with a prior when in ``given_sigma``).
        residuals: Per pose.
        chi2: Sum of the poses' chi2 plus the priors' terms; dof: residuals minus estimated parameters.
        observability: Rank, condition and unseen directions.
        confidence: Level of the intervals.
        noise: The chi2 test of the stated noise and the interval scale it implies.
        given_sigma: 1-sigma of the given values fitted with a prior, m or rad.
        absolute_covariance: ``covariance`` with the stated noise as it is (never larger than ``covariance``).
        arm_accuracy: The arm's stated absolute accuracy the weights and intervals include (None: none).
        systematic_covariance: 9x9 the camera's systematic allowance, common to the poses, adds to
            ``covariance`` and ``absolute_covariance`` (never scaled; None: no pose stated one).
        error_budget: The mount's error budget (:func:`~cellcal.core.handeye.systematic.error_budget`).
        systematic_note: What the allowance widened, in words ("" without it).
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
    noise: NoiseCheck
    given_sigma: Mapping[str, float] = field(default_factory=dict)
    absolute_covariance: FloatArray | None = None
    arm_accuracy: ArmAccuracy | None = None
    systematic_covariance: FloatArray | None = None
    error_budget: dict[str, Any] | None = None
    systematic_note: str = ""

    @property
    def z(self) -> float:
        """Half-width of the intervals in sigmas (Student-t when the scale came from the data)."""
        return self.noise.interval_z

    @property
    def interval_scale(self) -> float:
        """Factor the residuals put on the stated noise's 1-sigma (1 unless ``noise.verdict`` is ``scaled``)."""
        return self.noise.interval_scale

    @property
    def notes(self) -> tuple[str, ...]:
        """What the intervals rest on, in words: the noise test's finding and the given values."""
        note = self.noise.note()
        arm = [] if self.arm_accuracy is None else [self.arm_accuracy.note()]
        camera = [self.systematic_note] if self.systematic_note else []
        return (*camera, *arm, *([note] if note else []), *given_notes(self.given, self.given_sigma))

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
        absolute = self.covariance if self.absolute_covariance is None else self.absolute_covariance
        return {"chi2": self.chi2, "dof": self.dof, "chi2_per_dof": self.chi2 / self.dof if self.dof else None,
                "p_value": self.p_value, "given": list(self.given), "given_sigma": dict(self.given_sigma),
                "parameters": list(PARAMETERS), "covariance": self.covariance.tolist(),
                "covariance_absolute": absolute.tolist(), "interval_scale": self.interval_scale,
                "interval_z": self.z, "noise_model": self.noise.to_dict(), "notes": list(self.notes),
                **({} if self.arm_accuracy is None else {"arm_accuracy": self.arm_accuracy.to_dict()}),
                **({} if self.systematic_covariance is None else
                   {"covariance_systematic": self.systematic_covariance.tolist()})}


@dataclass(frozen=True)
class ArmAccuracy:
    """The arm's stated absolute accuracy as the hand-eye fit takes it (issue #39, ADR 0055).

    A real arm's error is smooth with the pose: over a plan it is mostly common to the poses, and
    varies from pose to pose by part of it, in step with the pose. All parts are isotropic with
    RMS length ``position_m`` and ``rotation_rad`` (1-sigma per axis: those over sqrt(3)). The
    common part is not in the residuals at all: in the flange frame it is a mount error, in the
    base frame a plane error, added to their covariance (:meth:`common_covariance`) and never
    scaled by chi2/dof. The part in step with the pose, ``trend`` times the accuracy, is a
    flange error linear in the pose (:mod:`cellcal.core.handeye.arm_trend`): common
    coefficients whose answers enter the intervals, never scaled, and which the chi2 test takes
    out. The rest, ``varying`` times it, is each pose's random flange error, propagated into its
    plane residual (:func:`~cellcal.core.handeye.model.arm_accuracy_covariance`): it weighs the
    poses and is in the chi2 test. ``trend = 0.5``, ``varying = 0.25``: what the sim's kinematic
    errors need on the hand-eye plan (ADR 0055 "The arm's error in step with the pose";
    ``benchmarks/handeye_arm_errors.py``).

    Attributes:
        position_m: RMS position error of a reported flange pose, m.
        rotation_rad: RMS orientation error, rad.
        source: Who stated it (``backend``, ``config``, ``sim``, ``recording ...``).
        varying: The part of it that varies at random from pose to pose, in the weights.
        trend: The part of it that varies in step with the pose (linear in it), common coefficients.
    """

    position_m: float
    rotation_rad: float
    source: str = "unstated"
    varying: float = 0.25
    trend: float = 0.5

    def common_covariance(self, mount: Pose, free: Sequence[int]) -> FloatArray:
        """9x9 covariance the error common to every pose puts on the estimated parameters (rows of ``free`` only).

        Common in the flange frame it is a mount error, exactly (``X' = D X``: the turn, and the turn
        times the mount's lever plus the shift); common in the base frame, the plane's tilt and offset.
        """
        var_r, var_t = self.rotation_rad**2 / 3.0, self.position_m**2 / 3.0
        t = np.asarray(mount.translation, dtype=np.float64)
        cross_t = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
        jac = np.zeros((6, 6))
        jac[:3, :3] = np.eye(3)  # the mount turns with the flange
        jac[3:, :3] = -cross_t  # its translation by dtheta x t
        jac[3:, 3:] = np.eye(3)  # and by the shift
        cov = np.zeros((len(PARAMETERS), len(PARAMETERS)))
        cov[:6, :6] = (jac * np.concatenate([np.full(3, var_r), np.full(3, var_t)])) @ jac.T
        cov[PLANE_TILT, PLANE_TILT] = np.eye(2) * var_r
        cov[PLANE_OFFSET, PLANE_OFFSET] = var_t
        keep = np.zeros(len(PARAMETERS), dtype=bool)
        keep[list(free)] = True
        cov[~keep, :] = 0.0
        cov[:, ~keep] = 0.0
        return cov

    def note(self) -> str:
        """One line for the intervals' notes."""
        return (f"the arm's absolute accuracy ({1000 * self.position_m:.3g} mm, "
                f"{math.degrees(self.rotation_rad):.3g} deg RMS, stated by {self.source}) is in the weights and the "
                "intervals: common to the poses in the mount and plane, half of it in step with the pose (a trend "
                "over the plan), a quarter at random per pose in the weights")

    def to_dict(self) -> dict[str, Any]:
        """JSON form (SI units)."""
        return {"position_m": self.position_m, "rotation_rad": self.rotation_rad, "source": self.source}


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


class _Problem(PlaneResiduals):
    """The whitened residual function of a set of observations over the free parameters."""

    def __init__(self, model: PlaneModel, observations: Sequence[PlaneObservation], free: Sequence[int],
                 arm_translation_sigma_m: float, arm_rotation_sigma_rad: float,
                 accuracy: ArmAccuracy | None = None) -> None:
        self.model = model
        self.observations = observations
        self.free = list(free)
        self.flanges = stack_poses([o.flange for o in observations])  # rotation matrices and translations
        lever = float(np.linalg.norm(model.nominal_mount.translation))
        mount = model.nominal_mount
        w = [whitening(o, arm_translation_sigma_m, arm_rotation_sigma_rad, lever,
                       None if accuracy is None else arm_accuracy_covariance(
                           o, mount, accuracy.varying * accuracy.position_m, accuracy.varying * accuracy.rotation_rad))
             for o in observations]
        self.bases = np.stack([b for b, _ in w])  # (N, 3, 2) tangent bases of the measured normals
        self.whiten = np.stack([m for _, m in w])  # (N, 3, 3) inverse Cholesky factors
        self.normals = np.stack([o.normal for o in observations])
        self.offsets = np.array([o.offset_m for o in observations])


def _setup(observations: Sequence[PlaneObservation], nominal_mount: Pose, nominal_plane: Plane,
           given: Sequence[str], arm_translation_sigma_m: float, arm_rotation_sigma_rad: float,
           accuracy: ArmAccuracy | None = None) -> tuple[PlaneModel, _Problem, FloatArray]:
    """The model, the residual function and the normals in the flange frame (N, 3) of a problem.

    Raises:
        CalibrationError: Fewer than 2 observations, or an unknown given name.
    """
    if len(observations) < 2:
        raise CalibrationError(f"hand-eye estimation needs at least 2 poses, got {len(observations)}")
    unknown = sorted(set(given) - set(PARAMETERS))
    if unknown:
        raise CalibrationError(f"unknown given parameter(s) {unknown}; expected some of {', '.join(PARAMETERS)}")
    # the configured normal is turned toward the cameras by the first measured normal (toward its camera), seen in
    # the base frame through the configured mount: not by the camera's configured position, which is on the wrong
    # side of a plane configured off by more than the camera's distance; the residuals cannot tell a normal from
    # its opposite, so a wrong side would converge to the mirrored mount
    first = observations[0]
    measured = (first.flange @ nominal_mount).rotation_matrix @ np.asarray(first.normal, dtype=np.float64)
    if float(measured @ nominal_plane.normal) < 0:
        nominal_plane = Plane(-nominal_plane.normal, -nominal_plane.offset_m)  # normal toward the camera side
    model = PlaneModel(nominal_mount, nominal_plane)
    free = [i for i, name in enumerate(PARAMETERS) if name not in given]
    problem = _Problem(model, observations, free, arm_translation_sigma_m, arm_rotation_sigma_rad, accuracy)
    normal = np.array(nominal_plane.normal)
    normals_flange = np.stack([o.flange.rotation.inv().apply(normal) for o in observations])  # u_i
    return model, problem, normals_flange


def observability(observations: Sequence[PlaneObservation], nominal_mount: Pose, nominal_plane: Plane, *,
                  given: Sequence[str] = (), arm_translation_sigma_m: float = 2.5e-5,
                  arm_rotation_sigma_rad: float = 0.0, arm_accuracy: ArmAccuracy | None = None) -> Observability:
    """What the observations can determine, at the configured values (no fit).

    Raises:
        CalibrationError: Fewer than 2 observations, or an unknown given name.
    """
    _, problem, normals_flange = _setup(observations, nominal_mount, nominal_plane, given,
                                        arm_translation_sigma_m, arm_rotation_sigma_rad, _accuracy(arm_accuracy))
    return analyse(jacobian(problem, np.zeros(len(problem.free))), problem.free, normals_flange)


def estimate_mount(observations: Sequence[PlaneObservation], nominal_mount: Pose, nominal_plane: Plane, *,
                   given: Sequence[str] = (), given_sigma: Mapping[str, float] | None = None,
                   arm_translation_sigma_m: float = 2.5e-5, arm_rotation_sigma_rad: float = 0.0,
                   confidence: float = 0.95, noise_test_level: float = NOISE_TEST_LEVEL,
                   max_interval_scale: float = MAX_INTERVAL_SCALE,
                   arm_accuracy: ArmAccuracy | None = None) -> HandEyeEstimate:
    """Estimate the mount and the base-frame plane from plane observations.

    Args:
        observations: One per pose (:func:`~cellcal.core.handeye.model.observation_from_pose`).
        nominal_mount: The configured ``T_flange_camera`` (start, and value of given mount parameters).
        nominal_plane: The configured base-frame plane (likewise); its normal is turned toward the cameras.
        given: Parameter names (:data:`PARAMETERS`) taken from the configured values instead of estimated.
        given_sigma: 1-sigma of some given values (m for translations and the plane offset, rad for
            turns and tilts): those are fitted with a Gaussian prior at the configured value; the
            others are held exact.
        arm_translation_sigma_m: 1-sigma of the arm's position read-back per axis, m.
        arm_rotation_sigma_rad: 1-sigma of its orientation read-back per axis, rad.
        confidence: Level of the intervals.
        noise_test_level: Level of each tail of the chi2 test of the stated noise.
        max_interval_scale: Largest factor the residuals may put on the stated noise's 1-sigma.
        arm_accuracy: The arm's stated absolute accuracy (:class:`ArmAccuracy`): each pose's flange
            errs at random by it, in the weights and the intervals (None or zeros: the read-back
            noise alone, as before issue #39).

    Raises:
        CalibrationError: Fewer than 2 observations, an unknown given name, or a sigma for a
            parameter that is not given (or not > 0).
        CalibrationQualityError: Gate ``observability``: the plan leaves a parameter unobservable;
            the message names it and the poses that would fix it. Gate ``noise_model``: the
            residuals are more than ``max_interval_scale`` times the stated noise.
    """
    sigmas = check_given_sigma(given, given_sigma or {})
    accuracy = _accuracy(arm_accuracy)
    model, problem, normals_flange = _setup(observations, nominal_mount, nominal_plane, given,
                                            arm_translation_sigma_m, arm_rotation_sigma_rad, accuracy)
    free = problem.free
    seen = analyse(jacobian(problem, np.zeros(len(free))), free, normals_flange)  # structural: before any fit
    if not seen.observable:
        raise CalibrationQualityError("observability", seen.rank, seen.n_parameters, seen.message())
    # the fitted parameters: the free ones and the given ones with a prior
    fitted = [i for i, name in enumerate(PARAMETERS) if i in free or name in sigmas]
    data = problem if len(fitted) == len(free) else _Problem(model, observations, fitted, arm_translation_sigma_m,
                                                              arm_rotation_sigma_rad, accuracy)
    prior_info = np.array([0.0 if i in free else sigmas[PARAMETERS[i]] ** -2 for i in fitted])  # 1/sigma²
    fit = _solve(data, prior_info)  # each pose weighed by its fit's noise (and the arm's per-pose part)
    x = fit.x
    jac = jacobian(data, x)
    info_data, info_prior = jac.T @ jac, np.diag(prior_info)
    lin = Linearised(fitted, jac, _inverse(info_data + info_prior), data.bases, data.whiten)
    # the camera's systematic terms: each one coefficient common to the poses (ADR 0059 "Amended")
    terms = systematic_terms(observations)
    responses = {key: lin.response(shifts) for key, shifts in terms.items()}  # first order, at the solution
    trend = {} if accuracy is None or accuracy.trend <= 0.0 else arm_trend_terms(
        observations, model.nominal_mount, accuracy.trend * accuracy.position_m, accuracy.trend * accuracy.rotation_rad)
    chi2, dof, worst = _noise_test_residuals(data, x, fit.fun, prior_info, {**terms, **trend})
    k = int(np.argmax([r.chi2 for r in worst]))
    noise = check_noise(chi2, dof, confidence=confidence, level=noise_test_level,
                        max_interval_scale=max_interval_scale,
                        detail=f"largest residual at pose {k + 1} (chi2 {worst[k].chi2:.4g})")
    absolute = _full_covariance(fitted, scaled_covariance(info_data, info_prior, 1.0))  # the stated noise
    cov = _full_covariance(fitted, scaled_covariance(info_data, info_prior, noise.interval_scale))  # Birge-scaled
    if accuracy is not None:  # the arm's error common to the poses: not in the residuals, never scaled
        common = accuracy.common_covariance(model.nominal_mount, free)
        absolute, cov = absolute + common, cov + common
    trend_cov = None if accuracy is None else _trend_covariance(lin, trend)
    if trend_cov is not None:  # the arm's error in step with the pose: common coefficients too, never scaled
        absolute, cov = absolute + trend_cov, cov + trend_cov
    sys_cov, note = None, ""
    if responses:  # the camera's allowance: not in the weights, never scaled
        sys_cov = sum((np.outer(d, d) for d in responses.values()), np.zeros((len(PARAMETERS), len(PARAMETERS))))
        note = systematic_note(cov, cov + sys_cov, observations, len(responses))
        absolute, cov = absolute + sys_cov, cov + sys_cov
    groups = {name: sum((np.outer(d, d) for key, d in responses.items() if member(key)), np.zeros((9, 9)))
              for name, member in GROUPS.items() if any(member(key) for key in responses)}
    params = data.full(x)
    mount = model.mount(params)
    budget = error_budget(lin, observations, mount, groups, _arm_budget(lin, model, observations, free, accuracy,
                                                                                trend_cov))
    on_free = [fitted.index(i) for i in free]  # the free parameters' columns, for the observability report
    return HandEyeEstimate(mount, model.plane(params), params, cov, tuple(given), worst, chi2, dof,
                           analyse(jac[:, on_free], free, normals_flange), confidence, noise, sigmas, absolute,
                           accuracy, sys_cov, budget, note)


def _noise_test_residuals(data: _Problem, x: FloatArray, fun: FloatArray, prior_info: FloatArray,
                          terms: Mapping[str, Sequence[tuple[FloatArray, float]]]
                          ) -> tuple[float, int, tuple[PoseResidual, ...]]:
    """chi2, dof and per-pose residuals of the test of the stated noise.

    Without systematic terms: the fit's own. With them, the residuals are tested after the camera's
    common terms: the fit re-solved with one coefficient per term, common to the poses, under the
    prior N(0, 1) (generalised least squares with the allowance's covariance across the poses), so
    that a systematic pattern the mount and plane cannot absorb is not taken for noise. The per-pose
    angle and offset are those of the estimate; their chi2 is what is left after the common terms.
    """
    if not terms:
        return float(fun @ fun), len(fun) - len(x), _residuals(data, x)
    patterns = np.column_stack([pattern(data.bases, data.whiten, s) for s in terms.values()])
    joint = _solve(data, prior_info, patterns)
    n_fit = len(x)
    left = (data(joint.x[:n_fit]) + patterns @ joint.x[n_fit:]).reshape(-1, 3)
    plain = _residuals(data, x)
    worst = tuple(dataclasses.replace(r, chi2=float(w @ w)) for r, w in zip(plain, left, strict=True))
    return float(joint.fun @ joint.fun), len(joint.fun) - len(joint.x), worst


def _inverse(h: FloatArray) -> FloatArray:
    """``h⁻¹`` (the pseudo-inverse when singular)."""
    try:
        out = np.linalg.inv(h)
    except np.linalg.LinAlgError:
        out = np.linalg.pinv(h)
    return np.asarray(out, dtype=np.float64)


def _trend_covariance(lin: Linearised, trend: Mapping[str, Sequence[Shift]]) -> FloatArray:
    """9x9 covariance of the parameters from the arm's trend coefficients (:func:`arm_trend_terms`), unscaled."""
    out = np.zeros((len(PARAMETERS), len(PARAMETERS)))
    for shifts in trend.values():
        d = lin.response(shifts)
        out += np.outer(d, d)
    return out


def _arm_budget(lin: Linearised, model: PlaneModel, observations: Sequence[PlaneObservation], free: Sequence[int],
                accuracy: ArmAccuracy | None, trend_cov: FloatArray | None = None) -> FloatArray:
    """9x9 covariance the arm's stated accuracy (or the unstated default) puts on the parameters.

    Its common part as :meth:`ArmAccuracy.common_covariance`, its trend's coefficients' answers
    (``trend_cov`` when the estimate has them already), its random part propagated from each pose.
    """
    arm = accuracy or ArmAccuracy(UNSTATED_ARM_MODEL.accuracy_m, UNSTATED_ARM_MODEL.accuracy_rad, "unstated")
    mount = model.nominal_mount
    per_pose = [arm_accuracy_covariance(o, mount, arm.varying * arm.position_m, arm.varying * arm.rotation_rad)
                for o in observations]
    if trend_cov is None:
        trend_cov = _trend_covariance(lin, arm_trend_terms(observations, mount, arm.trend * arm.position_m,
                                                           arm.trend * arm.rotation_rad))
    out: FloatArray = arm.common_covariance(mount, free) + lin.propagate(per_pose) + trend_cov
    return out


def _accuracy(arm_accuracy: ArmAccuracy | None) -> ArmAccuracy | None:
    """``arm_accuracy`` checked (finite, >= 0), None when it states no error."""
    if arm_accuracy is None:
        return None
    values = (arm_accuracy.position_m, arm_accuracy.rotation_rad)
    if not all(isinstance(v, (int, float)) and math.isfinite(v) and v >= 0 for v in values):
        raise CalibrationError(f"the arm's accuracy must be finite and >= 0, got {values}")
    return arm_accuracy if any(values) else None


def _solve(data: _Problem, prior_info: FloatArray, patterns: FloatArray | None = None) -> Any:
    """Levenberg-Marquardt from the configured values: the whitened data residuals and the priors'.

    Args:
        data: The residual function of the fitted parameters.
        prior_info: Per fitted parameter, the information ``1/sigma²`` of its prior at the
            configured value (0: no prior, a free parameter).
        patterns: (3N, K) the whitened residuals' change per unit of each systematic term's common
            coefficient (fitted after the parameters, each with the prior N(0, 1)); None: none.

    Returns:
        scipy's ``OptimizeResult`` (``x``: the parameter steps then the coefficients, ``fun``: every residual).
    """
    from scipy.optimize import least_squares

    s = np.zeros((len(data.observations) * 3, 0)) if patterns is None else patterns
    k, n_sys = len(prior_info), s.shape[1]

    def residuals(z: FloatArray) -> FloatArray:
        """Whitened data residuals, then the priors' (value - configured) / sigma, then the coefficients'."""
        x = z[:k]
        return np.concatenate([data(x) + s @ z[k:], (x * np.sqrt(prior_info))[prior_info > 0], z[k:]])

    def residual_jacobian(z: FloatArray) -> FloatArray:
        priors = np.diag(np.sqrt(prior_info))[prior_info > 0]
        return np.vstack([np.hstack([jacobian(data, z[:k]), s]),
                          np.hstack([priors, np.zeros((priors.shape[0], n_sys))]),
                          np.hstack([np.zeros((n_sys, k)), np.eye(n_sys)])])

    return least_squares(residuals, np.zeros(k + n_sys), jac=residual_jacobian, method="lm", xtol=1e-15,
                         ftol=1e-15)


def _full_covariance(fitted: Sequence[int], cov_fitted: FloatArray) -> FloatArray:
    """The covariance of the fitted parameters placed in the 9x9 of all (zero for those held exact)."""
    cov = np.zeros((len(PARAMETERS), len(PARAMETERS)))
    cov[np.ix_(fitted, fitted)] = cov_fitted
    return cov


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


__all__ = ["ArmAccuracy", "HandEyeEstimate", "PoseResidual", "estimate_mount", "jacobian", "observability",
           "rpy_with_sigma_deg"]
