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

How it stays cheap (ADR 0056, "Speed"): the plane's Jacobian columns are analytic and kept as rows, the
normal equations are built directly (``JᵀJ`` of ~200k x 15 is milliseconds); the robust pass runs on a
strided subsample and only tells the outliers and where to start; each lower field order starts from the
highest order's solution projected through its normal equations (the field terms are extra linear
columns) and takes one step; the fits on every view extend the training fits by the held-out views'
columns alone. Gauss-Newton converges quadratically here, so a step below 0.1 sigma ends it.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from cellcal.core.depthcal.observability import GEOMETRY_LIMITS, analyse, fisher_covariance
from cellcal.core.depthcal.result import DepthcalResult, ViewResidual
from cellcal.core.depthcal.view import DepthcalView
from cellcal.core.methods.fullframe.honesty import DEFF_SIGNIFICANCE, design_effect
from cellcal.devices.errors import ConfigError
from cellcal.devices.measurement import DEFAULT_ALLOWANCES, MeasurementModel
from cellcal.devices.pose import Pose
from cellcal.devices.systematic import SystematicError, field_terms

if TYPE_CHECKING:
    from cellcal.core.handeye.estimator import ArmAccuracy

__all__ = ["DEFAULT_POINTS_PER_VIEW", "INLIER_SIGMAS", "MIN_VIEWS", "fit_depthcal"]

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
#: Valid pixels a view gives the fit at most (a seeded sample): the scale's precision grows with them.
DEFAULT_POINTS_PER_VIEW = 16000
#: The robust pass (soft-L1, to tell the outliers) runs on a strided subsample of about this many points a view.
ROBUST_POINTS_PER_VIEW = 2000
#: Gauss-Newton stops after a step below this share of every parameter's (conditional) sigma: it converges
#: quadratically here (a step of 2 sigmas is followed by one of about 0.01), so the next would be ~1e-4.
_STEP_SIGMAS = 0.1
#: Steps of the central differences for the mount's columns (rad, m).
_STEP_ANGLE = 1e-6
_STEP_LENGTH = 1e-6
_PLANE_NAMES = ["plane_tilt_a_rad", "plane_tilt_b_rad", "plane_offset_m"]
_MOUNT_NAMES = ["mount_rx_rad", "mount_ry_rad", "mount_rz_rad", "mount_tx_m", "mount_ty_m", "mount_tz_m"]


def _dot(a: FloatArray, b: FloatArray) -> FloatArray:
    """``a @ b`` for a matrix and a vector (either way round) without BLAS: OpenBLAS threads a long
    matrix-vector or dot product and, on a busy machine, its spinning threads cost more than they save
    (measured: the whole fit twice the wall and CPU time with two threads than with one)."""
    out: FloatArray = np.einsum("ij,j->i", a, b) if a.ndim == 2 else np.einsum("i,ij->j", a, b)
    return out


def _sq(r: FloatArray) -> float:
    """``r @ r`` without BLAS (OpenBLAS threads a long dot product; see :func:`_dot`)."""
    return float(np.einsum("i,i->", r, r))


