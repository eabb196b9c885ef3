"""Gauss-Newton passes of the range model over camera-frame points (float32, in place), from a start plane.

A scale from below, reweighting passes on a subsample until converged, then the answer:
two passes over every point (the second from the first's plane), the sandwich covariance
and the radial bias. Method and rationale: docs/adr/0007-full-frame-fit.md ("Model",
"Weighting", "Robustness", "Uncertainty").
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from statistics import NormalDist  # not scipy.special: its 0.2 s import is off calibrate's start-up
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from cellcal.core.geometry.planes import Plane
from cellcal.core.methods.fullframe.points import KEEP_POINTS, kept_array
from cellcal.core.methods.fullframe.settings import MIN_POINTS, FullFrameSettings
from cellcal.core.methods.fullframe.space import Model, SpaceFit
from cellcal.devices.errors import CalibrationError

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
F32 = NDArray[np.float32]

__all__ = ["Cutoff", "FinalPass", "KeepMask", "Model", "NothingLeftError", "Pass", "Scratch", "basis", "final_pass",
           "fit_from_start", "gn_pass", "step_plane", "truncation"]

#: Passes over every point (the second from the first one's plane).
FINAL_PASSES = 2


class KeepMask(Protocol):
    """``(inliers, whitened residuals) -> points allowed to stay inliers`` (image-space clean-up).

    Attributes:
        scale: Robust scale of the whitened residuals, set before each pass over every point.
    """

    scale: float

    def __call__(self, inliers: BoolArray, z: F32) -> BoolArray:
        """The points allowed to stay inliers."""
        ...

_SQRT_2PI = math.sqrt(2.0 * math.pi)


class NothingLeftError(CalibrationError):
    """The edge clean-up left fewer than ``MIN_POINTS`` inliers (the caller names the gate).

    Attributes:
        n_points: Points of the pass; n_near: near the plane; n_left: left after the clean-up.
    """

    def __init__(self, n_points: int, n_near: int, n_left: int) -> None:
        self.n_points, self.n_near, self.n_left = n_points, n_near, n_left
        super().__init__(_few_inliers(n_points, n_near, n_left, True))


def basis(n: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Two unit vectors completing the unit vector ``n`` to a right-handed orthonormal basis."""
    x, y, z = float(n[0]), float(n[1]), float(n[2])
    # e1 = normalise(ex - x n), or normalise(ey - y n) when n is close to ex
    e1 = np.array([1.0 - x * x, -x * y, -x * z]) if abs(x) < 0.8 else np.array([-y * x, 1.0 - y * y, -y * z])
    e1 /= math.sqrt(float(e1 @ e1))
    a, b, c = float(e1[0]), float(e1[1]), float(e1[2])
    return e1, np.array([y * c - z * b, z * a - x * c, x * b - y * a])   # e2 = n x e1


def truncation(c: float) -> tuple[float, float]:
    """For a Gaussian cut at ``±c`` sigma: (variance factor of the kept part, covariance factor).

    The first divides the inlier mean square to estimate sigma^2; the second multiplies
    the sandwich covariance of the hard-rejection estimator (its derivative loses the
    ``2 c phi(c)`` of the points crossing the cut).
    """
    p = math.erf(c / math.sqrt(2.0))                        # kept probability 2 Phi(c) - 1
    jump = 2.0 * c * math.exp(-0.5 * c * c) / _SQRT_2PI     # 2 c phi(c)
    kept_var = (p - jump) / p                               # E[z^2 | |z| < c]
    bread = p - jump
    return kept_var, (p / bread) ** 2 if bread > 0 else 1.0


def step_plane(n: FloatArray, e1: FloatArray, e2: FloatArray, offset: float, step: FloatArray
               ) -> tuple[FloatArray, float]:
    """Apply a step ``(d_e1, d_e2, d_offset)``: the new unit normal and offset."""
    n_new = n + step[0] * e1 + step[1] * e2                 # tangent move of the normal ...
    return n_new / np.linalg.norm(n_new), offset + float(step[2])   # ... back onto the sphere


