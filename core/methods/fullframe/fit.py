"""The robust full-frame fit: triplet hypotheses, reweighted Gauss-Newton on the ranges, intervals.

Points are in the camera frame (OpenCV: x right, y down, z along the optical axis), metres,
with the sensor at the origin; the fitted normal points toward the camera (``offset_m > 0``).
Method and rationale: docs/adr/0007-full-frame-fit.md.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import ndtr, ndtri

from cellcal.core.geometry.planes import Plane
from cellcal.core.methods.fullframe.gates import gate_table, image_coverage
from cellcal.core.methods.fullframe.result import Estimate, FullFrameResult
from cellcal.core.methods.fullframe.settings import MIN_POINTS, FullFrameSettings
from cellcal.devices.errors import CalibrationError, CalibrationQualityError
from cellcal.devices.types import Frame

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
F32 = NDArray[np.float32]

__all__ = ["fit_full_frame", "fit_plane_points"]

_SQRT_2PI = math.sqrt(2.0 * math.pi)


# ---------------------------------------------------------------------- numerics
def _basis(n: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Two unit vectors completing the unit vector ``n`` to a right-handed orthonormal basis."""
    x, y, z = float(n[0]), float(n[1]), float(n[2])
    # e1 = normalise(ex - x n), or normalise(ey - y n) when n is close to ex
    e1 = np.array([1.0 - x * x, -x * y, -x * z]) if abs(x) < 0.8 else np.array([-y * x, 1.0 - y * y, -y * z])
    e1 /= math.sqrt(float(e1 @ e1))
    a, b, c = float(e1[0]), float(e1[1]), float(e1[2])
    return e1, np.array([y * c - z * b, z * a - x * c, x * b - y * a])   # e2 = n x e1


def _truncation(c: float) -> tuple[float, float]:
    """For a Gaussian cut at ``±c`` sigma: (variance factor of the kept part, covariance factor).

    The first divides the inlier mean square to estimate sigma^2; the second multiplies
    the sandwich covariance of the hard-rejection estimator (its derivative loses the
    ``2 c phi(c)`` of the points crossing the cut).
    """
    p = 2.0 * float(ndtr(c)) - 1.0                          # kept probability 2 Phi(c) - 1
    jump = 2.0 * c * math.exp(-0.5 * c * c) / _SQRT_2PI     # 2 c phi(c)
    kept_var = (p - jump) / p                               # E[z^2 | |z| < c]
    bread = p - jump
    return kept_var, (p / bread) ** 2 if bread > 0 else 1.0


def _step_plane(n: FloatArray, e1: FloatArray, e2: FloatArray, offset: float, step: FloatArray
                ) -> tuple[FloatArray, float]:
    """Apply a step ``(d_e1, d_e2, d_offset)``: the new unit normal and offset."""
    n_new = n + step[0] * e1 + step[1] * e2                 # tangent move of the normal ...
    return n_new / np.linalg.norm(n_new), offset + float(step[2])   # ... back onto the sphere


@dataclass(frozen=True)
class _Cutoff:
    """Hard inlier cut-off on the normalised range residual: ``k_sig`` scales, within [lo, hi]."""

    k_sig: float
    lo: float                 # min_inlier_threshold_m at the median pixel's noise
    hi: float                 # max_inlier_threshold_m at the median pixel's noise
    kept_var: float           # variance factor of a Gaussian cut at ±k_sig (see _truncation)
    cov_factor: float         # covariance factor of the hard-rejection estimator

    def at(self, scale: float) -> float:
        """The cut-off for a robust scale ``scale`` of the normalised residuals."""
        return min(max(self.k_sig * scale, self.lo), self.hi)


