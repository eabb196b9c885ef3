"""The joint fit of a camera's systematic depth error with the plane in the base frame (:func:`fit_depthcal`).

Model (ADR 0056). The plane is fixed in the robot's base frame, ``n · x = h`` (unknown unit normal
``n`` and offset ``h``); the camera's pose in view ``i`` is ``C_i = F_i · M`` (the flange pose the arm
reported times the mount, optionally refined). A valid pixel's ray (the direction of its measured
point) meets the plane at a range ``t``; its true native value is the disparity ``f·B / Z`` (stereo,
``Z = t · ray_z``) or the range ``t`` (ToF), and what the camera should have measured is
:meth:`SystematicError.distort` of it. The residual, measured minus predicted, is whitened by the
model's noise (``disparity_noise_px``; ToF ``range_sigma_m`` at the point's range and incidence).

Why it is determined: the arm moves the camera by known amounts, so between views at different
heights the true depths differ by known amounts while a scale error multiplies them; the plane seen
under different inclinations crosses every pixel at several depths, so an offset or a field fixed to
the pixels is told from the plane's height and tilt. The field's order is chosen by the residual
RMS of views held out of the fit (the lowest order within noise of the best); the final correction
is refitted on every view. Covariance: the Jacobian's, times chi-square per degree of freedom and the
design effect of spatially correlated residuals (as the full-frame fit, ADR 0028) when above 1.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cellcal.core.depthcal.observability import GEOMETRY_LIMITS, analyse, fisher_covariance
from cellcal.core.depthcal.result import DepthcalResult, ViewResidual
from cellcal.core.depthcal.view import DepthcalView
from cellcal.core.methods.fullframe.honesty import DEFF_SIGNIFICANCE, design_effect
from cellcal.devices.errors import ConfigError
from cellcal.devices.measurement import DEFAULT_ALLOWANCES, MeasurementModel
from cellcal.devices.pose import Pose
from cellcal.devices.systematic import SystematicError, field_basis, normalised_pixels

__all__ = ["INLIER_SIGMAS", "MIN_VIEWS", "fit_depthcal"]

FloatArray = NDArray[np.float64]
#: Points farther than this many (robust) sigmas from the robust fit are outliers (speckle, edges).
INLIER_SIGMAS = 5.0
#: Soft-L1 scale of the robust pass, in sigmas.
ROBUST_SCALE = 3.0
#: The fit's weak prior on each correction term, about 0: this many times its limit (the camera's allowance).
#: It changes nothing a plan sees (the data's sigma is far smaller) and keeps what it cannot see bounded.
PRIOR_ALLOWANCES = 10.0
#: Fewer views than this cannot separate the scale from the plane.
MIN_VIEWS = 3
#: Steps of the central differences for the geometry's columns (rad, m).
_STEP_ANGLE = 1e-6
_STEP_LENGTH = 1e-6
_PLANE_NAMES = ["plane_tilt_a_rad", "plane_tilt_b_rad", "plane_offset_m"]
_MOUNT_NAMES = ["mount_rx_rad", "mount_ry_rad", "mount_rz_rad", "mount_tx_m", "mount_ty_m", "mount_tz_m"]


@dataclass
class _Points:
    """The sampled points of a set of views, stacked."""

    ray: FloatArray            # (N, 3) unit rays, camera frame
    u: FloatArray
    v: FloatArray
    measured: FloatArray       # native value, px or m
    basis: FloatArray          # (N, n_field) field monomials at the chosen order
    slices: list[slice]        # per view
    masks: list[NDArray[np.bool_]]   # per view, flat pixel mask of the sample
    shape: tuple[int, int]

    def subset(self, views: Sequence[int]) -> _Points:
        idx = np.concatenate([np.arange(self.slices[i].start, self.slices[i].stop) for i in views])
        slices, start = [], 0
        for i in views:
            n = self.slices[i].stop - self.slices[i].start
            slices.append(slice(start, start + n))
            start += n
        return _Points(self.ray[idx], self.u[idx], self.v[idx], self.measured[idx], self.basis[idx], slices,
                       [self.masks[i] for i in views], self.shape)

    def take(self, keep: NDArray[np.bool_]) -> _Points:
        """Only the points where ``keep`` (the views' masks follow)."""
        slices, masks, start = [], [], 0
        for s, m in zip(self.slices, self.masks, strict=True):
            k = keep[s]
            n = int(np.count_nonzero(k))
            slices.append(slice(start, start + n))
            start += n
            mm = m.copy()
            mm[np.flatnonzero(m)[~k]] = False
            masks.append(mm)
        return _Points(self.ray[keep], self.u[keep], self.v[keep], self.measured[keep], self.basis[keep], slices,
                       masks, self.shape)


@dataclass
class _Problem:
    """What one least-squares fit needs: the kind, the poses, which correction terms are free."""

    stereo: bool
    fb: float
    flanges: list[Pose]
    mount: Pose
    estimate_mount: bool
    n0: FloatArray             # the plane normal the tilt angles are measured from
    e1: FloatArray
    e2: FloatArray
    template: SystematicError  # kind, field order and wiggle period of the correction
    free: NDArray[np.intp]     # indices of the correction's vector that are fitted
    prior: FloatArray          # per free term, a weak prior's 1-sigma about 0 (keeps what a plan cannot see bounded)

    @property
    def n_geometry(self) -> int:
        return 3 + (6 if self.estimate_mount else 0)

    def normal(self, g: FloatArray) -> FloatArray:
        n = self.n0 + g[0] * self.e1 + g[1] * self.e2
        out: FloatArray = n / np.linalg.norm(n)
        return out

    def camera_poses(self, g: FloatArray) -> list[tuple[FloatArray, FloatArray]]:
        """Per view ``(R_base_camera, origin)`` for geometry ``g``."""
        mount = self.mount
        if self.estimate_mount:
            mount = mount @ Pose.from_xyz_rotvec(g[6:9], g[3:6])
        out = []
        for f in self.flanges:
            c = f @ mount
            out.append((c.rotation_matrix, np.asarray(c.translation, dtype=np.float64)))
        return out

    def true_values(self, g: FloatArray, pts: _Points) -> tuple[FloatArray, FloatArray, FloatArray]:
        """True native value, range along the ray (m) and cos of incidence, per point."""
        n = self.normal(g)
        h = float(g[2])
        t = np.empty(pts.ray.shape[0])
        cos = np.empty_like(t)
        for s, (rot, origin) in zip(pts.slices, self.camera_poses(g), strict=True):
            nd = np.einsum("ij,j->i", pts.ray[s], rot.T @ n)   # n · (R ray)
            nd = np.minimum(nd, -1e-6)              # the ray must go towards the plane
            t[s] = (h - float(n @ origin)) / nd
            cos[s] = -nd
        t = np.maximum(t, 1e-4)
        true = self.fb / (t * pts.ray[:, 2]) if self.stereo else t
        return true, t, cos

    def design(self, true: FloatArray, pts: _Points) -> FloatArray:
        """d(measured)/d(correction vector): head columns from the true values, the field's from the basis."""
        tp = self.template
        if self.stereo:
            head = np.column_stack([true, np.ones_like(true)])
        else:
            if tp.wiggle_period_m > 0.0:
                phase = 2.0 * math.pi * true / tp.wiggle_period_m
                cos, sin = np.cos(phase), np.sin(phase)
            else:
                cos = sin = np.zeros_like(true)
            head = np.column_stack([true, np.ones_like(true), cos, sin])
        return np.hstack([head, pts.basis[:, :tp.field_order and len(tp.field_coeffs)]])

    def vector(self, x: FloatArray) -> FloatArray:
        """The correction's full vector from the fitted parameters (fixed terms 0)."""
        c = np.zeros(len(self.template.names))
        c[self.free] = x[self.n_geometry:]
        return c

    def predicted(self, x: FloatArray, pts: _Points, field: FloatArray | None = None) -> FloatArray:
        """What the camera should measure (``distort`` of the true value), per point; ``field``: its image field."""
        true, _, _ = self.true_values(x[:self.n_geometry], pts)
        c = self.vector(x)
        out: FloatArray = true * (1.0 + c[0]) + c[1]
        head = 2
        if not self.stereo:
            head = 4
            if self.template.wiggle_period_m > 0.0 and (c[2] or c[3]):
                phase = (2.0 * math.pi / self.template.wiggle_period_m) * true
                out += c[2] * np.cos(phase) + c[3] * np.sin(phase)
        if c.size > head:
            out += np.einsum("ij,j->i", pts.basis[:, :c.size - head], c[head:]) if field is None else field
        return out


def _sample(views: Sequence[DepthcalView], model: MeasurementModel, order: int, max_points: int,
            seed: int) -> _Points:
    rng = np.random.default_rng(seed)
    rays, us, vs, meas, masks, slices = [], [], [], [], [], []
    start = 0
    shape = (views[0].frame.intrinsics.height, views[0].frame.intrinsics.width)
    for k, view in enumerate(views):
        fr = view.frame
        intr = fr.intrinsics
        xyz = fr.xyz.reshape(-1, 3).astype(np.float64)
        dist = fr.distance.reshape(-1).astype(np.float64)
        ok = fr.valid.reshape(-1) & np.all(np.isfinite(xyz), axis=1) & (xyz[:, 2] > 0) & np.isfinite(dist)
        idx = np.flatnonzero(ok)
        if idx.size < 50:
            raise ConfigError(f"view {view.name or k}: {idx.size} valid pixels, too few to see the plane",
                              key="depthcal.views")
        if idx.size > max_points:
            idx = np.sort(rng.choice(idx, size=max_points, replace=False))
        p = xyz[idx]
        rays.append(p / np.linalg.norm(p, axis=1)[:, None])
        u, v = normalised_pixels(intr.width, intr.height, intr.cx, intr.cy)
        us.append(u.reshape(-1)[idx])
        vs.append(v.reshape(-1)[idx])
        meas.append(model.fb_px_m / p[:, 2] if model.triangulating else dist[idx])
        mask = np.zeros(ok.size, dtype=bool)
        mask[idx] = True
        masks.append(mask)
        slices.append(slice(start, start + idx.size))
        start += idx.size
    u_all, v_all = np.concatenate(us), np.concatenate(vs)
    return _Points(np.concatenate(rays), u_all, v_all, np.concatenate(meas), field_basis(u_all, v_all, order),
                   slices, masks, shape)


def _initial_plane(views: Sequence[DepthcalView], mount: Pose) -> tuple[FloatArray, float]:
    """A plane through the measured points in the base frame (trimmed least squares), normal towards the cameras."""
    pts = []
    for view in views:
        xyz = view.frame.xyz.reshape(-1, 3).astype(np.float64)
        ok = view.frame.valid.reshape(-1) & np.all(np.isfinite(xyz), axis=1)
        sample = xyz[ok][:: max(1, int(np.count_nonzero(ok)) // 2000)]
        pts.append((view.flange_pose @ mount).apply(sample))
    p = np.concatenate(pts)
    keep = np.ones(len(p), dtype=bool)
    for _ in range(4):
        c = p[keep].mean(axis=0)
        _, _, vt = np.linalg.svd(p[keep] - c, full_matrices=False)
        n = vt[2]
        r = (p - c) @ n
        mad = float(np.median(np.abs(r[keep] - np.median(r[keep])))) + 1e-9
        keep = np.abs(r - np.median(r[keep])) < 4.0 * 1.4826 * mad
    origin = np.asarray((views[0].flange_pose @ mount).translation)
    if float((origin - c) @ n) < 0:
        n = -n
    return n, float(n @ c)


def _tangents(n: FloatArray) -> tuple[FloatArray, FloatArray]:
    ref = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = ref - n * float(ref @ n)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(n, e1)


@dataclass
class _Fit:
    x: FloatArray
    pts: _Points               # the inliers
    sigma: FloatArray          # their noise, native unit
    jac: FloatArray            # whitened Jacobian at x over the inliers
    resid: FloatArray          # whitened residuals of the inliers
    prior_jac: FloatArray      # the prior's rows of the Jacobian


def _residual_fn(prob: _Problem, pts: _Points, sigma: FloatArray
                 ) -> tuple[Callable[[FloatArray], FloatArray], Callable[[FloatArray], FloatArray]]:
    ng = prob.n_geometry
    steps = np.array([_STEP_ANGLE, _STEP_ANGLE, _STEP_LENGTH] + [_STEP_ANGLE] * 3 + [_STEP_LENGTH] * 3)[:ng]

    def fun(x: FloatArray) -> FloatArray:
        out: FloatArray = np.concatenate([(pts.measured - prob.predicted(x, pts)) / sigma, x[ng:] / prob.prior])
        return out

    def jac(x: FloatArray) -> FloatArray:
        true, _, _ = prob.true_values(x[:ng], pts)
        cols = [-(prob.design(true, pts)[:, prob.free]) / sigma[:, None]]
        geo = np.empty((pts.measured.size, ng))
        field = np.zeros(pts.measured.size)   # the field does not move with the geometry: left out of the differences
        for k in range(ng):
            xp, xm = x.copy(), x.copy()
            xp[k] += steps[k]
            xm[k] -= steps[k]
            diff = prob.predicted(xp, pts, field) - prob.predicted(xm, pts, field)
            geo[:, k] = -diff / (2 * steps[k]) / sigma
        rows = np.hstack([np.zeros((prob.free.size, ng)), np.diag(1.0 / prob.prior)])
        return np.vstack([np.hstack([geo, *cols]), rows])

    return fun, jac


def _noise(prob: _Problem, model: MeasurementModel, x: FloatArray, pts: _Points, fallback: float) -> FloatArray:
    """Per point noise 1-sigma in the native unit (stereo: constant; ToF: the model's law at range and incidence)."""
    if prob.stereo:
        return np.full(pts.measured.size, model.disparity_noise_px)
    _, t, cos = prob.true_values(x[:prob.n_geometry], pts)
    sig = model.range_sigma_m(t, cos)
    if sig is None:
        return np.full(pts.measured.size, fallback)
    return np.maximum(np.asarray(sig, dtype=np.float64), 1e-6)


def _gauss_newton(fun: Callable[[FloatArray], FloatArray], jac: Callable[[FloatArray], FloatArray], x: FloatArray,
                  robust: bool, iterations: int) -> FloatArray:
    """Gauss-Newton on the normal equations (the problem is linear in the correction, nearly so in the plane).

    ``robust``: iteratively reweighted with soft-L1 weights of scale :data:`ROBUST_SCALE` (speckle and
    edges lose their pull). Singular directions (a plan that cannot see a parameter) get the minimum-norm
    step. A step that raises the cost is halved.
    """
    def cost(r: FloatArray) -> float:
        if robust:
            k = ROBUST_SCALE
            return float(np.sum(2.0 * k * k * (np.sqrt(1.0 + (r / k) ** 2) - 1.0)))
        return float(r @ r)

    r = fun(x)
    c = cost(r)
    for _ in range(iterations):
        j = jac(x)
        w = 1.0 / np.sqrt(1.0 + (r / ROBUST_SCALE) ** 2) if robust else np.ones_like(r)
        jw = j * w[:, None]
        # einsum, not BLAS: OpenBLAS threads on a tall, thin product lose more than they gain on a busy machine
        a = np.einsum("ij,ik->jk", j, jw)
        b = np.einsum("ij,i->j", jw, r)
        d = np.sqrt(np.maximum(np.diag(a), 1e-300))
        step = -np.linalg.lstsq(a / np.outer(d, d), b / d, rcond=1e-12)[0] / d
        for _half in range(8):
            r_new = fun(x + step)
            c_new = cost(r_new)
            if c_new <= c:
                break
            step = step / 2.0
        else:
            break
        x = x + step
        done = c - c_new <= 1e-10 * max(c, 1e-300)
        r, c = r_new, c_new
        if done:
            break
    return x


def _solve(prob: _Problem, model: MeasurementModel, pts: _Points, x0: FloatArray) -> _Fit:
    """Robust pass (soft-L1 weights) on every point, then a plain fit on the inliers."""
    sigma = _noise(prob, model, x0, pts, fallback=0.001)
    if not prob.stereo and model.range_sigma_m(1.0) is None:
        r0 = pts.measured - prob.predicted(x0, pts)
        sigma = np.full_like(sigma, max(1.4826 * float(np.median(np.abs(r0 - np.median(r0)))), 1e-5))
    fun, jac = _residual_fn(prob, pts, sigma)
    x = _gauss_newton(fun, jac, x0, robust=True, iterations=30)
    r = fun(x)[:pts.measured.size]
    scale = max(1.4826 * float(np.median(np.abs(r))), 1.0)
    keep = np.abs(r) < INLIER_SIGMAS * scale
    inl = pts.take(keep)
    sigma_in = _noise(prob, model, x, inl, fallback=float(np.median(sigma)))
    if not prob.stereo and model.range_sigma_m(1.0) is None:
        sigma_in = sigma[keep]
    fun, jac = _residual_fn(prob, inl, sigma_in)
    x = _gauss_newton(fun, jac, x, robust=False, iterations=20)
    n = inl.measured.size
    return _Fit(x, inl, sigma_in, jac(x)[:n], fun(x)[:n], jac(x)[n:])


def _evaluate(prob: _Problem, model: MeasurementModel, x: FloatArray, pts: _Points, fallback: float
              ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Native residuals, their noise and the metres-per-native-unit factor, per point."""
    resid = pts.measured - prob.predicted(x, pts)
    sigma = _noise(prob, model, x, pts, fallback)
    _, t, _ = prob.true_values(x[:prob.n_geometry], pts)
    if prob.stereo:
        z = t * pts.ray[:, 2]
        to_m = z * z / prob.fb
    else:
        to_m = np.ones_like(t)
    return resid, sigma, to_m


def _rms(a: FloatArray) -> float:
    return float(np.sqrt(np.mean(a * a))) if a.size else math.nan


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


def fit_depthcal(views: Sequence[DepthcalView], *, mount: Pose, model: MeasurementModel,
                 field_orders: Sequence[int] = (0, 1, 2, 3), holdout_every: int = 4,
                 wiggle_period_m: float | None = None, estimate_mount: bool = False,
                 max_points_per_view: int = 4000, seed: int = 0) -> DepthcalResult:
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

    Raises:
        ConfigError: Too few views, an unknown camera kind, no view to hold out, a view without the plane.
    """
    started = time.perf_counter()
    if model.kind not in ("stereo", "structured_light", "tof"):
        raise ConfigError(f"depthcal needs a stereo, structured_light or tof camera model, got {model.kind!r}",
                          key="camera.model.kind")
    if len(views) < MIN_VIEWS:
        raise ConfigError(f"needs at least {MIN_VIEWS} views at several heights, got {len(views)}",
                          key="depthcal.views")
    orders = sorted({int(o) for o in field_orders})
    if not orders:
        raise ConfigError("needs at least one field order", key="depthcal.field_orders")
    stereo = model.triangulating
    held = [i for i in range(len(views)) if holdout_every >= 2 and (i + 1) % holdout_every == 0]
    train = [i for i in range(len(views)) if i not in held]
    if not held or len(train) < MIN_VIEWS:
        raise ConfigError(f"holding out every {holdout_every}th of {len(views)} views leaves "
                          f"{len(held)} held out and {len(train)} to fit (needs >= 1 and >= {MIN_VIEWS})",
                          key="depthcal.holdout_every")
    period = float(wiggle_period_m or 0.0) if not stereo else 0.0
    kind = "stereo" if stereo else "tof"
    pts_all = _sample(views, model, max(orders), max_points_per_view, seed)
    n0, h0 = _initial_plane(views, mount)
    e1, e2 = _tangents(n0)
    fb = model.fb_px_m if stereo else 1.0
    flanges = [v.flange_pose for v in views]

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

    def x_start(prob: _Problem) -> FloatArray:
        return np.concatenate([[0.0, 0.0, h0], np.zeros(prob.n_geometry - 3), np.zeros(prob.free.size)])

    def solve(order: int | None, which: Sequence[int]) -> tuple[_Problem, _Fit]:
        prob = problem(order, which)
        pts = pts_all.subset(which)
        return prob, _solve(prob, model, pts, x_start(prob))

    # --- held-out pass: each order fitted without the held-out views, judged on them
    held_pts = pts_all.subset(held)
    scores: dict[int, float] = {}
    held_eval: dict[int, tuple[FloatArray, FloatArray, FloatArray, NDArray[np.bool_]]] = {}
    for order in orders:
        prob, fit = solve(order, train)
        hp = _Problem(**{**prob.__dict__, "flanges": [flanges[i] for i in held]})
        resid, sig, to_m = _evaluate(hp, model, fit.x, held_pts, float(np.median(fit.sigma)))
        w = resid / sig
        keep = np.abs(w) < INLIER_SIGMAS * max(1.4826 * float(np.median(np.abs(w))), 1.0)
        scores[order] = _rms(resid[keep])
        held_eval[order] = (resid, sig, to_m, keep)
    best = min(scores.values())
    n_held = int(np.count_nonzero(held_eval[min(scores, key=lambda k: scores[k])][3]))
    tol = best * max(0.005, 2.0 / math.sqrt(2.0 * max(n_held, 1)))
    order = min(o for o in orders if scores[o] <= best + tol)
    resid_a, sig_a, to_m_a, keep_a = held_eval[order]
    prob_b, fit_b = solve(None, train)
    hp_b = _Problem(**{**prob_b.__dict__, "flanges": [flanges[i] for i in held]})
    resid_b, _, to_m_b = _evaluate(hp_b, model, fit_b.x, held_pts, float(np.median(fit_b.sigma)))

    # --- the final correction on every view, and the uncorrected fit for the training views' "before"
    prob, fit = solve(order, range(len(views)))
    prob_0, fit_0 = solve(None, range(len(views)))
    resid_f, _, to_m_f = _evaluate(prob, model, fit.x, pts_all, float(np.median(fit.sigma)))
    resid_0, _, to_m_0 = _evaluate(prob_0, model, fit_0.x, pts_all, float(np.median(fit_0.sigma)))
    w_f = resid_f / _noise(prob, model, fit.x, pts_all, float(np.median(fit.sigma)))
    keep_f = np.abs(w_f) < INLIER_SIGMAS * max(1.4826 * float(np.median(np.abs(w_f))), 1.0)

    rows: list[ViewResidual] = []
    for i, view in enumerate(views):
        name = view.name or f"view {i}"
        if i in held:
            s = held_pts.slices[held.index(i)]
            k = keep_a[s]
            rows.append(ViewResidual(name, True, int(np.count_nonzero(k)), _rms(resid_b[s][k]), _rms(resid_a[s][k]),
                                     _rms((resid_b * to_m_b)[s][k]), _rms((resid_a * to_m_a)[s][k])))
        else:
            s = pts_all.slices[i]
            k = keep_f[s]
            rows.append(ViewResidual(name, False, int(np.count_nonzero(k)), _rms(resid_0[s][k]),
                                     _rms(resid_f[s][k]), _rms((resid_0 * to_m_0)[s][k]),
                                     _rms((resid_f * to_m_f)[s][k])))

    # --- covariance: the Jacobian's, scaled by chi-square per dof and the design effect when above 1
    fisher = np.einsum("ij,ik->jk", fit.jac, fit.jac)       # the data's alone: what the plan sees
    with_prior = fisher + np.einsum("ij,ik->jk", fit.prior_jac, fit.prior_jac)
    cov, _, _ = fisher_covariance(with_prior)
    dof = max(fit.resid.size - fisher.shape[0], 1)
    chi2 = float(fit.resid @ fit.resid) / dof
    deff, se = design_effect(fit.resid.astype(np.float32), fit.pts.masks, fit.pts.shape)
    factor = max(1.0, chi2)
    notes = []
    if chi2 > 1.0 + 3.0 * math.sqrt(2.0 / dof):
        notes.append(f"residuals {math.sqrt(chi2):.2f}x the stated noise: intervals widened by that")
    if deff > 1.0 + DEFF_SIGNIFICANCE * se:
        factor *= deff
        notes.append(f"residuals correlated across neighbouring pixels (design effect {deff:.2f}): "
                     f"intervals widened by {math.sqrt(deff):.2f}x")
    cov = cov * factor
    ng = prob.n_geometry
    names = prob.template.names
    full_cov = np.zeros((len(names), len(names)))
    full_cov[np.ix_(prob.free, prob.free)] = cov[ng:, ng:]
    correction = SystematicError.from_vector(kind, prob.vector(fit.x), field_order=order,  # type: ignore[arg-type]
                                             wiggle_period_m=period, covariance=full_cov)

    # --- observability from the noise alone, and the plan's spread of heights and inclinations
    normal = prob.normal(fit.x[:ng])
    h = float(fit.x[2])
    poses = prob.camera_poses(fit.x[:ng])
    heights = np.array([float(normal @ o) - h for _, o in poses])
    incl = np.degrees(np.arccos(np.clip([-float(rot[:, 2] @ normal) for rot, _ in poses], -1.0, 1.0)))
    geo_names = _PLANE_NAMES + (_MOUNT_NAMES if estimate_mount else [])
    all_names = geo_names + [names[k] for k in prob.free]
    obs = analyse(fisher, all_names, _limits(all_names, model, stereo),
                  height_spread_m=float(np.ptp(heights)), inclination_spread_deg=float(np.ptp(incl)),
                  estimate_mount=estimate_mount)
    if not obs.observable:
        notes.append("not seen by this plan: " + obs.message())
    mount_out = mount_cov = None
    if estimate_mount:
        mount_out = mount @ Pose.from_xyz_rotvec(fit.x[6:9], fit.x[3:6])
        mount_cov = cov[3:9, 3:9]
    return DepthcalResult(
        correction=correction, plane_normal_base=normal, plane_offset_m=h, plane_covariance=cov[:3, :3],
        field_order=order, order_scores=scores, views=rows,
        holdout_rms_before=_rms(resid_b[keep_a]), holdout_rms_after=_rms(resid_a[keep_a]),
        noise_only_rms=_rms(sig_a[keep_a]), observability=obs, mount=mount_out, mount_covariance=mount_cov,
        kind=kind, variance_factor=factor, n_points=int(fit.resid.size),
        elapsed_s=time.perf_counter() - started, notes=tuple(notes))