@dataclass(frozen=True)
class Cutoff:
    """Hard inlier cut-off on the normalised range residual: ``k_sig`` scales, within [lo, hi]."""

    k_sig: float
    lo: float                 # min_inlier_threshold_m at the median pixel's noise
    hi: float                 # max_inlier_threshold_m at the median pixel's noise
    kept_var: float           # variance factor of a Gaussian cut at ±k_sig (see truncation)
    cov_factor: float         # covariance factor of the hard-rejection estimator

    def at(self, scale: float) -> float:
        """The cut-off for a robust scale ``scale`` of the normalised residuals."""
        return min(max(self.k_sig * scale, self.lo), self.hi)


@dataclass
class Pass:
    """Sums of one Gauss-Newton pass over a point set."""

    step: FloatArray          # (d_e1, d_e2, d_offset)
    hessian: FloatArray       # J^T W J
    n_inliers: int
    z2_sum: float             # sum of squared normalised residuals of the inliers


@dataclass
class FinalPass(Pass):
    """The last pass over every point: also the sandwich meat, the residual sums and the inliers."""

    meat: FloatArray          # sum (w rho)^2 J J^T
    ortho2_sum: float         # sum of squared orthogonal residuals of the inliers, m^2
    model_ortho2_sum: float   # sum over the inliers of the squared orthogonal noise shape
    inliers: BoolArray
    radial: tuple[FloatArray, FloatArray]   # (4x4 J^T W J, J^T W rho) with the radial column
    z: F32 | None = None      # whitened residuals, 0 off the inliers (the answer pass; a scratch row)


class Scratch:
    """Point-sized float32 rows reused by the passes over every point of one fit.

    Fresh point-sized temporaries cost page faults (the allocator returns large blocks to
    the system when they are freed and the next pass touches new pages): with these rows
    allocated once per fit, the passes compute the same values in place.
    """

    ROWS = 8

    def __init__(self, n: int) -> None:
        self.f = np.empty((self.ROWS, n), dtype=np.float32)
        self.mask = np.empty(n, dtype=np.bool_)

    @classmethod
    def shared(cls, n: int) -> Scratch:
        """Rows for ``n`` points over one block of memory that this thread's fits keep between fits.

        See :func:`~cellcal.core.methods.fullframe.points.kept_array`; fits of more than ``KEEP_POINTS``
        allocate their own (the allocator keeps blocks that large in the heap). The rows are valid
        until the thread's next fit.
        """
        if n > KEEP_POINTS:
            return cls(n)
        out = cls.__new__(cls)
        out.f = kept_array("scratch", cls.ROWS * n, np.float32).reshape(cls.ROWS, n)   # C-contiguous rows
        out.mask = kept_array("scratch_mask", n, np.bool_)
        return out


def residuals(b0: F32, dm: F32, offset: float, thr: float, model: Model, scratch: Scratch | None = None
              ) -> tuple[F32, F32, F32, F32 | None, BoolArray]:
    """Whitened range residuals of points with ``b0 = p·n`` (N,) and ranges ``dm``.

    Returns ``1/cos``, the predicted range ``t``, the whitened residual ``z``, the
    inverse sigma (None when unweighted) and the inlier mask ``|z| < thr`` (in front).
    With ``scratch`` the first four live in its rows 0-3 (row 4 is used and left free).
    """
    f32 = np.float32
    buf = scratch or Scratch(dm.size)
    inv_c = np.divide(dm, b0, out=buf.f[0])    # 1 / cos(ray, normal), negative in front
    t = np.multiply(inv_c, f32(-offset), out=buf.f[1])   # predicted range along the ray
    z = np.subtract(dm, t, out=buf.f[2])       # range residual rho ...
    if model.sigma is not None:
        isig: F32 | None = np.divide(f32(1.0), model.sigma, out=buf.f[3])
    elif model.weighted:                       # 1 / (t^e / sqrt|cos|)
        isig = np.multiply(t, inv_c, out=buf.f[3])
        np.abs(isig, out=isig)
        np.sqrt(isig, out=isig)
        if model.exponent != 1.5:              # |t|^(e - 1) as exp((e - 1) log|t|): float32 pow is 2x slower
            tmp = np.abs(t, out=buf.f[4])
            np.log(tmp, out=tmp)
            tmp *= f32(model.exponent - 1.0)
            np.exp(tmp, out=tmp)
            isig *= tmp
        isig *= t
        np.divide(f32(1.0), isig, out=isig)
    else:
        isig = None
    if isig is not None:
        z *= isig                              # ... whitened
    inl = np.less(np.abs(z, out=buf.f[4]), f32(thr))   # inliers: within the cut-off ...
    inl &= np.greater(t, 0, out=buf.mask)      # ... and the plane in front along the ray
    return inv_c, t, z, isig, inl


