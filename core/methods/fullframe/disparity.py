"""The full-frame fit of a stereo or structured-light camera, in its native space: disparity.

For a rectified pinhole pair a plane ``n·X + c = 0`` is an affine function of disparity over
the normalised image coordinates ``(x/z, y/z)``: with ``d = f·B / Z``,
``d = α·x/z + β·y/z + γ`` and ``(α, β, γ) = -(f·B / c)·n``. Disparity noise is homoscedastic
(plus the rounding to ``2^-bits`` px, Sheppard's ``q²/12``), so the fit is ordinary least
squares on the inliers, with an inlier band never narrower than one quantisation step.
The plane is reported in metres like the range fit. Rationale: docs/adr/0027-measurement-model.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from numpy.typing import NDArray

from cellcal.core.geometry.planes import Plane
from cellcal.core.methods.fullframe.honesty import disparity_lattice
from cellcal.core.methods.fullframe.passes import basis, truncation
from cellcal.core.methods.fullframe.points import FIXED_SEED, ExpectedPlane, Nearness, Points, Sample, fixed_subsample
from cellcal.core.methods.fullframe.settings import MIN_POINTS, FullFrameSettings
from cellcal.core.methods.fullframe.space import Floors, Model, SpaceFit
from cellcal.core.methods.fullframe.systematic import Response, pixel_uv
from cellcal.devices.errors import CalibrationError, CalibrationQualityError
from cellcal.devices.measurement import MeasurementModel
from cellcal.devices.readable import quantity_pair

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
F32 = NDArray[np.float32]

__all__ = ["DISTANCE_EXPONENT", "DisparityFit", "DisparitySpace", "design_effect", "disparity_lattice", "fit_disparity"]

#: Depth noise of a disparity camera grows as Z² (σ_Z = Z²/(f·B)·σ_d): the range exponent it implies.
DISTANCE_EXPONENT = 2.0
#: Sides of the pixel blocks whose mean residuals measure the spatial correlation, px (the largest factor counts).
BLOCK_PX = (8, 16, 32)
#: Blocks needed at a scale for its estimate to count.
MIN_BLOCKS = 8
#: A block counts for the correlation estimate when at least this fraction of its pixels are inliers.
BLOCK_MIN_FILL = 0.5
#: Share of the rounding's systematic amplitude left after its expected pattern is removed (the
#: pattern's phase comes from the fitted, not the true, disparity and its size from an estimated
#: sigma): kept in the intervals. Set on simulated planes with 0.1-0.5 px noise, integer steps.
RESIDUAL_ROUNDING_SHARE = 0.5
#: Re-fits on the inliers at most (the inlier set of an affine model settles in a few).
MAX_REFITS = 30
#: Unknown disparity noise: the effective sigma is estimated, but never below the rounding alone.
RESIDUAL_FLOOR_NOTE = "disparity sigma not stated: estimated from the residuals (never below the rounding's q/sqrt(12))"


@dataclass(frozen=True)
class DisparityFit:
    """A plane fitted in disparity space, in the shape the shared assembly of the full-frame fit takes.

    Attributes:
        plane: The plane, camera frame, normal toward the camera, metres.
        cov: 3x3 covariance of the plane's steps ``(d_e1, d_e2, d_offset)`` (rad, rad, m), with
            ``e1, e2 = basis(plane.normal)``; inflated by the observed scale and the spatial correlation.
        e1, e2: The tangent basis of ``cov``.
        inliers: (N,) bool, points within the inlier band.
        residual_rms_m: RMS orthogonal distance of the inliers to the plane, metres.
        expected_rms_m: The RMS the disparity model predicts for those inliers, metres.
        floor_rms_m: The part of it due to the rounding alone (``q/sqrt(12)``), metres.
        noise_scale_m: Depth-noise sigma at Z = 1 m implied by the disparity sigma used,
            ``sigma_d / (f·B)``, metres (range exponent :data:`DISTANCE_EXPONENT`).
        notes: What widened the intervals, and why, in short sentences.
        disparity: ``(α, β, γ)`` px, the affine disparity plane over ``(x/z, y/z)``.
        disparity_cov: Its 3x3 covariance, px².
        residual_rms_px: RMS disparity residual of the inliers, px.
        sigma_used_px: The disparity sigma the covariance is scaled by, px.
        design_effect: Variance factor of the spatial correlation (>= 1).
        band_px: The inlier band ``|r| < band_px``, px.
    """

    plane: Plane
    cov: FloatArray
    e1: FloatArray
    e2: FloatArray
    inliers: BoolArray
    residual_rms_m: float
    expected_rms_m: float
    floor_rms_m: float
    noise_scale_m: float
    notes: tuple[str, ...]
    disparity: FloatArray
    disparity_cov: FloatArray
    residual_rms_px: float
    sigma_used_px: float
    design_effect: float
    band_px: float


# ---------------------------------------------------------------------- conversions
def plane_from_disparity(v: FloatArray, fb_px_m: float) -> Plane:
    """The metric plane of the disparity plane ``v = (α, β, γ)`` (px) of a camera with ``f·B`` (px·m)."""
    norm = float(np.linalg.norm(v))
    return Plane(-v / norm, fb_px_m / norm)            # n = -v/|v|, c = f·B/|v| > 0: toward the camera


def disparity_from_plane(plane: Plane, fb_px_m: float) -> FloatArray:
    """``(α, β, γ)`` (px) of a metric plane (normal toward the camera, offset > 0)."""
    n = np.asarray(plane.normal, dtype=np.float64)
    return -(fb_px_m / plane.offset_m) * n


def _tangent_jacobian(v: FloatArray, fb_px_m: float, e1: FloatArray, e2: FloatArray) -> FloatArray:
    """d(d_e1, d_e2, d_offset)/d(α, β, γ) at ``v``: rows ``-e1/|v|``, ``-e2/|v|``, ``f·B n/|v|²``."""
    norm = float(np.linalg.norm(v))
    n = -v / norm
    return np.stack([-e1 / norm, -e2 / norm, fb_px_m * n / norm**2])


# ---------------------------------------------------------------------- statistics
def design_effect(residuals: FloatArray, pixel_index: NDArray[np.intp], shape: tuple[int, int],
                  block_px: tuple[int, ...] = BLOCK_PX) -> float:
    """Variance factor of spatially correlated residuals: ``mean(n_k m_k²) / mean(r²)`` over pixel blocks.

    For independent residuals the mean ``m_k`` of the ``n_k`` residuals of a block has variance
    ``σ²/n_k``, so the ratio is 1; correlated ones (block matching, a rounding pattern, the same
    pixel pooled from several frames of a static scene) average less and raise it. Several block
    sizes are tried, since a rounding pattern on a nearly frontal plane is correlated over long
    distances, and the largest factor is kept; blocks less than half full are skipped, and a
    size with fewer than :data:`MIN_BLOCKS` blocks does not count. Returns at least 1.

    Args:
        residuals: (N,) residuals of the inliers (any unit).
        pixel_index: (N,) flat pixel index (row-major in ``shape``) of each residual.
        shape: ``(H, W)`` of the image.
        block_px: Sides of the square blocks tried, px.
    """
    h, w = shape
    var = float(np.mean(residuals * residuals))
    if var <= 0.0:
        return 1.0
    rows, cols = np.divmod(pixel_index, w)
    best = 1.0
    for b in block_px:
        n_bc = -(-w // b)
        block = (rows // b) * n_bc + cols // b                 # block id of each residual
        n_blocks = (-(-h // b)) * n_bc
        count = np.bincount(block, minlength=n_blocks)
        total = np.bincount(block, weights=residuals, minlength=n_blocks)
        full = count >= BLOCK_MIN_FILL * b * b                 # well-filled blocks only
        if np.count_nonzero(full) < MIN_BLOCKS:
            continue
        mean = total[full] / count[full]
        best = max(best, float(np.mean(count[full] * mean * mean)) / var)   # E[n m²] / σ²
    return best


def rounding_bias_px(sigma_d_px: float, step_px: float) -> float:
    """Largest mean error of rounding a disparity with Gaussian noise ``sigma_d_px`` to ``step_px``, px.

    The rounding error's mean, as a function of where the true value falls between two
    levels, is a periodic pattern whose first harmonic has the amplitude
    ``(q/π)·exp(-2π²σ²/q²)``: negligible once the noise dithers the rounding (σ >= q/2), up to
    ``q/π`` without noise. Averaging more pixels does not reduce it.
    """
    return step_px / math.pi * math.exp(-2.0 * math.pi**2 * (sigma_d_px / step_px) ** 2)


def rounding_mean_px(d_px: FloatArray, sigma_d_px: float, step_px: float, harmonics: int = 4) -> FloatArray:
    """Mean error of rounding ``d + noise`` to ``step_px`` at true disparities ``d_px``, px.

    The rounding error of a value ``x`` is the sawtooth ``(q/π) Σ_k ((-1)^k / k) sin(2πk x/q)``;
    Gaussian noise ``σ`` damps its ``k``-th harmonic by ``exp(-2π²k²σ²/q²)``.
    """
    out = np.zeros_like(d_px, dtype=np.float64)
    w = 2.0 * math.pi / step_px
    for k in range(1, harmonics + 1):
        damp = math.exp(-2.0 * (math.pi * k * sigma_d_px / step_px) ** 2)
        if damp < 1e-9:
            break
        out += (step_px / math.pi) * ((-1.0) ** k / k) * damp * np.sin(k * w * d_px)
    return out


def _solve(ata: FloatArray, atd: FloatArray) -> tuple[FloatArray, FloatArray]:
    """``v = (aᵀa)⁻¹ aᵀd`` and ``(aᵀa)⁻¹`` from the normal equations."""
    try:
        inv = np.asarray(np.linalg.inv(ata), dtype=np.float64)
    except np.linalg.LinAlgError:
        raise CalibrationError("full-frame fit is degenerate: the inliers do not span a plane") from None
    v: FloatArray = inv @ atd
    return v, inv


class _Normal:
    """The normal equations of ``d ≈ α x + β y + γ`` over any inlier mask, from 9 per-point products.

    One (N, 9) matrix of ``x², xy, x, y², y, 1, xd, yd, d`` is formed once; a mask's normal
    equations are then one matrix-vector product, not a gather of the inliers per re-fit.
    """

    def __init__(self, a: FloatArray, d: FloatArray) -> None:
        x, y = a[:, 0], a[:, 1]
        self.prods = np.stack([x * x, x * y, x, y * y, y, np.ones_like(x), x * d, y * d, d], axis=1)

    def solve(self, mask: BoolArray) -> tuple[FloatArray, FloatArray]:
        """``v`` and ``(aᵀa)⁻¹`` of the points in ``mask``."""
        s = mask.astype(np.float64) @ self.prods               # masked sums of the products
        ata = np.array([[s[0], s[1], s[2]], [s[1], s[3], s[4]], [s[2], s[4], s[5]]])
        return _solve(ata, s[6:9])


# ---------------------------------------------------------------------- the fit
def _start(a: FloatArray, d: FloatArray, band: float, settings: FullFrameSettings, fb: float,
           expected: ExpectedPlane | None) -> FloatArray:
    """The best triplet plane in disparity space by truncated squared residuals (MSAC) on a fixed subsample."""
    idx = fixed_subsample(d.size, settings.sample_points)
    sub_a, sub_d = a[idx], d[idx]
    rng = np.random.default_rng(FIXED_SEED if settings.seed is None else settings.seed)
    trip = rng.integers(0, idx.size, size=(settings.hypotheses, 3))
    mats = sub_a[trip]                                          # (K, 3, 3): rows (x/z, y/z, 1)
    rhs = sub_d[trip]                                           # (K, 3)
    ok = np.abs(np.linalg.det(mats)) > 1e-12                    # drop collinear triplets
    if not ok.any():
        raise CalibrationError("full-frame fit: the points are collinear or coincident; no plane is defined")
    hyp = np.linalg.solve(mats[ok], rhs[ok][..., None])[..., 0]   # (K', 3) disparity planes
    hyp = hyp[np.linalg.norm(hyp, axis=1) > 0]
    if expected is not None:                                     # only planes near the one the user means
        size = np.linalg.norm(hyp, axis=1)
        near = expected.within(-hyp / size[:, None], fb / size)   # metric planes: n = -v/|v|, c = f·B/|v|
        if not near.ok.any():
            _refuse_expected(near, hyp, sub_a, sub_d, band, expected)
        hyp = hyp[near.ok]
    res = sub_d[None, :] - hyp @ sub_a.T                         # (K', m) residuals, px
    loss = np.minimum(res * res, band * band).sum(axis=1)       # truncated quadratic (MSAC)
    return np.asarray(hyp[int(np.argmin(loss))], dtype=np.float64)


def _refuse_expected(nearness: Nearness, hyp: FloatArray, a: FloatArray, d: FloatArray, band: float,
                     expected: ExpectedPlane) -> None:
    """No hypothesis near the expected plane: name the gate and the best plane that was found instead."""
    res = d[None, :] - hyp @ a.T
    best = int(np.argmin(np.minimum(res * res, band * band).sum(axis=1)))
    angle, offset = float(nearness.angle_rad[best]), float(nearness.offset_m[best])
    shown_a, tol_a = quantity_pair(angle, expected.angle_tolerance_rad, "rad")
    shown_o, tol_o = quantity_pair(offset, expected.offset_tolerance_m, "m")
    raise CalibrationQualityError(
        "expected_plane", angle, expected.angle_tolerance_rad,
        f"no plane within {tol_a} and {tol_o} of the expected one; the dominant plane found is {shown_a} and "
        f"{shown_o} away from it", unit="rad")


def fit_disparity(p: F32, pixel_index: NDArray[np.intp], shape: tuple[int, int], model: MeasurementModel,
                  settings: FullFrameSettings, expected: ExpectedPlane | None = None) -> DisparityFit:
    """Fit the plane of a stereo or structured-light camera's points in disparity space.

    Args:
        p: (3, N) float32 camera-frame points (OpenCV frame, metres), z > 0.
        pixel_index: (N,) flat pixel index of each point within its frame (frames share ``shape``).
        shape: ``(H, W)`` of the frames, px.
        model: The camera's measurement model (``triangulating``: baseline, focal, subpixel bits).
        settings: ``inlier_threshold_sigma`` (band in sigmas), ``confidence`` is applied later,
            ``hypotheses`` / ``sample_points`` / ``seed`` for the start.
        expected: Only planes within its tolerances are considered (None: the dominant plane).

    Returns:
        The plane with its covariance and residual figures (see :class:`DisparityFit`).

    Raises:
        CalibrationError: ``model`` is not a disparity model, or no plane is defined.
        CalibrationQualityError: Gate ``expected_plane`` when no plane near ``expected`` exists.
    """
    if not model.triangulating:
        raise CalibrationError(f"fit_disparity needs a stereo or structured-light model, got {model.kind!r}")
    fb = model.fb_px_m
    q = model.disparity_step_px
    a, d = _disparities(p, fb)
    stated = model.disparity_sigma_px is not None
    sigma_model = model.disparity_noise_px                      # sqrt(σ_d² + q²/12), px
    band = max(settings.inlier_threshold_sigma * sigma_model, q)   # never narrower than one step
    v = _start(a, d, band, settings, fb, expected)
    v, ata_inv, inl, sigma, band = _settle(a, d, v, band, sigma_model, settings.inlier_threshold_sigma, q)
    # ---- weakly dithered rounding: remove its expected pattern at the fitted disparities (a few passes)
    a_in = a[inl]
    sigma_d = float((model.disparity_sigma_px if stated else math.sqrt(max(sigma * sigma - q * q / 12.0, 0.0)))
                    or 0.0)
    v, r_in, b = _unround(a_in, d[inl], v, ata_inv, sigma_d, q)
    sigma_used, cov_factor, notes = _scale(r_in, band, sigma, sigma_model, stated, q)
    # ---- spatial correlation: block means of the residuals (pooled frames of a static scene count here)
    n_in = int(r_in.size)
    deff = design_effect(r_in, pixel_index[inl], shape)
    if deff > 1.05:
        notes.append(f"spatially correlated residuals: variance x{deff:.3g} (about {n_in / deff:.0f} "
                     f"independent points of {n_in})")
    cov_v = ata_inv * (sigma_used * sigma_used * deff * cov_factor)
    b *= RESIDUAL_ROUNDING_SHARE                                  # what the correction above leaves
    if b > 1e-6 * q:
        cov_v, seen = _rounding_pattern(a_in, v, ata_inv, cov_v, b, q, sigma_used * sigma_used * cov_factor, deff)
        if seen:
            notes.append(f"disparity rounding weakly dithered (sigma_d {sigma_d:.2g} px for steps of "
                         f"{q:.3g} px): its pattern removed, up to {b:.2g} px left in the intervals")
    plane, e1, e2, cov = _metric(v, fb, cov_v)
    rms_m, lever_m = _metric_residuals(plane, p[:, inl], a_in, fb)
    expected_px = sigma_model if stated else sigma_used
    return DisparityFit(
        plane=plane, cov=cov, e1=e1, e2=e2, inliers=inl, residual_rms_m=rms_m, expected_rms_m=expected_px * lever_m,
        floor_rms_m=q / math.sqrt(12.0) * lever_m,
        noise_scale_m=sigma_used / fb, notes=tuple(notes), disparity=v, disparity_cov=cov_v,
        residual_rms_px=math.sqrt(float(r_in @ r_in) / n_in), sigma_used_px=sigma_used, design_effect=deff,
        band_px=band)


def _disparities(p: F32, fb: float) -> tuple[FloatArray, FloatArray]:
    """Rows ``(x/z, y/z, 1)`` (normalised image coordinates, exact) and the measured disparity ``f·B/z`` (px)."""
    z = p[2].astype(np.float64)
    a = np.empty((z.size, 3))
    np.divide(p[0], z, out=a[:, 0])
    np.divide(p[1], z, out=a[:, 1])
    a[:, 2] = 1.0
    return a, fb / z


def _metric_residuals(plane: Plane, p_in: F32, a_in: FloatArray, fb: float) -> tuple[float, float]:
    """The inliers' RMS orthogonal residual (m) and RMS lever ``|d(orthogonal)/d(disparity)|`` (m/px)."""
    pts = p_in.astype(np.float64)
    n = np.asarray(plane.normal, dtype=np.float64)
    ortho = n @ pts + plane.offset_m                             # orthogonal residuals, m
    zin = pts[2]
    lever = zin * zin / fb * np.abs(a_in @ n)
    n_in = pts.shape[1]
    return math.sqrt(float(ortho @ ortho) / n_in), math.sqrt(float(lever @ lever) / n_in)