def _gram(a: FloatArray, b: FloatArray) -> FloatArray:
    """``a @ b.T`` of two row matrices ``(p, N)``, in slices of the columns small enough that OpenBLAS runs
    each on one thread (see :func:`_dot`; with the whole product the fit took 1.25x the CPU time with
    two threads than with one, with the slices the same)."""
    step = max(256, (1 << 17) // max(a.shape[0] * b.shape[0], 1))
    out = np.zeros((a.shape[0], b.shape[0]))
    for start in range(0, a.shape[1], step):
        out += a[:, start:start + step] @ b[:, start:start + step].T
    return out


@dataclass
class _Points:
    """The sampled points of a set of views, stacked."""

    ray: FloatArray            # (3, N) unit rays, camera frame, one row per axis
    u: FloatArray
    v: FloatArray
    measured: FloatArray       # native value, px or m
    basis: FloatArray          # (n_field, N) field monomials at the highest order, one row per monomial
    slices: list[slice]        # per view
    masks: list[NDArray[np.bool_]]   # per view, flat pixel mask of the sample
    shape: tuple[int, int]

    def index(self, views: Sequence[int]) -> NDArray[np.intp]:
        """Indices of the named views' points, in the order of ``views``."""
        if not views:
            return np.zeros(0, dtype=np.intp)
        return np.concatenate([np.arange(self.slices[i].start, self.slices[i].stop) for i in views])

    def subset(self, views: Sequence[int]) -> _Points:
        idx = self.index(views)
        slices, start = [], 0
        for i in views:
            n = self.slices[i].stop - self.slices[i].start
            slices.append(slice(start, start + n))
            start += n
        return _Points(self.ray[:, idx], self.u[idx], self.v[idx], self.measured[idx], self.basis[:, idx], slices,
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
        return _Points(self.ray[:, keep], self.u[keep], self.v[keep], self.measured[keep], self.basis[:, keep], slices,
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

    @property
    def n_field(self) -> int:
        return len(self.template.field_coeffs) if self.template.field_order else 0

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

    def true_values(self, g: FloatArray, pts: _Points, derivatives: bool = False
                    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray | None]:
        """True native value, range along the ray (m), cos of incidence and (``derivatives``) d(true)/d(g), per point.

        The derivatives are one row per geometry parameter, ``(n_geometry, N)``.

        The plane's columns are analytic (per view: the ray meets ``n · x = h`` at ``t = (h - n·o) / (n·R ray)``);
        the mount's, when estimated, central differences.
        """
        n = self.normal(g)
        h = float(g[2])
        size = pts.ray.shape[1]
        t = np.empty(size)
        nd_all = np.empty(size)
        poses = self.camera_poses(g)
        if derivatives:
            # d n / d g_k for the two tilts: the tangent's part normal to n over |n0 + g0 e1 + g1 e2|
            m = float(np.linalg.norm(self.n0 + g[0] * self.e1 + g[1] * self.e2))
            dn = [(e - n * float(n @ e)) / m for e in (self.e1, self.e2)]
            dt = np.empty((3, size))
        for s, (rot, origin) in zip(pts.slices, poses, strict=True):
            ray = pts.ray[:, s]
            nd = _dot(rot.T @ n, ray)               # n · (R ray)
            nd = np.minimum(nd, -1e-6)              # the ray must go towards the plane
            ts = (h - float(n @ origin)) / nd
            t[s] = ts
            nd_all[s] = nd
            if derivatives:
                for k in range(2):                  # dt/dg_k = -(o·dn_k + t ray·(Rᵀ dn_k)) / nd
                    dt[k, s] = -(float(origin @ dn[k]) + ts * _dot(rot.T @ dn[k], ray)) / nd
                dt[2, s] = 1.0 / nd
        clipped = t < 1e-4
        t = np.maximum(t, 1e-4)
        cos = -nd_all
        true = self.fb / (t * pts.ray[2]) if self.stereo else t
        if not derivatives:
            return true, t, cos, None
        jac = np.empty((self.n_geometry, size))    # one row per geometry parameter
        dtrue_dt = np.where(clipped, 0.0, -true / t if self.stereo else 1.0)
        np.multiply(dt, dtrue_dt, out=jac[:3])
        for k in range(3, self.n_geometry):
            step = _STEP_ANGLE if k < 6 else _STEP_LENGTH
            gp, gm = g.copy(), g.copy()
            gp[k] += step
            gm[k] -= step
            jac[k] = (self.true_values(gp, pts)[0] - self.true_values(gm, pts)[0]) / (2.0 * step)
        return true, t, cos, jac

    def vector(self, x: FloatArray) -> FloatArray:
        """The correction's full vector from the fitted parameters (fixed terms 0)."""
        c = np.zeros(len(self.template.names))
        c[self.free] = x[self.n_geometry:]
        return c

    def _wiggle(self, true: FloatArray) -> tuple[FloatArray, FloatArray]:
        phase = (2.0 * math.pi / self.template.wiggle_period_m) * true
        return np.cos(phase), np.sin(phase)

    def predicted(self, x: FloatArray, pts: _Points, true: FloatArray | None = None) -> FloatArray:
        """What the camera should measure (``distort`` of the true value), per point."""
        if true is None:
            true = self.true_values(x[:self.n_geometry], pts)[0]
        c = self.vector(x)
        out: FloatArray = true * (1.0 + c[0]) + c[1]
        head = 2
        if not self.stereo:
            head = 4
            if self.template.wiggle_period_m > 0.0 and (c[2] or c[3]):
                cos, sin = self._wiggle(true)
                out += c[2] * cos + c[3] * sin
        if c.size > head:
            out += _dot(c[head:], pts.basis[:c.size - head])
        return out

    def columns(self, x: FloatArray, pts: _Points) -> tuple[FloatArray, FloatArray]:
        """d(predicted)/d(fitted parameters), one row per parameter ``(n_geometry + n_free, N)``, and the prediction."""
        ng = self.n_geometry
        true, _, _, dtrue = self.true_values(x[:ng], pts, derivatives=True)
        assert dtrue is not None
        c = self.vector(x)
        tp = self.template
        slope = np.full(true.size, 1.0 + c[0])   # d(predicted)/d(true)
        full = [true, np.ones_like(true)]
        if not self.stereo:
            if tp.wiggle_period_m > 0.0:
                cos, sin = self._wiggle(true)
                slope += (2.0 * math.pi / tp.wiggle_period_m) * (c[3] * cos - c[2] * sin)
            else:
                cos = sin = np.zeros_like(true)
            full += [cos, sin]
        head = len(full)
        out = np.empty((ng + self.free.size, true.size))
        np.multiply(dtrue, slope, out=out[:ng])
        for k, j in enumerate(self.free):
            out[ng + k] = full[j] if j < head else pts.basis[j - head]
        return out, self.predicted(x, pts, true)


def _sample(views: Sequence[DepthcalView], model: MeasurementModel, order: int, max_points: int,
            seed: int) -> tuple[_Points, FloatArray]:
    """Up to ``max_points`` valid pixels per view (seeded), and their measured points (camera frame)."""
    rng = np.random.default_rng(seed)
    rays, us, vs, meas, masks, slices, points = [], [], [], [], [], [], []
    start = 0
    shape = (views[0].frame.intrinsics.height, views[0].frame.intrinsics.width)
    for k, view in enumerate(views):
        fr = view.frame
        intr = fr.intrinsics
        xyz32 = fr.xyz.reshape(-1, 3)
        dist32 = fr.distance.reshape(-1)
        z = xyz32[:, 2]
        ok = fr.valid.reshape(-1) & (z > 0) & np.isfinite(xyz32[:, 0]) & np.isfinite(xyz32[:, 1]) \
            & np.isfinite(z) & np.isfinite(dist32)
        idx = np.flatnonzero(ok)
        if idx.size < 50:
            raise ConfigError(f"view {view.name or k}: {idx.size} valid pixels, too few to see the plane",
                              key="depthcal.views")
        if idx.size > max_points:
            idx = np.sort(rng.choice(idx, size=max_points, replace=False))
        p = xyz32[idx].astype(np.float64)
        points.append(p)
        rays.append((p / np.linalg.norm(p, axis=1)[:, None]).T)
        rows, cols = np.divmod(idx, intr.width)
        us.append((cols - intr.cx) / (intr.width / 2.0))
        vs.append((rows - intr.cy) / (intr.height / 2.0))
        meas.append(model.fb_px_m / p[:, 2] if model.triangulating else dist32[idx].astype(np.float64))
        mask = np.zeros(ok.size, dtype=bool)
        mask[idx] = True
        masks.append(mask)
        slices.append(slice(start, start + idx.size))
        start += idx.size
    u_all, v_all = np.concatenate(us), np.concatenate(vs)
    return (_Points(np.concatenate(rays, axis=1), u_all, v_all, np.concatenate(meas), _monomials(u_all, v_all, order),
                    slices, masks, shape), np.concatenate(points))


def _monomials(u: FloatArray, v: FloatArray, order: int) -> FloatArray:
    """The field's monomials (:func:`~cellcal.devices.systematic.field_basis`'s, in its order) as rows ``(n, N)``,
    by products of powers (``**`` of arrays is several times slower)."""
    terms = field_terms(order)
    out = np.empty((len(terms), u.size))
    pu, pv = [np.ones_like(u)], [np.ones_like(v)]
    for _ in range(order):
        pu.append(pu[-1] * u)
        pv.append(pv[-1] * v)
    for k, (i, j) in enumerate(terms):
        np.multiply(pu[i], pv[j], out=out[k])
    return out


def _initial_plane(pts: _Points, points: FloatArray, flanges: Sequence[Pose], mount: Pose
                   ) -> tuple[FloatArray, float]:
    """A plane through the measured points in the base frame (trimmed least squares), normal towards the cameras."""
    base = []
    for s, flange in zip(pts.slices, flanges, strict=True):
        sample = points[s][:: max(1, (s.stop - s.start) // 2000)]
        base.append((flange @ mount).apply(sample))
    p = np.concatenate(base)
    keep = np.ones(len(p), dtype=bool)
    for _ in range(4):
        c = p[keep].mean(axis=0)
        q = p[keep] - c
        n = np.linalg.eigh(np.einsum("ij,ik->jk", q, q))[1][:, 0]   # the scatter's least direction
        r = _dot(p - c, n)
        mad = float(np.median(np.abs(r[keep] - np.median(r[keep])))) + 1e-9
        keep = np.abs(r - np.median(r[keep])) < 4.0 * 1.4826 * mad
    origin = np.asarray((flanges[0] @ mount).translation)
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
    fisher: FloatArray         # JᵀJ of the whitened residuals at x (the data's alone, no prior)
    resid: FloatArray          # whitened residuals of the inliers
    prior: FloatArray          # the prior's information, diagonal over the parameters (0 for the geometry)


def _noise(prob: _Problem, model: MeasurementModel, x: FloatArray, pts: _Points, fallback: float) -> FloatArray:
    """Per point noise 1-sigma in the native unit (stereo: constant; ToF: the model's law at range and incidence)."""
    if prob.stereo:
        return np.full(pts.measured.size, model.disparity_noise_px)
    _, t, cos, _ = prob.true_values(x[:prob.n_geometry], pts)
    sig = model.range_sigma_m(t, cos)
    if sig is None:
        return np.full(pts.measured.size, fallback)
    return np.maximum(np.asarray(sig, dtype=np.float64), 1e-6)


def _gauss_newton(prob: _Problem, pts: _Points, sigma: FloatArray, x: FloatArray, robust: bool,
                  iterations: int) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Gauss-Newton on the normal equations (the problem is linear in the correction, nearly so in the plane).

    The normal equations are built from the analytic columns (:meth:`_Problem.columns`) and the weak prior
    is added to them directly. ``robust``: iteratively reweighted with soft-L1 weights of scale
    :data:`ROBUST_SCALE` (speckle and edges lose their pull). Singular directions (a plan that cannot see
    a parameter) get the minimum-norm step. A step that raises the cost is halved. Stops when a step is
    below :data:`_STEP_SIGMAS` of every parameter's (conditional) sigma.

    Returns:
        ``(x, fisher, resid)``: the solution, ``JᵀJ`` of the whitened residuals at the last linearisation
        (unweighted, no prior) and the whitened residuals at ``x``.
    """
    ng = prob.n_geometry
    prior_info = np.concatenate([np.zeros(ng), 1.0 / prob.prior ** 2])
    inv_sigma = 1.0 / sigma

    def cost(r: FloatArray, xx: FloatArray) -> float:
        p = float(np.sum(xx[ng:] ** 2 / prob.prior ** 2))
        if robust:
            k = ROBUST_SCALE
            return float(np.sum(2.0 * k * k * (np.sqrt(1.0 + (r / k) ** 2) - 1.0))) + p
        return _sq(r) + p

    cols, pred = prob.columns(x, pts)
    r = (pts.measured - pred) * inv_sigma
    c = cost(r, x)
    fisher = np.zeros((x.size, x.size))
    for it in range(iterations):
        jw = cols                                 # d(predicted)/dx whitened (rows): the residual's Jacobian is -jwᵀ
        jw *= inv_sigma                           # in place: a fresh (p, N) array page-faults on every use
        if robust:
            w = 1.0 / np.sqrt(1.0 + (r / ROBUST_SCALE) ** 2)
            jww = jw * w
            a = _gram(jww, jw)
            b = _dot(jww, r)
            fisher = a
        else:
            fisher = _gram(jw, jw)
            a = fisher
            b = _dot(jw, r)
        a = a + np.diag(prior_info)
        b = b - prior_info * x
        d = np.sqrt(np.maximum(np.diag(a), 1e-300))
        scaled = np.linalg.lstsq(a / np.outer(d, d), b / d, rcond=1e-12)[0]
        step = scaled / d
        accepted = last = False
        for _half in range(8):
            x_new = x + step
            last = it == iterations - 1 or float(np.max(np.abs(scaled))) < _STEP_SIGMAS
            if last:                              # the columns at x_new are not needed
                pred = prob.predicted(x_new, pts)
            else:
                cols_new, pred = prob.columns(x_new, pts)
            r_new = (pts.measured - pred) * inv_sigma
            c_new = cost(r_new, x_new)
            if c_new <= c:
                accepted = True
                break
            step = step / 2.0
            scaled = scaled / 2.0
        if not accepted:
            break
        x, r, c = x_new, r_new, c_new
        if last:
            break
        cols = cols_new
    return x, fisher, r


def _solve(prob: _Problem, pts: _Points, sigma: FloatArray, x0: FloatArray, iterations: int = 20) -> _Fit:
    """A plain (not robust) fit of the points from ``x0``."""
    x, fisher, r = _gauss_newton(prob, pts, sigma, x0, robust=False, iterations=iterations)
    prior = np.concatenate([np.zeros(prob.n_geometry), 1.0 / prob.prior ** 2])
    return _Fit(x, pts, sigma, fisher, r, prior)


def _extend(prob: _Problem, train: _Fit, pts: _Points, sigma: FloatArray, held: Sequence[int],
            held_flanges: list[Pose]) -> _Fit:
    """The fit on every view's points ``pts`` from the fit on the training views, by one Gauss-Newton step.

    At the training solution the training points' gradient is zero and their normal matrix is known, so
    the step needs the columns of the held-out views' points alone: ``(F_train + F_held + P) d = J_heldᵀ r_held
    - P x``. The step is small (the held-out views add a quarter of the data) and the problem converges
    quadratically: what it leaves is about 0.01 of a sigma. Should the cost rise, a full fit from there.
    """
    ng = prob.n_geometry
    x = train.x
    idx = pts.index(held)
    held_pts = pts.subset(held)
    held_prob = dataclasses.replace(prob, flanges=held_flanges)
    cols, pred = held_prob.columns(x, held_pts)
    inv_sigma = 1.0 / sigma[idx]
    jw = cols
    jw *= inv_sigma
    r_held = (held_pts.measured - pred) * inv_sigma
    fisher = train.fisher + _gram(jw, jw)
    a = fisher + np.diag(train.prior)
    b = _dot(jw, r_held) - train.prior * x
    d = np.sqrt(np.maximum(np.diag(a), 1e-300))
    x_new = x + np.linalg.lstsq(a / np.outer(d, d), b / d, rcond=1e-12)[0] / d
    r = (pts.measured - prob.predicted(x_new, pts)) / sigma
    before = _sq(train.resid) + _sq(r_held) + float(np.sum(x[ng:] ** 2 * train.prior[ng:]))
    if _sq(r) + float(np.sum(x_new[ng:] ** 2 * train.prior[ng:])) > before:
        return _solve(prob, pts, sigma, x)
    return _Fit(x_new, pts, sigma, fisher, r, train.prior)


def _evaluate(prob: _Problem, model: MeasurementModel, x: FloatArray, pts: _Points, fallback: float
              ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Native residuals, their noise and the metres-per-native-unit factor, per point."""
    true, t, cos, _ = prob.true_values(x[:prob.n_geometry], pts)
    resid = pts.measured - prob.predicted(x, pts, true)
    if prob.stereo:
        sigma = np.full(pts.measured.size, model.disparity_noise_px)
        z = t * pts.ray[2]
        to_m = z * z / prob.fb
    else:
        sig = model.range_sigma_m(t, cos)
        sigma = (np.full(pts.measured.size, fallback) if sig is None
                 else np.maximum(np.asarray(sig, dtype=np.float64), 1e-6))
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
    pts_all, points = _sample(views, model, max(orders), max_points_per_view, seed)
    flanges = [v.flange_pose for v in views]
    n0, h0 = _initial_plane(pts_all, points, flanges, mount)
    e1, e2 = _tangents(n0)
    fb = model.fb_px_m if stereo else 1.0
    no_law = not stereo and model.range_sigma_m(1.0) is None

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

    def start_from(prob: _Problem, src: _Problem, x: FloatArray, normal: FloatArray | None = None) -> FloatArray:
        """``prob``'s parameters from ``src``'s solution ``x``: the geometry and the terms both have.

        With ``src``'s normal matrix at ``x`` (its solution on the same points), the terms ``prob`` lacks are
        dropped and the rest moved as the normal equations say (exact for a linear problem, so the lower
        orders of the held-out pass start a step or two from their own solutions).
        """
        ng = prob.n_geometry
        src_names = [src.template.names[k] for k in src.free]
        kept = list(range(ng)) + [ng + src_names.index(prob.template.names[k]) if prob.template.names[k] in src_names
                                  else -1 for k in prob.free]
        if normal is None or -1 in kept:
            names = dict(zip(src.template.names, src.vector(x), strict=True))
            terms = [names.get(prob.template.names[k], 0.0) for k in prob.free]
            return np.concatenate([x[:ng], np.asarray(terms, dtype=np.float64)])
        dropped = [i for i in range(x.size) if i not in kept]
        out = x[kept].copy()
        if dropped:
            a_kk = normal[np.ix_(kept, kept)]
            d = np.sqrt(np.maximum(np.diag(a_kk), 1e-300))
            rhs = normal[np.ix_(kept, dropped)] @ x[dropped]
            out += np.linalg.lstsq(a_kk / np.outer(d, d), rhs / d, rcond=1e-12)[0] / d
        return out

    everything = list(range(len(views)))
    # --- the robust pass: the highest order on every view, on a strided subsample (its job is to tell the
    #     outliers, and to start the plain fits near their solutions)
    prob_r = problem(max(orders), everything)
    stride = max(1, -(-pts_all.measured.size // (ROBUST_POINTS_PER_VIEW * len(views))))
    sub = pts_all.take(np.arange(pts_all.measured.size) % stride == 0)
    x0 = np.concatenate([[0.0, 0.0, h0], np.zeros(prob_r.n_geometry - 3), np.zeros(prob_r.free.size)])
    sigma_sub = _noise(prob_r, model, x0, sub, fallback=0.001)
    fallback = 0.001
    if no_law:
        r0 = sub.measured - prob_r.predicted(x0, sub)
        fallback = max(1.4826 * float(np.median(np.abs(r0 - np.median(r0)))), 1e-5)
        sigma_sub = np.full_like(sigma_sub, fallback)
    x_r, _, r_sub = _gauss_newton(prob_r, sub, sigma_sub, x0, robust=True, iterations=30)
    scale = max(1.4826 * float(np.median(np.abs(r_sub))), 1.0)
    sigma_all = _noise(prob_r, model, x_r, pts_all, fallback=fallback)
    keep = np.abs((pts_all.measured - prob_r.predicted(x_r, pts_all)) / sigma_all) < INLIER_SIGMAS * scale
    inl = pts_all.take(keep)
    sigma_in = sigma_all[keep]
    # the inliers' and their noise's indices per set of views
    train_idx = inl.index(train)
    inl_train = inl.subset(train)

    def solve(order: int | None, which: Sequence[int], pts: _Points, sigma: FloatArray,
              src: tuple[_Problem, FloatArray], normal: FloatArray | None = None) -> tuple[_Problem, _Fit]:
        prob = problem(order, which)
        # from the projected start one step leaves about 0.01 sigma (it converges quadratically): enough to
        # score an order on the held-out views, whose RMS it changes by less than 1e-4
        return prob, _solve(prob, pts, sigma, start_from(prob, *src, normal), 20 if normal is None else 1)

    # --- held-out pass: each order fitted without the held-out views (from the robust solution), judged on them
    held_pts = pts_all.subset(held)
    scores: dict[int, float] = {}
    held_eval: dict[int, tuple[FloatArray, FloatArray, FloatArray, NDArray[np.bool_]]] = {}
    train_fits: dict[int | None, tuple[_Problem, _Fit]] = {}
    top: tuple[_Problem, _Fit] | None = None
    for order in [*reversed(orders), None]:              # the highest from the robust solution, the rest from it
        if top is None:
            prob, fit = solve(order, train, inl_train, sigma_in[train_idx], (prob_r, x_r))
            top = prob, fit
        else:
            prob, fit = solve(order, train, inl_train, sigma_in[train_idx], (top[0], top[1].x),
                              top[1].fisher + np.diag(top[1].prior))
        train_fits[order] = (prob, fit)
        hp = dataclasses.replace(prob, flanges=[flanges[i] for i in held])
        resid, sig, to_m = _evaluate(hp, model, fit.x, held_pts, float(np.median(fit.sigma)))
        if order is None:
            resid_b, to_m_b = resid, to_m
            continue
        w = resid / sig
        k = np.abs(w) < INLIER_SIGMAS * max(1.4826 * float(np.median(np.abs(w))), 1.0)
        scores[order] = _rms(resid[k])
        held_eval[order] = (resid, sig, to_m, k)
    best = min(scores.values())
    n_held = int(np.count_nonzero(held_eval[min(scores, key=lambda k: scores[k])][3]))
    tol = best * max(0.005, 2.0 / math.sqrt(2.0 * max(n_held, 1)))
    order = min(o for o in orders if scores[o] <= best + tol)
    resid_a, sig_a, to_m_a, keep_a = held_eval[order]

    # --- the final correction on every view, and the uncorrected fit for the training views' "before",
    #     each its training fit extended by the held-out views
    held_flanges = [flanges[i] for i in held]
    prob = problem(order, everything)
    fit = _extend(prob, train_fits[order][1], inl, sigma_in, held, held_flanges)
    prob_0 = problem(None, everything)
    fit_0 = _extend(prob_0, train_fits[None][1], inl, sigma_in, held, held_flanges)
    resid_f, sig_f, to_m_f = _evaluate(prob, model, fit.x, pts_all, float(np.median(fit.sigma)))
    resid_0, _, to_m_0 = _evaluate(prob_0, model, fit_0.x, pts_all, float(np.median(fit_0.sigma)))
    w_f = resid_f / sig_f
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
    unmodelled, said = _unmodelled(prob, fit, model, order, arm_accuracy, h_inv=cov)
    cov = cov * factor + unmodelled   # unscaled: the data cannot tell them from the truth
    notes += said
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
