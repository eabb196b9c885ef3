"""The joint fit of a camera's systematic depth error with the plane in the base frame (:func:`fit_depthcal`).

Model (ADR 0056). The plane is fixed in the robot's base frame, ``n · x = h`` (unknown unit normal
``n`` and offset ``h``); the camera's pose in view ``i`` is ``C_i = F_i · M`` (the flange pose the arm
reported times the mount, optionally refined). A valid pixel's ray (the direction of its measured
point) meets the plane at a range ``t``; its true native value is the disparity ``f·B / Z`` (stereo,
``Z = t · ray_z``) or the range ``t`` (ToF), and what the camera should have measured is
:meth:`SystematicError.distort` of it. The residual, measured minus predicted, is whitened by the
model's noise (``disparity_noise_px``; ToF ``range_sigma_m`` at the point's range and incidence).
The problem and its Jacobian are :mod:`cellcal.core.depthcal.problem`'s.

Why it is determined: the arm moves the camera by known amounts, so between views at different
heights the true depths differ by known amounts while a scale error multiplies them; the plane seen
under different inclinations crosses every pixel at several depths, so an offset or a field fixed to
the pixels is told from the plane's height and tilt. The field's order is chosen by the residual
RMS of views held out of the fit (the lowest order within noise of the best,
:mod:`cellcal.core.depthcal.orders`); the final correction is refitted on every view. Covariance: the
Jacobian's, times chi-square per degree of freedom and the design effect of spatially correlated
residuals (as the full-frame fit, ADR 0028) when above 1, plus what the fit does not model (a field
left out, the arm's stated accuracy), unscaled.

How it stays cheap (ADR 0056, "Speed"): the solver (:mod:`cellcal.core.depthcal.solver`) builds the
normal equations directly from analytic columns; the robust pass runs on a strided subsample and only
tells the outliers and where to start; the lower field orders start from the highest's solution and
take one step; the fits on every view extend the training fits by the held-out views' columns alone.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from cellcal.core.depthcal.observability import GEOMETRY_LIMITS, Observability, analyse, fisher_covariance
from cellcal.core.depthcal.orders import OrderChoice, ProblemFactory, choose_order
from cellcal.core.depthcal.problem import FloatArray, _initial_plane, _Points, _Problem, _rms, _sample, _sq, _tangents
from cellcal.core.depthcal.result import DepthcalResult, ViewResidual
from cellcal.core.depthcal.solver import INLIER_SIGMAS, _evaluate, _extend, _Fit, _gauss_newton, _inliers, _noise
from cellcal.core.depthcal.view import DepthcalView
from cellcal.core.methods.fullframe.honesty import DEFF_SIGNIFICANCE, design_effect
from cellcal.devices.errors import ConfigError
from cellcal.devices.measurement import DEFAULT_ALLOWANCES, MeasurementModel
from cellcal.devices.pose import Pose
from cellcal.devices.systematic import SystematicError

if TYPE_CHECKING:
    from cellcal.core.handeye.estimator import ArmAccuracy

__all__ = ["DEFAULT_POINTS_PER_VIEW", "INLIER_SIGMAS", "MIN_VIEWS", "fit_depthcal"]

#: The fit's weak prior on each correction term, about 0: this many times its limit (the camera's allowance).
#: It changes nothing a plan sees (the data's sigma is far smaller) and keeps what it cannot see bounded.
PRIOR_ALLOWANCES = 10.0
#: Fewer views than this cannot separate the scale from the plane.
MIN_VIEWS = 3
#: Valid pixels a view gives the fit at most (a seeded sample): the scale's precision grows with them.
DEFAULT_POINTS_PER_VIEW = 16000
#: The robust pass (soft-L1, to tell the outliers) runs on a strided subsample of about this many points a view.
ROBUST_POINTS_PER_VIEW = 2000
_PLANE_NAMES = ["plane_tilt_a_rad", "plane_tilt_b_rad", "plane_offset_m"]
_MOUNT_NAMES = ["mount_rx_rad", "mount_ry_rad", "mount_rz_rad", "mount_tx_m", "mount_ty_m", "mount_tz_m"]


def fit_depthcal(views: Sequence[DepthcalView], *, mount: Pose, model: MeasurementModel,
                 field_orders: Sequence[int] = (0, 1, 2, 3), holdout_every: int = 4,
                 wiggle_period_m: float | None = None, estimate_mount: bool = False,
                 max_points_per_view: int = DEFAULT_POINTS_PER_VIEW, seed: int = 0,
                 arm_accuracy: ArmAccuracy | None = None) -> DepthcalResult:
    """Fit the camera's systematic depth error jointly with the plane in the base frame (module docstring).

    Args:
        views: Frames of the plane (as captured) with the flange poses the arm reported.
        mount: ``T_flange_camera``, the camera's mount (refined when ``estimate_mount``).
        model: The camera's measurement model (stereo / structured light: ``f·B`` and the disparity noise;
            ToF: the range noise law).
        field_orders: Image-field orders to try; held-out error picks one.
        holdout_every: Every ``holdout_every``-th view (the 4th, 8th, ...) is held out to choose the order
            and measure the error before and after.
        wiggle_period_m: ToF: the wiggling's period in range, m (None: no wiggling term).
        estimate_mount: Refine the mount in the same fit (6 more parameters).
        max_points_per_view: Valid pixels sampled per view (seeded).
        seed: Seed of the sampling.
        arm_accuracy: The arm's stated accuracy: what it does to the fit enters the intervals
            (:func:`~cellcal.core.depthcal.arm.arm_covariance`); None: the reported flanges taken as exact.

    Raises:
        ConfigError: Too few views, an unknown camera kind, no view to hold out, a view without the plane.
    """
    started = time.perf_counter()
    orders, held, train = _split_views(views, model, field_orders, holdout_every)
    stereo = model.triangulating
    period = float(wiggle_period_m or 0.0) if not stereo else 0.0
    kind = "stereo" if stereo else "tof"
    pts_all, points = _sample(views, model, max(orders), max_points_per_view, seed)
    flanges = [v.flange_pose for v in views]
    n0, h0 = _initial_plane(pts_all, points, flanges, mount)
    problem = _problems(model, flanges, mount, estimate_mount, period, n0)
    everything = list(range(len(views)))
    # --- the robust pass: the highest order on every view (tells the outliers, and where the fits start)
    prob_r = problem(max(orders), everything)
    x_r, inl, sigma_in = _robust_pass(prob_r, model, pts_all, h0)
    # --- held-out pass: each order fitted without the held-out views (from the robust solution), judged on them
    held_flanges = [flanges[i] for i in held]
    choice = choose_order(problem, orders, model, train=train, held=held, held_flanges=held_flanges, inliers=inl,
                          sigma=sigma_in, pts_all=pts_all, start=(prob_r, x_r))
    order = choice.order
    # --- the final correction on every view, and the uncorrected fit for the training views' "before",
    #     each its training fit extended by the held-out views
    prob = problem(order, everything)
    fit = _extend(prob, choice.fit, inl, sigma_in, held, held_flanges)
    prob_0 = problem(None, everything)
    fit_0 = _extend(prob_0, choice.fit_none, inl, sigma_in, held, held_flanges)
    rows = _rows(views, held, model, pts_all, choice, (prob, fit), (prob_0, fit_0))
    cov, factor, notes = _covariance(prob, fit, model, order, arm_accuracy)
    ng = prob.n_geometry
    full_cov = np.zeros((len(prob.template.names), len(prob.template.names)))
    full_cov[np.ix_(prob.free, prob.free)] = cov[ng:, ng:]
    correction = SystematicError.from_vector(kind, prob.vector(fit.x), field_order=order,  # type: ignore[arg-type]
                                             wiggle_period_m=period, covariance=full_cov)
    obs = _observability(prob, fit, model)
    if not obs.observable:
        notes.append("not seen by this plan: " + obs.message())
    mount_out = mount_cov = None
    if estimate_mount:
        mount_out = mount @ Pose.from_xyz_rotvec(fit.x[6:9], fit.x[3:6])
        mount_cov = cov[3:9, 3:9]
    return DepthcalResult(
        correction=correction, plane_normal_base=prob.normal(fit.x[:ng]), plane_offset_m=float(fit.x[2]),
        plane_covariance=cov[:3, :3], field_order=order, order_scores=choice.scores, views=rows,
        holdout_rms_before=choice.rms_before, holdout_rms_after=choice.rms_after, noise_only_rms=choice.noise_rms,
        observability=obs, mount=mount_out, mount_covariance=mount_cov, kind=kind, variance_factor=factor,
        n_points=int(fit.resid.size), elapsed_s=time.perf_counter() - started, notes=tuple(notes))


def _split_views(views: Sequence[DepthcalView], model: MeasurementModel, field_orders: Sequence[int],
                 holdout_every: int) -> tuple[list[int], list[int], list[int]]:
    """The field orders to try (ascending), the held-out views' and the training views' indices.

    Raises:
        ConfigError: An unknown camera kind, too few views, no field order, no view to hold out.
    """
    if model.kind not in ("stereo", "structured_light", "tof"):
        raise ConfigError(f"depthcal needs a stereo, structured_light or tof camera model, got {model.kind!r}",
                          key="camera.model.kind")
    if len(views) < MIN_VIEWS:
        raise ConfigError(f"needs at least {MIN_VIEWS} views at several heights, got {len(views)}",
                          key="depthcal.views")
    orders = sorted({int(o) for o in field_orders})
    if not orders:
        raise ConfigError("needs at least one field order", key="depthcal.field_orders")
    held = [i for i in range(len(views)) if holdout_every >= 2 and (i + 1) % holdout_every == 0]
    train = [i for i in range(len(views)) if i not in held]
    if not held or len(train) < MIN_VIEWS:
        raise ConfigError(f"holding out every {holdout_every}th of {len(views)} views leaves "
                          f"{len(held)} held out and {len(train)} to fit (needs >= 1 and >= {MIN_VIEWS})",
                          key="depthcal.holdout_every")
    return orders, held, train


def _problems(model: MeasurementModel, flanges: list[Pose], mount: Pose, estimate_mount: bool, period: float,
              n0: FloatArray) -> ProblemFactory:
    """The problem of a field order (None: no correction) on the named views.

    All share the plane's reference normal ``n0`` (the tilts are measured from it) and a weak prior on each
    correction term (:data:`PRIOR_ALLOWANCES` times its limit); the wiggling is fitted only with a period.
    """
    stereo = model.triangulating
    kind = "stereo" if stereo else "tof"
    e1, e2 = _tangents(n0)
    fb = model.fb_px_m if stereo else 1.0

    def problem(order: int | None, which: Sequence[int]) -> _Problem:
        tp = SystematicError(kind, wiggle_period_m=period, field_order=order or 0)   # type: ignore[arg-type]
        if order is None:
            free = np.zeros(0, dtype=np.intp)
        else:
            free = np.array([k for k, name in enumerate(tp.names)
                             if not (name.startswith("wiggle_") and period <= 0.0)], dtype=np.intp)
        prior = PRIOR_ALLOWANCES * np.array(_limits([tp.names[k] for k in free], model, stereo))
        return _Problem(stereo, fb, [flanges[i] for i in which], mount, estimate_mount, n0, e1, e2, tp, free,
                        prior)

    return problem


def _robust_pass(prob: _Problem, model: MeasurementModel, pts: _Points, h0: float
                 ) -> tuple[FloatArray, _Points, FloatArray]:
    """The robust (soft-L1) fit of ``prob`` on a strided subsample of ``pts``: its solution, the inliers, their noise.

    Its job is to tell the outliers (speckle, edges: beyond :data:`INLIER_SIGMAS` robust sigmas) and to start
    the plain fits near their solutions. Without a ToF noise law the noise is the residuals' MAD at the start.
    """
    no_law = not prob.stereo and model.range_sigma_m(1.0) is None
    stride = max(1, -(-pts.measured.size // (ROBUST_POINTS_PER_VIEW * len(pts.slices))))
    sub = pts.take(np.arange(pts.measured.size) % stride == 0)
    x0 = np.concatenate([[0.0, 0.0, h0], np.zeros(prob.n_geometry - 3), np.zeros(prob.free.size)])
    sigma_sub = _noise(prob, model, x0, sub, fallback=0.001)
    fallback = 0.001
    if no_law:
        r0 = sub.measured - prob.predicted(x0, sub)
        fallback = max(1.4826 * float(np.median(np.abs(r0 - np.median(r0)))), 1e-5)
        sigma_sub = np.full_like(sigma_sub, fallback)
    x_r, _, r_sub = _gauss_newton(prob, sub, sigma_sub, x0, robust=True, iterations=30)
    sigma_all = _noise(prob, model, x_r, pts, fallback=fallback)
    keep = _inliers((pts.measured - prob.predicted(x_r, pts)) / sigma_all, r_sub)
    return x_r, pts.take(keep), sigma_all[keep]


def _rows(views: Sequence[DepthcalView], held: list[int], model: MeasurementModel, pts: _Points,
          choice: OrderChoice, final: tuple[_Problem, _Fit], uncorrected: tuple[_Problem, _Fit]
          ) -> list[ViewResidual]:
    """Per view the residual RMS before and after the correction over its inliers, native unit and metres.

    A held-out view's from the fits without it (``choice``: a fair test); a training view's from the fits
    on every view, with the correction (``final``) and without (``uncorrected``), evaluated on ``pts``.
    """
    (prob, fit), (prob_0, fit_0) = final, uncorrected
    resid_f, sig_f, to_m_f = _evaluate(prob, model, fit.x, pts, float(np.median(fit.sigma)))
    resid_0, _, to_m_0 = _evaluate(prob_0, model, fit_0.x, pts, float(np.median(fit_0.sigma)))
    keep_f = _inliers(resid_f / sig_f)
    rows: list[ViewResidual] = []
    for i, view in enumerate(views):
        if i in held:
            s = choice.points.slices[held.index(i)]
            k = choice.keep[s]
            before, after = choice.resid_before[s][k], choice.resid_after[s][k]
            m_before, m_after = choice.to_m_before[s][k], choice.to_m_after[s][k]
        else:
            s = pts.slices[i]
            k = keep_f[s]
            before, after, m_before, m_after = resid_0[s][k], resid_f[s][k], to_m_0[s][k], to_m_f[s][k]
        rows.append(ViewResidual(view.name or f"view {i}", i in held, int(np.count_nonzero(k)), _rms(before),
                                 _rms(after), _rms(before * m_before), _rms(after * m_after)))
    return rows


def _covariance(prob: _Problem, fit: _Fit, model: MeasurementModel, order: int, arm: ArmAccuracy | None
                ) -> tuple[FloatArray, float, list[str]]:
    """The parameters' covariance (geometry, then the free terms), the factor the data's part was widened by, notes.

    The Jacobian's (the weak prior included), times chi-square per degree of freedom and the design effect
    of spatially correlated residuals when each is above 1; plus what the fit does not model
    (:func:`_unmodelled`), unscaled.
    """
    fisher = fit.fisher                                     # the data's alone: what the plan sees
    with_prior = fisher + np.diag(fit.prior)
    cov, _, _ = fisher_covariance(with_prior)
    dof = max(fit.resid.size - fisher.shape[0], 1)
    chi2 = _sq(fit.resid) / dof
    deff, se = design_effect(fit.resid.astype(np.float32), fit.pts.masks, fit.pts.shape)
    factor = max(1.0, chi2)
    notes = []
    if chi2 > 1.0 + 3.0 * math.sqrt(2.0 / dof):
        notes.append(f"residuals {math.sqrt(chi2):.2f}x the stated noise: intervals widened by that")
    if deff > 1.0 + DEFF_SIGNIFICANCE * se:
        factor *= deff
        notes.append(f"residuals correlated across neighbouring pixels (design effect {deff:.2f}): "
                     f"intervals widened by {math.sqrt(deff):.2f}x")
    unmodelled, said = _unmodelled(prob, fit, model, order, arm, h_inv=cov)
    cov = cov * factor + unmodelled   # unscaled: the data cannot tell them from the truth
    return cov, factor, notes + said


def _observability(prob: _Problem, fit: _Fit, model: MeasurementModel) -> Observability:
    """What the plan sees of each parameter: from the noise alone (the data's information, no prior) and the
    plan's spread of heights above the plane and inclinations to it."""
    ng = prob.n_geometry
    normal = prob.normal(fit.x[:ng])
    h = float(fit.x[2])
    poses = prob.camera_poses(fit.x[:ng])
    heights = np.array([float(normal @ o) - h for _, o in poses])
    incl = np.degrees(np.arccos(np.clip([-float(rot[:, 2] @ normal) for rot, _ in poses], -1.0, 1.0)))
    geo_names = _PLANE_NAMES + (_MOUNT_NAMES if prob.estimate_mount else [])
    all_names = geo_names + [prob.template.names[k] for k in prob.free]
    return analyse(fit.fisher, all_names, _limits(all_names, model, prob.stereo),
                   height_spread_m=float(np.ptp(heights)), inclination_spread_deg=float(np.ptp(incl)),
                   estimate_mount=prob.estimate_mount)


def _limits(names: Sequence[str], model: MeasurementModel, stereo: bool) -> list[float]:
    allow = model.allowance
    default = DEFAULT_ALLOWANCES["stereo" if stereo else "tof"]
    scale, offset, fld = (a if a > 0 else d for a, d in zip(allow, default, strict=True))
    out = []
    for name in names:
        if name in GEOMETRY_LIMITS:
            out.append(GEOMETRY_LIMITS[name])
        elif name in ("fb_error", "scale_error"):
            out.append(scale)
        elif name in ("disparity_offset_px", "offset_m"):
            out.append(offset)
        else:
            out.append(fld)
    return out


def _unmodelled(prob: _Problem, fit: _Fit, model: MeasurementModel, order: int, arm: ArmAccuracy | None,
                h_inv: FloatArray) -> tuple[FloatArray, list[str]]:
    """What the fit does not model, as covariance of its parameters, and the notes that say so.

    A field the held-out error could not tell from the noise (order < 2) is not gone: the camera's
    field allowance for the shapes left out (:mod:`cellcal.core.depthcal.leftover`); the arm's stated
    accuracy, the reported flanges being the camera's motion (:mod:`cellcal.core.depthcal.arm`).
    Both from one linearisation at the solution; ``h_inv`` is the normal matrix's inverse.
    """
    p = h_inv.shape[0]
    if arm is not None and arm.position_m <= 0.0 and arm.rotation_rad <= 0.0:
        arm = None
    leftover = order < 2 and model.allowance[2] > 0.0
    if arm is None and not leftover:
        return np.zeros((p, p)), []
    cols, pred = prob.columns(fit.x, fit.pts)
    jw = cols / fit.sigma                                  # (p, N) whitened d(predicted)/dx
    out, notes = np.zeros((p, p)), []
    if leftover:
        from cellcal.core.depthcal.leftover import leftover_field_covariance

        out += leftover_field_covariance(fit, model, order, jw, h_inv)
        notes.append(f"the image field of order > {order} was not fitted: the camera's field allowance is in "
                     "the intervals")
    if arm is not None:
        from cellcal.core.depthcal.arm import arm_covariance

        out += arm_covariance(prob, fit, arm, jw, pred, h_inv)
        notes.append(f"the arm's stated accuracy ({1000 * arm.position_m:.3g} mm, "
                     f"{math.degrees(arm.rotation_rad):.3g} deg RMS, {arm.source}) is in the "
                     "intervals: the reported flange poses are the camera's motion")
    return out, notes