def _settle(a: FloatArray, d: FloatArray, v: FloatArray, band: float, sigma_model: float, k_sig: float, q: float
            ) -> tuple[FloatArray, FloatArray, BoolArray, float, float]:
    """Hard-cut least squares until the inlier set settles: ``(v, (AᵀA)⁻¹, inliers, sigma, band)``.

    The band follows the scale, which grows from the model's (or the rounding's) to the smallest
    self-consistent one (ADR 0007, "Robustness"); it is never narrower than one step ``q``.
    """
    inl = np.zeros(d.size, dtype=bool)
    sigma = sigma_model
    normal = _Normal(a, d)
    for _ in range(MAX_REFITS):
        r = d - a @ v
        new = np.abs(r) < band
        n_now = int(np.count_nonzero(new))
        if n_now < MIN_POINTS:
            raise CalibrationError(f"full-frame fit: only {n_now} of {d.size} points lie within "
                                   f"{band:.3g} px of the plane; no plane is defined")
        if np.array_equal(new, inl):
            break
        inl = new
        v, _ = normal.solve(inl)
        kept_var, _cf = truncation(band / max(sigma, 1e-12))
        r = d - a @ v
        r2 = float(np.dot(r * r, inl))                          # the inliers' squared residuals
        sigma = max(math.sqrt(r2 / max(n_now - 3, 1) / kept_var), sigma_model)   # truncation-corrected
        band = max(k_sig * sigma, q)
    v, ata_inv = normal.solve(inl)
    return v, ata_inv, inl, sigma, band