def gram(cols: Sequence[F32]) -> FloatArray:
    """Symmetric matrix of the dot products of the columns (float64 sums)."""
    k = len(cols)
    out = np.empty((k, k))
    for i in range(k):
        for j in range(i, k):
            out[i, j] = out[j, i] = float(np.dot(cols[i], cols[j]))
    return out


def _solve(h: FloatArray, g: FloatArray) -> FloatArray:
    try:
        return np.asarray(-np.linalg.solve(h, g), dtype=np.float64)   # Gauss-Newton step
    except np.linalg.LinAlgError:
        raise CalibrationError("full-frame fit is degenerate: the inliers do not span a plane") from None


def _columns(b: F32, dm: F32, inv_c: F32, t: F32, isig: F32, out: F32 | None = None) -> tuple[F32, F32, F32]:
    """Whitened, masked Jacobian columns (t and inv_c reused in place, the first in ``out``); ``isig`` masked."""
    t *= inv_c
    t /= dm
    t *= isig                                  # q = t / (|p| cos) / sigma
    a1 = np.multiply(t, b[1], out=out)
    a2 = np.multiply(t, b[2], out=t)
    a3 = np.multiply(inv_c, isig, out=inv_c)
    return a1, a2, a3


def _projections(p: F32, n: FloatArray, e1: FloatArray, e2: FloatArray, out: F32 | None = None) -> F32:
    """(3, N) float32: p·n, p·e1, p·e2 (into ``out`` when given)."""
    return np.matmul(np.stack([n, e1, e2]).astype(np.float32), p, out=out)


def _mask_weights(z: F32, isig: F32 | None, inl: BoolArray, scratch: Scratch) -> F32:
    """Residuals and inverse sigmas of the outliers set to 0 (in place); the masked inverse sigmas."""
    z *= inl
    if isig is not None:
        return np.multiply(isig, inl, out=isig)
    ones: F32 = scratch.f[3]                   # unweighted: the mask as float32 weights
    ones[...] = inl
    return ones


def gn_pass(p: F32, dm: F32, n: FloatArray, e1: FloatArray, e2: FloatArray, offset: float,
            thr: float, model: Model, scratch: Scratch | None = None) -> Pass:
    """One reweighted Gauss-Newton pass of the range model over points ``p`` (3, N).

    The range along the ray ``r = p / |p|`` predicted by the plane is
    ``t = -offset / (r·n)``; the residual ``rho = |p| - t`` has the Jacobian
    ``(t (r·e1) / (r·n), t (r·e2) / (r·n), 1 / (r·n))`` with respect to the normal's
    tangent steps along ``e1``, ``e2`` and the offset. Everything is whitened by the
    point's noise sigma and masked to the inliers, in place on a few float32 buffers
    (``scratch``'s rows, reused by the passes of one fit, when given).
    """
    buf = scratch or Scratch(dm.size)
    b = _projections(p, n, e1, e2, out=buf.f[5:8])
    inv_c, t, z, isig, inl = residuals(b[0], dm, offset, thr, model, buf)
    n_in = int(np.count_nonzero(inl))
    if n_in < MIN_POINTS:
        raise CalibrationError(f"full-frame fit: only {n_in} of {dm.size} points lie near the start plane; "
                               "no plane is defined")
    isig = _mask_weights(z, isig, inl, buf)
    cols = _columns(b, dm, inv_c, t, isig, out=buf.f[4])
    h = gram(cols)
    g = np.array([float(np.dot(c, z)) for c in cols])   # J^T W rho
    return Pass(_solve(h, g), h, n_in, float(np.dot(z, z)))