@dataclass
class _Pass:
    """Sums of one Gauss-Newton pass over a point set."""

    step: FloatArray          # (d_e1, d_e2, d_offset)
    hessian: FloatArray       # J^T W J
    n_inliers: int
    z2_sum: float             # sum of squared normalised residuals of the inliers
    meat: FloatArray | None = None      # sum (w rho)^2 J J^T (final pass only)
    ortho2_sum: float = math.nan        # sum of squared orthogonal residuals (final pass only)
    inliers: BoolArray | None = None    # (final pass only)


def _residuals(b0: F32, dm: F32, offset: float, thr: float, weighted: bool, exponent: float,
               sigma: F32 | None) -> tuple[F32, F32, F32, F32 | None, BoolArray]:
    """Whitened range residuals of points with ``b0 = p·n`` (N,) and ranges ``dm``.

    Returns ``1/cos``, the predicted range ``t``, the whitened residual ``z``, the
    inverse sigma (None when unweighted) and the inlier mask ``|z| < thr`` (in front).
    """
    f32 = np.float32
    inv_c = np.divide(dm, b0)                  # 1 / cos(ray, normal), negative in front
    t = inv_c * f32(-offset)                   # predicted range along the ray
    z = np.subtract(dm, t)                     # range residual rho ...
    if sigma is not None:
        isig: F32 | None = np.divide(f32(1.0), sigma)
    elif weighted:                             # 1 / (t^e / sqrt|cos|)
        isig = np.multiply(t, inv_c)
        np.abs(isig, out=isig)
        if exponent == 1.5:
            np.sqrt(isig, out=isig)
            isig *= t
        else:
            np.power(isig, f32(0.5), out=isig)
            isig *= np.abs(t) ** f32(exponent - 1.0) * t
        np.divide(f32(1.0), isig, out=isig)
    else:
        isig = None
    if isig is not None:
        z *= isig                              # ... whitened
    inl = np.abs(z) < f32(thr)                 # inliers: within the cut-off ...
    inl &= t > 0                               # ... and the plane in front along the ray
    return inv_c, t, z, isig, inl


def _gram(cols: Sequence[F32]) -> FloatArray:
    """Symmetric 3x3 matrix of the dot products of three columns (float64 sums)."""
    out = np.empty((3, 3))
    for i in range(3):
        for k in range(i, 3):
            out[i, k] = out[k, i] = float(np.dot(cols[i], cols[k]))
    return out


def _gn_pass(p: F32, dm: F32, n: FloatArray, e1: FloatArray, e2: FloatArray, offset: float,
             thr: float, weighted: bool, exponent: float, sigma: F32 | None = None,
             final: bool = False, refine: Callable[[BoolArray], BoolArray] | None = None) -> _Pass:
    """One reweighted Gauss-Newton pass of the range model over points ``p`` (3, N).

    The range along the ray ``r = p / |p|`` predicted by the plane is
    ``t = -offset / (r·n)``; the residual ``rho = |p| - t`` has the Jacobian
    ``(t (r·e1) / (r·n), t (r·e2) / (r·n), 1 / (r·n))`` with respect to the normal's
    tangent steps along ``e1``, ``e2`` and the offset. Everything is whitened by the
    point's noise sigma and masked to the inliers, in place on a few float32 buffers.

    Args:
        thr: Cut-off on the noise-normalised range residual.
        sigma: Per-point range-noise sigma (N,), replacing the noise model if given.
        final: Also return the sandwich "meat", the orthogonal residual sum and the
            inlier mask.
        refine: Maps the inlier mask (N,) to the points allowed to stay inliers.
    """
    f32 = np.float32
    basis = np.stack([n, e1, e2]).astype(f32)
    b = basis @ p                              # (3, N): p·n, p·e1, p·e2
    inv_c, t, z, isig, inl = _residuals(b[0], dm, offset, thr, weighted, exponent, sigma)
    if refine is not None:
        inl &= refine(inl)                     # image-space clean-up of the inliers
    n_in = int(np.count_nonzero(inl))
    if n_in < MIN_POINTS:
        raise CalibrationError(f"full-frame fit found only {n_in} inlier(s); no plane is defined")
    z *= inl                                   # r: whitened, masked residual
    if isig is None:
        isig = inl.astype(f32)
    else:
        isig *= inl                            # masked 1 / sigma
    t *= inv_c
    t /= dm
    t *= isig                                  # q = t / (|p| cos) / sigma
    a1 = np.multiply(t, b[1])                  # whitened Jacobian columns
    a2 = np.multiply(t, b[2], out=t)
    a3 = np.multiply(inv_c, isig, out=inv_c)
    cols = (a1, a2, a3)
    h = _gram(cols)                            # J^T W J
    g = np.array([float(np.dot(c, z)) for c in cols])   # J^T W rho
    try:
        step = np.asarray(-np.linalg.solve(h, g), dtype=np.float64)   # Gauss-Newton step
    except np.linalg.LinAlgError:
        raise CalibrationError("full-frame fit is degenerate: the inliers do not span a plane") from None
    z2 = float(np.dot(z, z))                   # sum of squared whitened inlier residuals
    if not final:
        return _Pass(step, h, n_in, z2)
    meat = _gram([np.multiply(c, z, out=c if c is not a1 else None) for c in cols])   # sum (w rho)^2 J J^T
    ortho = np.add(b[0], f32(offset), out=isig)   # orthogonal residual p·n + offset ...
    ortho *= inl                                  # ... of the inliers
    return _Pass(step, h, n_in, z2, meat, float(np.dot(ortho, ortho)), inl)