def _unround(a_in: FloatArray, d_in: FloatArray, v: FloatArray, ata_inv: FloatArray, sigma_d: float, q: float
             ) -> tuple[FloatArray, FloatArray, float]:
    """Remove the rounding's expected pattern when weakly dithered: ``(v, inlier residuals, pattern amplitude)``."""
    b = rounding_bias_px(sigma_d, q)
    if b > 1e-3 * q:
        for _ in range(3):
            mu = rounding_mean_px(a_in @ v, sigma_d, q)
            v = ata_inv @ (a_in.T @ (d_in - mu))
        d_in = d_in - mu
    return v, d_in - a_in @ v, b


def _scale(r_in: FloatArray, band: float, sigma: float, sigma_model: float, stated: bool, q: float
           ) -> tuple[float, float, list[str]]:
    """The sigma the covariance is scaled by (the model's, or the data's when larger or none is stated).

    Returns ``(sigma_used, cov_factor, notes)``: the cut estimator's variance is
    ``σ²/(N (p - 2cφ))``; ``(AᵀA)⁻¹ ≈ 1/(N p)`` is scaled by the truncation-corrected ``σ²``, so
    its factor is ``p / (p - 2cφ)``: the square root of the sandwich's factor (which multiplies
    the uncorrected inlier meat).
    """
    kept_var, sandwich_factor = truncation(band / max(sigma, 1e-12))
    cov_factor = math.sqrt(sandwich_factor)
    observed = math.sqrt(float(r_in @ r_in) / max(int(r_in.size) - 3, 1) / kept_var)   # truncation-corrected
    notes: list[str] = []
    if stated:
        sigma_used = max(sigma_model, observed)
        if observed > 1.05 * sigma_model:
            notes.append(f"disparity residuals {observed / sigma_model:.3g}x the model's "
                         f"{sigma_model:.3g} px: intervals widened by that factor")
    else:
        sigma_used = max(observed, q / math.sqrt(12.0))
        notes.append(RESIDUAL_FLOOR_NOTE)
    return sigma_used, cov_factor, notes