def final_pass(p: F32, dm: F32, n: FloatArray, e1: FloatArray, e2: FloatArray, offset: float,
               thr: float, model: Model, keep: KeepMask | None, *, answer: bool = True,
               scratch: Scratch | None = None) -> FinalPass:
    """The pass over every point: step, sandwich meat, inliers, residual sums and the radial column.

    ``keep`` (if given) sees the inlier mask and the whitened residuals (units of the noise
    model) and returns the points allowed to stay.
    The radial column is the squared image radius ``(x² + y²) / z²`` of each point over its
    largest value: a range bias growing toward the border (ADR 0007, "Multipath").
    Without ``answer`` (a pass whose plane only starts the next one) only the step, the
    Hessian, the inliers and the scale's sum are formed; the rest is zero. ``scratch``
    (rows for ``p.shape[1]`` points) is reused by the passes of one fit.
    """
    buf = scratch or Scratch(dm.size)
    b = _projections(p, n, e1, e2, out=buf.f[5:8])
    inv_c, t, z, isig, inl = residuals(b[0], dm, offset, thr, model, buf)
    n_near = int(np.count_nonzero(inl))
    if keep is not None:
        inl &= keep(inl, z)                    # image-space clean-up of the inliers
    n_in = int(np.count_nonzero(inl))
    if n_in < MIN_POINTS:
        if keep is not None and n_near >= MIN_POINTS:
            raise NothingLeftError(dm.size, n_near, n_in)
        raise CalibrationError(_few_inliers(dm.size, n_near, n_in, keep is not None))
    unweighted_shape = _model_shape(t, inv_c, model, inl) if isig is None and answer else None
    isig = _mask_weights(z, isig, inl, buf)
    if not answer:                             # a start for the next pass: step, Hessian, scale only
        cols = _columns(b, dm, inv_c, t, isig, out=buf.f[4])
        h = gram(cols)
        g = np.array([float(np.dot(c, z)) for c in cols])
        return FinalPass(_solve(h, g), h, n_in, float(np.dot(z, z)), np.zeros((3, 3)), 0.0, 0.0, inl,
                         (np.zeros((4, 4)), np.zeros(4)))
    return _answer_sums(p, dm, b, (inv_c, t, z, isig), inl, offset, n_in, unweighted_shape, buf)


def _answer_sums(p: F32, dm: F32, b: F32, rows: tuple[F32, F32, F32, F32], inl: BoolArray, offset: float,
                 n_in: int, unweighted_shape: float | None, buf: Scratch) -> FinalPass:
    """The answer pass's sums from the masked residuals: step, Hessian, meat, radial column, residual sums."""
    f32 = np.float32
    inv_c, t, z, isig = rows
    cols = _columns(b, dm, inv_c, t, isig, out=buf.f[4])   # rows 4, 1, 0; rows 6 (p·e1) and 7 (p·e2) free
    rad = np.divide(dm, p[2], out=buf.f[7])
    np.square(rad, out=rad)
    rad -= f32(1.0)                            # squared image radius (x² + y²) / z² = |p|² / z² - 1
    rad *= np.divide(isig, f32(max(float(rad.max()), 1e-12)), out=isig)   # isig is in a3 already
    h4 = gram((*cols, rad))
    g4 = np.array([float(np.dot(c, z)) for c in (*cols, rad)])
    meat = gram([np.multiply(c, z, out=buf.f[k]) for k, c in zip((3, 6, 7), cols, strict=True)])
    if unweighted_shape is None:               # sum (w rho)^2 J J^T above; orthogonal noise shape sigma |cos| = 1 / a3
        inv_a3 = buf.f[3]
        inv_a3.fill(0.0)
        np.divide(f32(1.0), cols[2], out=inv_a3, where=inl)
        model_ortho2 = float(np.dot(inv_a3, inv_a3))
    else:
        model_ortho2 = unweighted_shape
    ortho = np.add(b[0], f32(offset), out=b[1])           # orthogonal residual p·n + offset ...
    ortho *= inl                                          # ... of the inliers
    return FinalPass(_solve(h4[:3, :3], g4[:3]), h4[:3, :3].copy(), n_in, float(np.dot(z, z)), meat,
                     float(np.dot(ortho, ortho)), model_ortho2, inl, (h4, g4), z)