def _hypothesis(p: F32, settings: FullFrameSettings, rng: np.random.Generator) -> tuple[FloatArray, float]:
    """Best triplet plane by the quantile of normalised orthogonal residuals (unit n, offset)."""
    n_pts = p.shape[1]
    m = min(n_pts, settings.sample_points)
    sub = np.take(p, rng.integers(0, n_pts, m), axis=1).T.astype(np.float64)   # m random points
    idx = rng.integers(0, m, size=(3, settings.hypotheses))                     # a random triplet each
    a = sub[idx[0]]
    u = sub[idx[1]] - a
    v = sub[idx[2]] - a
    nrm = np.empty_like(u)                     # normal u x v of each triplet
    nrm[:, 0] = u[:, 1] * v[:, 2] - u[:, 2] * v[:, 1]
    nrm[:, 1] = u[:, 2] * v[:, 0] - u[:, 0] * v[:, 2]
    nrm[:, 2] = u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]
    length = np.sqrt(np.einsum("ij,ij->i", nrm, nrm))
    ok = length > 1e-9 * np.einsum("ij,ij->i", u, u)    # drop (nearly) collinear triplets
    if not ok.any():
        raise CalibrationError("full-frame fit: the points are collinear or coincident; no plane is defined")
    nrm = nrm[ok] / length[ok, None]
    off = -np.einsum("ij,ij->i", nrm, a[ok])
    sub32 = sub.astype(np.float32)
    res = nrm.astype(np.float32) @ sub32.T                # (K, m) orthogonal distances
    res += off.astype(np.float32)[:, None]
    np.abs(res, out=res)
    if settings.weighted:                                  # noise grows with the range
        rng_m = np.sqrt(np.einsum("ij,ij->i", sub32, sub32))
        res /= rng_m ** np.float32(settings.noise_distance_exponent)
    k = min(int(settings.hypothesis_quantile * m), m - 1)
    score = np.partition(res, k, axis=1)[:, k]             # the quantile of each plane's residuals
    j = int(np.argmin(score))                              # least quantile of squares wins
    n = nrm[j]
    d = float(off[j])
    if d < 0:                                              # normal toward the camera
        n, d = -n, -d
    return n, d