def _rounding_pattern(a_in: FloatArray, v: FloatArray, ata_inv: FloatArray, cov_v: FloatArray, b: float, q: float,
                      iid_scale: float, deff: float) -> tuple[FloatArray, bool]:
    """``cov_v`` with what the rounding's pattern left does to ``(α, β, γ)``, and whether it matters.

    The pattern ``b·sin(2π d/q + φ)`` of the true disparity ``d`` is systematic: no number of
    pixels averages it out. Its effect through this fit is taken as the RMS over the unknown
    phase ``φ``; the correlation factor already widened by ``(deff - 1)·iid`` (``iid``: the
    independent variance, ``diag((AᵀA)⁻¹)·iid_scale``), so only what that does not cover is added.
    """
    phase = (2.0 * math.pi / q) * (a_in @ v)                     # 2π d/q at the fitted disparity
    shift_sin = ata_inv @ (a_in.T @ np.sin(phase)) * b           # LS response to b·sin, px
    shift_cos = ata_inv @ (a_in.T @ np.cos(phase)) * b           # ... and to b·cos
    sys_var = (shift_sin**2 + shift_cos**2) / 2.0                # mean square over φ
    iid = np.diag(ata_inv) * iid_scale
    cov_v = cov_v + np.diag(np.maximum(sys_var - (deff - 1.0) * iid, 0.0))
    return cov_v, bool(np.any(sys_var > 0.1 * np.diag(cov_v)))