def _model_shape(t: F32, inv_c: F32, model: Model, inl: BoolArray) -> float:
    """Sum over the inliers of the squared orthogonal noise shape ``t^e sqrt|cos|`` (unweighted fits)."""
    f32 = np.float32
    out = np.abs(t) ** f32(model.exponent)
    out /= np.sqrt(np.abs(inv_c))
    out *= inl
    return float(np.dot(out, out))


def _few_inliers(n_points: int, n_near: int, n_left: int, edge: bool) -> str:
    """What happened when too few inliers are left for a plane."""
    if n_near >= MIN_POINTS and edge:
        return (f"full-frame fit: {n_points} valid pixels, {n_near} near the plane, {n_left} left after the "
                "edge margin (pixels next to invalid or off-plane patches, edge_margin_deg); no plane is defined")
    return f"full-frame fit: {n_points} valid points, only {n_near} near the plane; no plane is defined"


# ---------------------------------------------------------------------- from a start to the answer
def fit_from_start(p: F32, dm: F32, model: Model, settings: FullFrameSettings, n: FloatArray, offset: float,
                   keep: KeepMask | None = None) -> SpaceFit:
    """From a start plane (unit normal ``n``, ``offset``) to the answer, on points ``p`` (3, N) with ranges ``dm``.

    A scale from below on a strided subsample, passes there until converged, then the passes
    over every point. ``keep`` maps the inlier mask (N,) and the residuals of the converged
    plane to the points allowed in the last pass (image-space clean-up, see ``edge_margin_deg``).
    """
    if model.sigma is None:                                    # strided subsample for the passes
        ps, ds = _subsample(settings.refine_points, p, dm)
        sub = model
    else:
        ps, ds, ss = _subsample(settings.refine_points, p, dm, model.sigma)
        sub = replace(model, sigma=ss)
    s, cutoff = initial_scale(ps, ds, sub, n, offset, settings)
    n, offset, s = refine(ps, ds, sub, n, offset, s, cutoff, settings)
    return _final(p, dm, model, n, offset, s, cutoff, keep)