def _subsample(limit: int, *arrays: F32) -> list[F32]:
    """Every k-th point (last axis; contiguous copies) so that at most ``limit`` remain."""
    step = -(-arrays[0].shape[-1] // limit)
    if step <= 1:
        return list(arrays)
    return [np.ascontiguousarray(a[..., ::step]) for a in arrays]


@dataclass
class _Fit:
    plane: Plane
    cov: FloatArray           # covariance of (d_e1, d_e2, d_offset)
    e1: FloatArray
    e2: FloatArray
    inliers: BoolArray
    residual_rms_m: float
    noise_scale_m: float


def _initial_scale(p: F32, dm: F32, sigma: F32 | None, n: FloatArray, offset: float,
                   settings: FullFrameSettings) -> tuple[float, _Cutoff]:
    """Robust scale of the start plane's normalised range residuals on <= 1024 points, and the cut-off."""
    k0 = max(1, p.shape[1] // 1024)
    p0, d0 = p[:, ::k0], dm[::k0]
    inv_c = d0 / (n.astype(np.float32) @ p0)   # 1 / cos(ray, normal)
    t = inv_c * np.float32(-offset)            # predicted range along the ray
    z = d0 - t                                 # range residual ...
    sig_med = 1.0
    if sigma is not None:
        sig = sigma[::k0]
        z /= sig                               # ... normalised by the given sigmas
    elif settings.weighted:
        sig = (np.abs(t) ** np.float32(settings.noise_distance_exponent) / np.sqrt(np.abs(inv_c))).astype(np.float32)
        z /= sig                               # ... or by the noise model t^e / sqrt|cos|
    if sigma is not None or settings.weighted:
        mid = sig.size // 2
        sig_med = max(float(np.partition(sig, mid)[mid]), 1e-12)   # median pixel's sigma
    q = settings.hypothesis_quantile
    az = np.abs(z)
    kq = min(int(q * az.size), az.size - 1)
    s = float(np.partition(az, kq)[kq]) / float(ndtri(0.5 + q / 2.0))   # |z| quantile -> Gaussian sigma
    k_sig = settings.inlier_threshold_sigma
    kept_var, cov_factor = _truncation(k_sig)
    cutoff = _Cutoff(k_sig, settings.min_inlier_threshold_m / sig_med, settings.max_inlier_threshold_m / sig_med,
                     kept_var, cov_factor)
    return s, cutoff


def _converged(it: _Pass, s: float, s_new: float, floor_scale: float) -> bool:
    """The step is a small fraction of the parameters' (subsample) sigma and the scale has settled.

    Noise-free data: the cut-off sits at its floor (``floor_scale``) and the scale never settles
    in relative terms. The full-data pass after the loop finishes the job.
    """
    try:
        sd = np.sqrt(np.abs(np.diag(np.linalg.inv(it.hessian)))) * max(s_new, floor_scale)   # parameter sigmas
    except np.linalg.LinAlgError:
        sd = np.full(3, np.inf)
    settled = abs(s_new - s) <= 0.15 * s or max(s, s_new) <= floor_scale
    return bool(np.all(np.abs(it.step) <= 0.5 * sd)) and settled


def _refine(p: F32, dm: F32, sigma: F32 | None, n: FloatArray, offset: float, s: float, cutoff: _Cutoff,
            settings: FullFrameSettings) -> tuple[FloatArray, float, float]:
    """Reweighted Gauss-Newton passes (on the subsample) until converged: normal, offset, scale."""
    e1, e2 = _basis(n)
    for _ in range(settings.max_iterations):
        it = _gn_pass(p, dm, n, e1, e2, offset, cutoff.at(s), settings.weighted,
                      settings.noise_distance_exponent, sigma)
        n, offset = _step_plane(n, e1, e2, offset, it.step)
        e1, e2 = _basis(n)
        s_new = math.sqrt(it.z2_sum / it.n_inliers / cutoff.kept_var)   # inlier RMS, truncation-corrected
        converged = _converged(it, s, s_new, cutoff.lo / cutoff.k_sig)
        s = s_new
        if converged:
            break
    return n, offset, s


def _final_fit(p: F32, dm: F32, sigma: F32 | None, n: FloatArray, offset: float, s: float, cutoff: _Cutoff,
               settings: FullFrameSettings, refine_mask: Callable[[BoolArray], BoolArray] | None) -> _Fit:
    """The last Gauss-Newton pass over every point: plane, sandwich covariance, inliers, RMS, scale."""
    e1, e2 = _basis(n)
    fin = _gn_pass(p, dm, n, e1, e2, offset, cutoff.at(s), settings.weighted, settings.noise_distance_exponent,
                   sigma, final=True, refine=refine_mask)
    assert fin.meat is not None and fin.inliers is not None
    n_fin, offset_fin = _step_plane(n, e1, e2, offset, fin.step)
    try:
        h_inv = np.linalg.inv(fin.hessian)
    except np.linalg.LinAlgError:
        raise CalibrationError("full-frame fit is degenerate: the inliers do not span a plane") from None
    dof = max(fin.n_inliers - 3, 1)
    # sandwich H^-1 M H^-1, small-sample factor n / (n - 3), hard-rejection correction
    cov = h_inv @ fin.meat @ h_inv * (fin.n_inliers / dof) * cutoff.cov_factor
    plane = Plane(n_fin, offset_fin)
    rms = math.sqrt(fin.ortho2_sum / fin.n_inliers)
    noise = math.sqrt(fin.z2_sum / fin.n_inliers / cutoff.kept_var)   # truncation-corrected scale
    return _Fit(plane, cov, e1, e2, fin.inliers, rms, noise)


def _robust_fit(p: F32, dm: F32, settings: FullFrameSettings, sigma: F32 | None = None,
                refine_mask: Callable[[BoolArray], BoolArray] | None = None) -> _Fit:
    """The three stages on finite camera-frame points ``p`` (3, N) with ranges ``dm``.

    ``sigma`` (N,), if given, is each point's range-noise sigma (replaces the model).
    ``refine_mask`` maps the inlier mask (N,) of the converged plane to the points
    allowed in the last pass (image-space clean-up, see ``edge_margin_deg``).
    """
    rng = np.random.default_rng(settings.seed)
    n, offset = _hypothesis(p, settings, rng)                  # robust start
    if sigma is None:                                          # strided subsample for the passes
        ps, ds = _subsample(settings.refine_points, p, dm)
        ss = None
    else:
        ps, ds, ss = _subsample(settings.refine_points, p, dm, sigma)
    s, cutoff = _initial_scale(ps, ds, ss, n, offset, settings)
    n, offset, s = _refine(ps, ds, ss, n, offset, s, cutoff, settings)
    return _final_fit(p, dm, sigma, n, offset, s, cutoff, settings, refine_mask)   # one pass over all


# ---------------------------------------------------------------------- derived values
def _geometry(n: FloatArray, d: FloatArray) -> FloatArray:
    """Angle to the optical axis, tilt x, tilt y, height along the axis of planes (K, 4).

    Vectorised copies of :meth:`Plane.angle_to_optical_axis_rad`,
    :meth:`Plane.tilt_about_x_rad`, :meth:`Plane.tilt_about_y_rad` and
    :meth:`Plane.distance_along_optical_axis_m` (NaN where the axis misses the plane)
    for unit normals ``n`` (K, 3) and offsets ``d`` (K,).
    """
    nz = n[:, 2]
    f = np.where((nz > 0)[:, None], -n, n)            # the normal as seen from the camera
    out = np.empty((n.shape[0], 4))
    out[:, 0] = np.arcsin(np.minimum(1.0, np.abs(nz)))
    out[:, 1] = np.arctan2(-f[:, 1], -f[:, 2])
    out[:, 2] = np.arctan2(f[:, 0], -f[:, 2])
    with np.errstate(divide="ignore", invalid="ignore"):
        h = -d / nz
    out[:, 3] = np.where((np.abs(nz) >= 1e-12) & (h > 0), h, np.nan)
    return out


def _derived(fit: _Fit) -> tuple[list[float], list[float]]:
    """Angle, tilt x, tilt y, height and their 1-sigma (central-difference Jacobians)."""
    n0 = fit.plane.normal
    d0 = fit.plane.offset_m
    steps = np.array([1e-6, 1e-6, 1e-6 * max(abs(d0), 1e-3)])
    dp = np.concatenate([np.zeros((1, 3)), np.diag(steps), -np.diag(steps)])   # (7, 3): 0, +steps, -steps
    nn = n0 + dp[:, :1] * fit.e1 + dp[:, 1:2] * fit.e2
    norm = np.linalg.norm(nn, axis=1)
    v = _geometry(nn / norm[:, None], (d0 + dp[:, 2]) / norm)
    jac = ((v[1:4] - v[4:7]) / (2.0 * steps[:, None])).T                      # (4, 3)
    var = np.einsum("ij,jk,ik->i", jac, fit.cov, jac)                          # diag(J C J^T)
    return v[0].tolist(), np.sqrt(np.maximum(var, 0.0)).tolist()


def _assemble(fit: _Fit, settings: FullFrameSettings, *, n_points: int, valid_fraction: float,
              inlier_mask: BoolArray, coverage: float, n_frames: int) -> FullFrameResult:
    """The result: estimates with intervals, covariances of normal and offset, gate values."""
    (angle, tx, ty, height), (s_a, s_x, s_y, s_h) = _derived(fit)
    z = float(ndtri(0.5 + settings.confidence / 2.0))   # two-sided normal quantile: value ± z sigma
    e = np.stack([fit.e1, fit.e2], axis=1)
    cov_n = e @ fit.cov[:2, :2] @ e.T                    # tangent steps -> unit normal (3x3)
    cov_nd = e @ fit.cov[:2, 2]
    n_in = int(np.count_nonzero(fit.inliers))
    inlier_fraction = n_in / n_points
    gates = gate_table(settings, valid_fraction, inlier_fraction, fit.residual_rms_m, coverage)
    return FullFrameResult(
        plane=fit.plane, angle=Estimate.from_sigma(angle, s_a, z, 0.0, math.pi / 2),
        tilt_x=Estimate.from_sigma(tx, s_x, z), tilt_y=Estimate.from_sigma(ty, s_y, z),
        height=Estimate.from_sigma(height, s_h, z), confidence=settings.confidence,
        normal_covariance=cov_n, offset_variance_m2=float(fit.cov[2, 2]), normal_offset_covariance=cov_nd,
        valid_fraction=valid_fraction, inlier_fraction=inlier_fraction, residual_rms_m=fit.residual_rms_m,
        coverage=coverage, noise_scale_m=fit.noise_scale_m, n_points=n_points, n_inliers=n_in,
        n_frames=n_frames, inlier_mask=inlier_mask, gates=gates)


# ---------------------------------------------------------------------- public API
def fit_plane_points(points_m: ArrayLike, sigma_m: ArrayLike | None = None,
                     settings: FullFrameSettings | None = None) -> FullFrameResult:
    """Robust full-cloud plane fit of raw camera-frame points.

    The sensor must be at the origin (ranges are measured along the rays through it).

    Args:
        points_m: Shape (N, 3), camera frame, metres; rows with NaN/inf are skipped.
        sigma_m: Optional per-point range-noise sigma, metres, shape (N,): replaces the
            noise model's weights (rows with sigma <= 0 or non-finite are skipped).
        settings: Fit settings and gates; None uses the defaults.

    Returns:
        The result; ``inlier_mask`` has shape (N,), ``coverage`` is NaN (no image) and
        there is no coverage gate; ``valid_fraction`` counts finite rows.

    Raises:
        CalibrationError: Wrong shape or type, or no plane can be defined.
        CalibrationQualityError: Fewer than 16 usable points (gate ``valid_fraction``).
    """
    cfg = settings or FullFrameSettings()
    try:
        pts = np.asarray(points_m, dtype=np.float32)
    except (TypeError, ValueError):
        raise CalibrationError("points_m must be a numeric (N, 3) array") from None
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise CalibrationError(f"points_m must have shape (N, 3), got {pts.shape}")
    n_all = pts.shape[0]
    with np.errstate(invalid="ignore", over="ignore"):
        dm = np.sqrt(np.einsum("ij,ij->i", pts, pts))   # measured range |p|
    ok = np.isfinite(dm) & (dm > 0)
    sig: F32 | None = None
    if sigma_m is not None:
        try:
            sig = np.asarray(sigma_m, dtype=np.float32).reshape(-1)
        except (TypeError, ValueError):
            raise CalibrationError("sigma_m must be a numeric (N,) array") from None
        if sig.shape != (n_all,):
            raise CalibrationError(f"sigma_m must have shape ({n_all},), got {np.shape(sigma_m)}")
        ok &= np.isfinite(sig) & (sig > 0)
    n_ok = int(np.count_nonzero(ok))
    valid_fraction = n_ok / n_all if n_all else 0.0
    if n_ok < MIN_POINTS:
        raise CalibrationQualityError("valid_fraction", valid_fraction, cfg.min_valid_fraction,
                                      f"only {n_ok} usable point(s); a full-frame fit needs {MIN_POINTS}")
    p = np.ascontiguousarray(pts[ok].T)
    d = np.ascontiguousarray(dm[ok])
    fit = _robust_fit(p, d, cfg, None if sig is None else np.ascontiguousarray(sig[ok]))
    mask = np.zeros(n_all, dtype=bool)
    mask[ok] = fit.inliers
    return _assemble(fit, cfg, n_points=n_ok, valid_fraction=valid_fraction, inlier_mask=mask,
                     coverage=math.nan, n_frames=1)


def _frames_points(frames: Frame | Sequence[Frame]) -> tuple[list[Frame], F32, F32, list[BoolArray]]:
    """Validate frames; pooled valid points (3, N), ranges (N,) and each frame's flat mask."""
    if isinstance(frames, Frame):
        seq = [frames]
    else:
        try:
            seq = list(frames)
        except TypeError:
            raise CalibrationError(f"expected a Frame or a sequence of frames, got {type(frames).__name__}") from None
    if not seq:
        raise CalibrationError("fit_full_frame needs at least one frame")
    for i, f in enumerate(seq):
        if not isinstance(f, Frame):
            raise CalibrationError(f"frame {i} is a {type(f).__name__}, not a Frame")
        if f.shape != seq[0].shape:
            raise CalibrationError(f"frame {i} has shape {f.shape}, frame 0 has {seq[0].shape}")
    pts, dms, masks = [], [], []
    for f in seq:
        dist = f.distance.reshape(-1)
        with np.errstate(invalid="ignore"):
            m = f.valid.reshape(-1) & (dist > 0)   # NaN compares False
        idx = np.flatnonzero(m)
        p = np.take(f.xyz.reshape(-1, 3).T, idx, axis=1)    # (3, n) structure of arrays
        d = np.take(dist, idx)
        if not (math.isfinite(float(p.sum())) and math.isfinite(float(d.sum()))):   # rare: drop NaN/inf
            fin = np.isfinite(p).all(axis=0) & np.isfinite(d)
            m[idx[~fin]] = False
            p, d = np.ascontiguousarray(p[:, fin]), d[fin]
        pts.append(p)
        dms.append(d)
        masks.append(m)
    if len(seq) == 1:
        return seq, pts[0], dms[0], masks
    return seq, np.concatenate(pts, axis=1), np.concatenate(dms), masks


def _edge_keep(inliers: BoolArray, masks: list[BoolArray], shape: tuple[int, int], margin_px: int) -> BoolArray:
    """Points (pooled order) farther than ``margin_px`` from solid patches of non-plane pixels.

    Per frame: non-plane = outlier or invalid; a morphological opening (3x3) keeps
    patches, dropping isolated outliers (noise tails, random flying pixels); the
    patches grown by ``margin_px`` are excluded.
    """
    h, w = shape
    keep = np.ones(inliers.size, dtype=bool)
    k_open = np.ones((3, 3), np.uint8)
    k_grow = np.ones((2 * margin_px + 1, 2 * margin_px + 1), np.uint8)
    start = 0
    for m in masks:
        k = int(np.count_nonzero(m))
        off_plane = np.ones(h * w, dtype=np.uint8)
        off_plane[m] = ~inliers[start:start + k]
        patches = cv2.morphologyEx(off_plane.reshape(h, w), cv2.MORPH_OPEN, k_open)
        near = cv2.dilate(patches, k_grow).reshape(-1)
        keep[start:start + k] = near[m] == 0
        start += k
    return keep


def _pixel_inliers(inliers: BoolArray, masks: list[BoolArray], shape: tuple[int, int]) -> BoolArray:
    """(H, W) mask of the pixels that are inliers in at least half of the frames where they are valid."""
    h, w = shape
    if len(masks) == 1:
        flat = np.zeros(h * w, dtype=bool)
        flat[masks[0]] = inliers
        return flat.reshape(h, w)
    inl_count = np.zeros(h * w, dtype=np.int32)
    val_count = np.zeros(h * w, dtype=np.int32)
    start = 0
    for m in masks:
        k = int(np.count_nonzero(m))
        inl_count[m] += inliers[start:start + k]
        val_count += m
        start += k
    return ((val_count > 0) & (2 * inl_count >= val_count)).reshape(h, w)


def fit_full_frame(frames: Frame | Sequence[Frame], settings: FullFrameSettings | None = None) -> FullFrameResult:
    """Fit the measuring plane to every valid pixel of one or more frames of a static camera.

    Frames are pooled (each pixel of each frame is one observation). The fit does not
    raise on a failed gate: see ``result.gates`` or call :func:`check_gates`.

    Args:
        frames: One frame or several of the same camera and pose.
        settings: Fit settings and gates (the ``[full_frame]`` table); None: defaults.

    Returns:
        The plane (camera frame, normal toward the camera) with intervals and gates.

    Raises:
        CalibrationError: Malformed input (not frames, mixed shapes) or no plane defined.
        CalibrationQualityError: Fewer than 16 valid pixels (gate ``valid_fraction``).
    """
    cfg = settings or FullFrameSettings()
    seq, p, dm, masks = _frames_points(frames)
    h, w = seq[0].shape
    n_pixels = h * w * len(seq)
    n_ok = p.shape[1]
    valid_fraction = n_ok / n_pixels
    if n_ok < MIN_POINTS:
        raise CalibrationQualityError("valid_fraction", valid_fraction, cfg.min_valid_fraction,
                                      f"only {n_ok} valid pixel(s); a full-frame fit needs {MIN_POINTS}")
    refine = None
    intr = seq[0].intrinsics
    margin_px = math.ceil(math.radians(cfg.edge_margin_deg) * max(intr.fx, intr.fy) - 1e-9)   # degrees -> px
    if margin_px > 0:
        def refine(inliers: BoolArray) -> BoolArray:
            return _edge_keep(inliers, masks, (h, w), margin_px)
    fit = _robust_fit(p, dm, cfg, refine_mask=refine)
    mask = _pixel_inliers(fit.inliers, masks, (h, w))
    return _assemble(fit, cfg, n_points=n_ok, valid_fraction=valid_fraction, inlier_mask=mask,
                     coverage=image_coverage(mask, cfg), n_frames=len(seq))