def _metric(v: FloatArray, fb: float, cov_v: FloatArray) -> tuple[Plane, FloatArray, FloatArray, FloatArray]:
    """The metric plane of ``v``, its tangent basis and the covariance of its steps ``(d_e1, d_e2, d_offset)``."""
    plane = plane_from_disparity(v, fb)
    e1, e2 = basis(np.asarray(plane.normal, dtype=np.float64))
    jac = _tangent_jacobian(v, fb, e1, e2)
    return plane, e1, e2, jac @ cov_v @ jac.T


# ---------------------------------------------------------------------- the space
@dataclass(frozen=True)
class DisparitySpace:
    """A stereo or structured-light camera's measurement space: :func:`fit_disparity` for the full-frame fit.

    Attributes:
        settings: The ``[full_frame]`` table.
        measurement: The camera's model (``triangulating``: baseline, focal, subpixel bits, sigma).
    """

    settings: FullFrameSettings
    measurement: MeasurementModel
    name: ClassVar[str] = "disparity"

    @property
    def noise_shape(self) -> Model:
        """Depth noise grows as Z² (:data:`DISTANCE_EXPONENT`): the flatness gate's weights."""
        return Model(self.settings.weighted, DISTANCE_EXPONENT)

    def fit(self, points: Points, expected: ExpectedPlane | None) -> SpaceFit:
        """:func:`fit_disparity` on the pooled points (each one's pixel from the frames' masks)."""
        d = fit_disparity(points.p, points.pixel_index, points.shape, self.measurement, self.settings, expected)
        no_bias = (math.nan, math.nan, np.zeros(3))              # no radial range bias in disparity space
        return SpaceFit(d.plane, np.asarray(d.cov, dtype=np.float64), np.asarray(d.e1, dtype=np.float64),
                        np.asarray(d.e2, dtype=np.float64), np.asarray(d.inliers, dtype=bool),
                        float(d.residual_rms_m), float(d.noise_scale_m), math.nan, no_bias, None,
                        float(d.expected_rms_m), float(d.floor_rms_m), tuple(d.notes))

    def floors(self, fit: SpaceFit, points: Points, sample: Sample) -> Floors:
        """The disparity step and the model's sigma across the plane (found by the fit); depth is Z.

        The spatial correlation is already in the covariance (in disparity units), so no residuals.
        """
        return Floors(fit.floor_rms_m, fit.expected_rms_m, (self.measurement.disparity_sigma_px or 0.0) > 0, 0.0,
                      points.p[2], None)

    def response(self, fit: SpaceFit, points: Points, sample: Sample) -> Response:
        """The disparity ``d = -f·B (n·a)/c`` (``a = (x/z, y/z, 1)``) fitted by least squares, weights 1."""
        fb = self.measurement.fb_px_m
        p = sample.p
        a = np.vstack([p[0] / p[2], p[1] / p[2], np.ones(p.shape[1])])
        n, c = np.asarray(fit.plane.normal, dtype=np.float64), fit.plane.offset_m
        d = -fb * (n @ a) / c
        jac = np.column_stack([-fb * (fit.e1 @ a) / c, -fb * (fit.e2 @ a) / c, -d / c])
        u, v = pixel_uv(points.masks, points.shape, sample.index)
        return Response(fit.plane, fit.e1, fit.e2, jac, np.ones(d.size), d, -d * d / fb, u, v, "stereo")