def _subsample(limit: int, *arrays: F32) -> list[F32]:
    """Every k-th point (last axis; contiguous copies) so that at most ``limit`` remain."""
    step = -(-arrays[0].shape[-1] // limit)
    if step <= 1:
        return list(arrays)
    return [np.ascontiguousarray(a[..., ::step]) for a in arrays]


def initial_scale(p: F32, dm: F32, model: Model, n: FloatArray, offset: float,
                  settings: FullFrameSettings) -> tuple[float, Cutoff]:
    """A scale at or below the noise's, from the start plane's residuals, and the cut-off.

    The ``q`` quantile of |z| is divided by the Gaussian quantile of ``q / 0.5``: exact when
    half of the points are inliers (the least the inlier gate accepts), an underestimate
    when more are. The passes then grow it to the smallest self-consistent scale.
    """
    k0 = max(1, p.shape[1] // 1024)
    p0, d0 = p[:, ::k0], dm[::k0]
    inv_c = d0 / (n.astype(np.float32) @ p0)   # 1 / cos(ray, normal)
    t = inv_c * np.float32(-offset)            # predicted range along the ray
    z = d0 - t                                 # range residual ...
    sig_med = 1.0
    if model.sigma is not None or model.weighted:
        if model.sigma is not None:
            sig = model.sigma[::k0]
        else:                                  # ... or by the noise model t^e / sqrt|cos|
            sig = (np.abs(t) ** np.float32(model.exponent) / np.sqrt(np.abs(inv_c))).astype(np.float32)
        z /= sig                               # ... normalised
        mid = sig.size // 2
        sig_med = max(float(np.partition(sig, mid)[mid]), 1e-12)   # median pixel's sigma
    q = settings.hypothesis_quantile
    az = np.abs(z)
    kq = min(int(q * az.size), az.size - 1)
    level = min(q / 0.5, 0.98)
    s = float(np.partition(az, kq)[kq]) / NormalDist().inv_cdf(0.5 + level / 2.0)   # |z| quantile -> Gaussian sigma
    k_sig = settings.inlier_threshold_sigma
    kept_var, cov_factor = truncation(k_sig)
    cutoff = Cutoff(k_sig, settings.min_inlier_threshold_m / sig_med, settings.max_inlier_threshold_m / sig_med,
                    kept_var, cov_factor)
    return s, cutoff


def _converged(it: Pass, s: float, s_new: float, floor_scale: float) -> bool:
    """The step is a small fraction of the parameters' (subsample) sigma and the scale has settled.

    Noise-free data: the cut-off sits at its floor (``floor_scale``) and the scale never settles
    in relative terms. The full-data pass after the loop finishes the job.
    """
    try:
        sd = np.sqrt(np.abs(np.diag(np.linalg.inv(it.hessian)))) * max(s_new, floor_scale)   # parameter sigmas
    except np.linalg.LinAlgError:
        sd = np.full(3, np.inf)
    settled = abs(s_new - s) <= 0.01 * s or max(s, s_new) <= floor_scale
    return bool(np.all(np.abs(it.step) <= 0.1 * sd)) and settled


def refine(p: F32, dm: F32, model: Model, n: FloatArray, offset: float, s: float, cutoff: Cutoff,
           settings: FullFrameSettings) -> tuple[FloatArray, float, float]:
    """Reweighted Gauss-Newton passes (on the subsample) until converged: normal, offset, scale."""
    e1, e2 = basis(n)
    scratch = Scratch.shared(dm.size)                           # rows reused by every pass
    for _ in range(settings.max_iterations):
        it = gn_pass(p, dm, n, e1, e2, offset, cutoff.at(s), model, scratch)
        n, offset = step_plane(n, e1, e2, offset, it.step)
        e1, e2 = basis(n)
        s_new = math.sqrt(it.z2_sum / it.n_inliers / cutoff.kept_var)   # inlier RMS, truncation-corrected
        converged = _converged(it, s, s_new, cutoff.lo / cutoff.k_sig)
        s = s_new
        if converged:
            break
    return n, offset, s


def _final(p: F32, dm: F32, model: Model, n: NDArray[np.float64], offset: float, s: float, cutoff: Cutoff,
           keep: KeepMask | None) -> SpaceFit:
    """Passes over every point: plane, sandwich covariance, inliers, RMS, scale, multipath.

    The second pass starts from the first one's full-data plane and scale, so that the
    inliers and the edge clean-up of the answer do not depend on where the start was.
    """
    scratch = Scratch.shared(dm.size)                          # point-sized rows reused by both passes
    for k in range(FINAL_PASSES):
        e1, e2 = basis(n)
        if keep is not None:
            keep.scale = s
        fin: FinalPass = final_pass(p, dm, n, e1, e2, offset, cutoff.at(s), model, keep,
                                    answer=k == FINAL_PASSES - 1, scratch=scratch)
        n_fin, offset_fin = step_plane(n, e1, e2, offset, fin.step)
        s = math.sqrt(fin.z2_sum / fin.n_inliers / cutoff.kept_var)   # truncation-corrected scale
        if k < FINAL_PASSES - 1:
            n, offset = n_fin, offset_fin
    try:
        h_inv = np.linalg.inv(fin.hessian)
        h4_inv = np.linalg.inv(fin.radial[0])
    except np.linalg.LinAlgError:
        raise CalibrationError("full-frame fit is degenerate: the inliers do not span a plane") from None
    dof = max(fin.n_inliers - 3, 1)
    # sandwich H^-1 M H^-1, small-sample factor n / (n - 3), hard-rejection correction
    cov = h_inv @ fin.meat @ h_inv * (fin.n_inliers / dof) * cutoff.cov_factor
    rms = math.sqrt(fin.ortho2_sum / fin.n_inliers)
    unit = math.sqrt(cutoff.kept_var * fin.model_ortho2_sum / fin.n_inliers)
    step4 = -h4_inv @ fin.radial[1]                             # plane and radial range bias together
    beta_sigma = s * math.sqrt(max(float(h4_inv[3, 3]), 0.0) * cutoff.cov_factor)
    return SpaceFit(Plane(n_fin, offset_fin), cov, e1, e2, fin.inliers, rms, s, unit,
                    (-float(step4[3]), beta_sigma, step4[:3] - fin.step), fin.z)

