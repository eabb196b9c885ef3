"""The disparity-space plane fit pinned against independent computations (issue #32).

Small point clouds whose fit can be redone by hand: ordinary least squares on the inliers
(``np.linalg.lstsq``), the truncated-Gaussian factors by numerical integration, the metric
covariance through a finite-difference Jacobian of ``plane_from_disparity``, the lever of a
disparity error on the orthogonal residual by moving a point along its ray, the rounding's
mean error from the Gaussian's CDF, its systematic part by averaging over the unknown phase,
the design effect by looping over pixel blocks. Thresholds are tried on both sides of their
exact boundary, and the texts a user reads are pinned whole.
"""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
from scipy import integrate

from cellcal.core.geometry.planes import Plane
from cellcal.core.methods.fullframe.disparity import (
    RESIDUAL_FLOOR_NOTE,
    DisparityFit,
    _solve,
    design_effect,
    disparity_from_plane,
    disparity_lattice,
    fit_disparity,
    plane_from_disparity,
    rounding_bias_px,
    rounding_mean_px,
)
from cellcal.core.methods.fullframe.expected import ExpectedPlane
from cellcal.core.methods.fullframe.points import FIXED_SEED
from cellcal.core.methods.fullframe.settings import FullFrameSettings
from cellcal.devices.errors import CalibrationError, CalibrationQualityError
from cellcal.devices.measurement import MeasurementModel

H, W = 200, 320                 # px
F, B = 400.0, 0.08              # px, m
FB = F * B                      # 32 px·m
V_TRUE = np.array([3.0, -2.0, 40.0])   # (α, β, γ) px: a plane about 0.8 m away, tilted


def normalised(pix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(x/z, y/z)`` of flat pixel indices of an H x W image with the principal point at its centre."""
    rows, cols = np.divmod(pix, W)
    return (cols - (W - 1) / 2) / F, (rows - (H - 1) / 2) / F


def cloud(pix: np.ndarray, d: np.ndarray) -> np.ndarray:
    """(3, N) float32 camera points of the pixels ``pix`` measured at disparities ``d`` (px)."""
    x, y = normalised(pix)
    z = FB / d
    return np.stack([x * z, y * z, z]).astype(np.float32)


def measured(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """What the fit sees of the float32 points: rows ``(x/z, y/z, 1)`` and the disparity ``f·B/z``."""
    z = p[2].astype(np.float64)
    a = np.stack([p[0] / z, p[1] / z, np.ones_like(z)], axis=1)
    return a, FB / z


def model(bits: int, sigma_px: float | None) -> MeasurementModel:
    return MeasurementModel(kind="stereo", baseline_m=B, focal_px=F, subpixel_bits=bits, disparity_sigma_px=sigma_px)


def truncated(c: float) -> tuple[float, float]:
    """Integrals of a unit Gaussian cut at ±c: kept probability and kept second moment."""
    phi = lambda t: math.exp(-0.5 * t * t) / math.sqrt(2.0 * math.pi)  # noqa: E731
    p = integrate.quad(phi, -c, c, epsabs=1e-14, epsrel=1e-13)[0]
    m2 = integrate.quad(lambda t: t * t * phi(t), -c, c, epsabs=1e-14, epsrel=1e-13)[0]
    return p, m2


def tangent_jacobian_fd(v: np.ndarray, e1: np.ndarray, e2: np.ndarray, h: float = 1e-5) -> np.ndarray:
    """d(d_e1, d_e2, d_offset)/d(α, β, γ) by central differences of :func:`plane_from_disparity`."""
    jac = np.empty((3, 3))
    for j in range(3):
        step = np.zeros(3)
        step[j] = h
        hi, lo = plane_from_disparity(v + step, FB), plane_from_disparity(v - step, FB)
        dn = (np.asarray(hi.normal) - np.asarray(lo.normal)) / (2 * h)
        jac[:, j] = [dn @ e1, dn @ e2, (hi.offset_m - lo.offset_m) / (2 * h)]
    return jac


def lever_fd(p: np.ndarray, plane: Plane, h: float = 1e-4) -> np.ndarray:
    """|d(orthogonal distance)/d(disparity)| of each point, moving it along its ray (m/px)."""
    a, d = measured(p)
    n = np.asarray(plane.normal)

    def dist(disp: np.ndarray) -> np.ndarray:
        return (a * (FB / disp)[:, None]) @ n + plane.offset_m

    return np.abs(dist(d + h) - dist(d - h)) / (2 * h)


def exact_rounding_mean(d: np.ndarray, sigma: float, q: float, levels: int = 12) -> np.ndarray:
    """``E[round((d + σ N)/q)·q] - d`` summed over the levels around ``d`` with the Gaussian CDF."""
    from scipy.stats import norm

    base = np.round(d / q)
    out = np.zeros_like(d)
    for k in range(-levels, levels + 1):
        level = (base + k) * q
        prob = norm.cdf((level + q / 2 - d) / sigma) - norm.cdf((level - q / 2 - d) / sigma)
        out += prob * (level - d)
    return out


def corrected_fit(a_in: np.ndarray, d_in: np.ndarray, sigma: float, q: float,
                  passes: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Least squares with the mean rounding error removed at the fitted disparities: ``v`` and the residuals.

    Each pass removes the mean error at the previous pass's plane; the residuals are the last
    pass's data (rounding error removed) minus its plane.
    """
    v = np.linalg.lstsq(a_in, d_in, rcond=None)[0]
    clean = d_in
    for _ in range(passes):
        clean = d_in - exact_rounding_mean(a_in @ v, sigma, q)
        v = np.linalg.lstsq(a_in, clean, rcond=None)[0]
    return v, clean - a_in @ v


# ---------------------------------------------------------------------- a small cloud, fitted by hand
RNG = np.random.default_rng(2026)
PIX = np.sort(RNG.choice(H * W, size=68, replace=False))
X, Y = normalised(PIX)
OUTLIER = np.zeros(PIX.size, dtype=bool)
OUTLIER[::9][:8] = True                                       # 8 of 68 points far off the plane
NOISE = RNG.standard_normal(PIX.size)
OFFSETS = np.where(OUTLIER, RNG.uniform(8.0, 20.0, PIX.size), 0.0)


def small_cloud(noise_px: float) -> np.ndarray:
    d = V_TRUE[0] * X + V_TRUE[1] * Y + V_TRUE[2] + noise_px * NOISE + OFFSETS
    return cloud(PIX, d)


def fit_small(noise_px: float, sigma_px: float | None, bits: int = 0) -> tuple[DisparityFit, np.ndarray]:
    p = small_cloud(noise_px)
    return fit_disparity(p, PIX, (H, W), model(bits, sigma_px), FullFrameSettings()), p


def reference_scale(p: np.ndarray, mask: np.ndarray, c: float) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Least squares on ``mask``: ``v``, ``(AᵀA)⁻¹``, the residual sum of squares, the truncation-corrected sigma."""
    a, d = measured(p)
    v = np.linalg.lstsq(a[mask], d[mask], rcond=None)[0]
    r = d[mask] - a[mask] @ v
    rss = float(r @ r)
    prob, m2 = truncated(c)
    return v, np.linalg.inv(a[mask].T @ a[mask]), rss, math.sqrt(rss / (mask.sum() - 3) / (m2 / prob))


def test_a_small_fit_is_the_least_squares_of_its_inliers_with_every_output_pinned() -> None:
    """Stated 1 px noise, dithered (no rounding correction): every field against a fit redone by hand."""
    fit, p = fit_small(1.0, 1.0)
    assert np.array_equal(fit.inliers, ~OUTLIER)
    v, ata_inv, rss, observed = reference_scale(p, ~OUTLIER, 3.0)   # band = 3 sigma: cut at c = 3
    sigma_model = math.sqrt(1.0 + 1.0 / 12.0)                    # Sheppard: 1 px noise, integer steps
    assert np.allclose(fit.disparity, v, rtol=1e-10, atol=1e-10)
    assert fit.residual_rms_px == pytest.approx(math.sqrt(rss / 60), rel=1e-9)
    assert fit.sigma_used_px == pytest.approx(max(sigma_model, observed), rel=1e-9)
    assert fit.band_px == pytest.approx(3.0 * max(sigma_model, observed), rel=1e-9)
    assert fit.design_effect == 1.0                              # 68 points in 64000 pixels: no block half full
    prob, m2 = truncated(3.0)
    cov_factor = prob / m2                     # σ²/(N (p - 2cφ)) over σ²/(N p): see the Monte Carlo below
    assert np.allclose(fit.disparity_cov, ata_inv * fit.sigma_used_px**2 * cov_factor, rtol=1e-8, atol=0)
    assert fit.noise_scale_m == pytest.approx(fit.sigma_used_px / FB, rel=1e-12)
    # the metric plane: n = -v/|v| toward the camera, offset f·B/|v|
    assert np.allclose(fit.plane.normal, -v / np.linalg.norm(v), atol=1e-10)
    assert fit.plane.offset_m == pytest.approx(FB / np.linalg.norm(v), rel=1e-10)
    n = np.asarray(fit.plane.normal)
    assert abs(fit.e1 @ n) < 1e-12 and abs(fit.e2 @ n) < 1e-12 and np.allclose(np.cross(n, fit.e1), fit.e2)
    jac = tangent_jacobian_fd(fit.disparity, fit.e1, fit.e2)
    assert np.allclose(fit.cov, jac @ fit.disparity_cov @ jac.T, rtol=1e-6, atol=0)
    # residuals in metres: orthogonal distances of the inlier points, and what the model expects of them
    pts = p[:, ~OUTLIER].astype(np.float64)
    ortho = n @ pts + fit.plane.offset_m
    assert fit.residual_rms_m == pytest.approx(math.sqrt(float(np.mean(ortho**2))), rel=1e-9)
    lever = lever_fd(p[:, ~OUTLIER], fit.plane)
    assert fit.expected_rms_m == pytest.approx(sigma_model * math.sqrt(float(np.mean(lever**2))), rel=1e-6)
    assert fit.floor_rms_m == pytest.approx(math.sqrt(1.0 / 12.0) * math.sqrt(float(np.mean(lever**2))), rel=1e-6)
    assert observed <= 1.05 * sigma_model and fit.notes == ()


def test_the_widening_note_at_its_threshold() -> None:
    """Residuals 1.05 times the model's sigma: the note appears just above, not just below."""
    _, p = fit_small(1.0, 1.0)
    _, _, _, observed = reference_scale(p, ~OUTLIER, 3.0)
    for factor, noted in ((1.0 - 1e-6, True), (1.0 + 1e-6, False)):
        sigma_model = observed / 1.05 * factor
        sigma_d = math.sqrt(sigma_model**2 - 1.0 / 12.0)
        fit = fit_disparity(p, PIX, (H, W), model(0, sigma_d), FullFrameSettings())
        assert fit.sigma_used_px == pytest.approx(observed, rel=1e-9)
        if noted:
            assert fit.notes == (f"disparity residuals 1.05x the model's {sigma_model:.3g} px: intervals widened "
                                 "by that factor",)
        else:
            assert fit.notes == ()
    fit = fit_disparity(p, PIX, (H, W), model(0, 0.5), FullFrameSettings())
    ratio = observed / math.sqrt(0.25 + 1.0 / 12.0)
    assert fit.notes == (f"disparity residuals {ratio:.3g}x the model's 0.577 px: intervals widened by that factor",)


def test_unstated_noise_is_estimated_from_the_residuals() -> None:
    fit, p = fit_small(1.0, None)
    assert np.array_equal(fit.inliers, ~OUTLIER)
    c = fit.band_px / fit.sigma_used_px
    assert c == pytest.approx(3.0, rel=1e-12)                    # the band follows the estimated sigma
    v, _, _, observed = reference_scale(p, ~OUTLIER, 3.0)
    assert np.allclose(fit.disparity, v, rtol=1e-10, atol=1e-10)
    assert fit.sigma_used_px == pytest.approx(observed, rel=1e-9)
    assert fit.notes == (RESIDUAL_FLOOR_NOTE,)
    assert RESIDUAL_FLOOR_NOTE == ("disparity sigma not stated: estimated from the residuals (never below the "
                                   "rounding's q/sqrt(12))")
    lever = lever_fd(p[:, ~OUTLIER], fit.plane)
    assert fit.expected_rms_m == pytest.approx(observed * math.sqrt(float(np.mean(lever**2))), rel=1e-6)


def test_unstated_noise_is_never_below_the_rounding() -> None:
    """A plane rounded to 1/4 px with no noise: the residuals are below q/sqrt(12), the sigma used is not."""
    pix = np.arange(H * W)[::7]
    x, y = normalised(pix)
    d = np.round((V_TRUE[0] * x + V_TRUE[1] * y + V_TRUE[2]) * 4.0) / 4.0
    p = cloud(pix, d)
    fit = fit_disparity(p, pix, (H, W), model(2, None), FullFrameSettings())
    assert fit.residual_rms_px < 0.25 / math.sqrt(12.0)
    assert fit.sigma_used_px == pytest.approx(0.25 / math.sqrt(12.0), rel=1e-12)
    assert fit.band_px == 0.25                                   # 3 sigma is below one step: the band is the step
    # by hand: one pass on every point, cut at one step from a sigma that starts at q/sqrt(12) ...
    q, n = 0.25, pix.size
    a, dm = measured(p)
    assert fit.inliers.all()
    v = np.linalg.lstsq(a, dm, rcond=None)[0]
    r = dm - a @ v
    prob, m2 = truncated(math.sqrt(12.0))
    sigma = max(math.sqrt(float(r @ r) / (n - 3) / (m2 / prob)), q / math.sqrt(12.0))
    assert q / math.sqrt(12.0) < sigma < q / 3.0                 # above the rounding alone, below a third of a step
    # ... whose excess over the rounding is the noise that dithers it: the mean rounding error removed at that
    # sigma (rounding_mean_px is checked against the exact mean above), three passes
    sigma_d = math.sqrt(sigma * sigma - q * q / 12.0)
    for _ in range(3):
        mu = rounding_mean_px(a @ v, sigma_d, q)
        v = np.linalg.lstsq(a, dm - mu, rcond=None)[0]
    r = dm - mu - a @ v
    assert np.allclose(fit.disparity, v, rtol=1e-9, atol=1e-9)
    assert fit.residual_rms_px == pytest.approx(math.sqrt(float(np.mean(r * r))), rel=1e-7)


def test_a_stated_noise_of_zero_removes_the_bare_sawtooth() -> None:
    """σ_d = 0 stated, a nearly frontal plane rounded to 1/4 px without noise: the undamped sawtooth is removed."""
    q = 0.25
    pix = np.arange(H * W)[::7]
    x, y = normalised(pix)
    p = cloud(pix, np.round((1.0 * x - 0.5 * y + 40.1) / q) * q)  # a few levels: the pattern does not average out
    fit = fit_disparity(p, pix, (H, W), model(2, 0.0), FullFrameSettings())
    a, d = measured(p)
    assert fit.inliers.all()
    v = np.linalg.lstsq(a, d, rcond=None)[0]
    for _ in range(3):
        mu = rounding_mean_px(a @ v, 0.0, q)
        v = np.linalg.lstsq(a, d - mu, rcond=None)[0]
    assert np.allclose(fit.disparity, v, rtol=1e-9, atol=1e-9)
    assert fit.residual_rms_px == pytest.approx(math.sqrt(float(np.mean((d - mu - a @ v) ** 2))), rel=1e-7)
    plain = np.linalg.lstsq(a, d, rcond=None)[0]
    assert np.max(np.abs(v - plain)) > 1e-4                     # the correction is not a no-op here
    # half the undamped bias q/π is left in the intervals: q/(2π) = 0.04 px
    assert fit.notes[-1] == ("disparity rounding weakly dithered (sigma_d 0 px for steps of 0.25 px): its pattern "
                             "removed, up to 0.04 px left in the intervals")


# ---------------------------------------------------------------------- the rounding of a weakly dithered disparity
def sys_var_by_phase(a_in: np.ndarray, v: np.ndarray, b: float, q: float) -> np.ndarray:
    """Mean square over the phase φ of the least-squares response to ``b·sin(2π d/q + φ)`` (px²)."""
    phases = np.linspace(0.0, 2.0 * math.pi, 16, endpoint=False)
    d_fit = a_in @ v
    shifts = np.array([np.linalg.lstsq(a_in, b * np.sin(2 * math.pi * d_fit / q + ph), rcond=None)[0]
                       for ph in phases])
    return np.mean(shifts**2, axis=0)


#: σ_d/q where the rounding's bias (q/π)·exp(-2π²σ²/q²) is 1e-3 q: below it the pattern is removed.
S_CORRECT = math.sqrt(math.log(1000.0 / math.pi) / (2.0 * math.pi**2))
#: σ_d/q where half that bias is 1e-6 q: below it, its systematic part enters the intervals.
S_SYSTEMATIC = math.sqrt(math.log(0.5e6 / math.pi) / (2.0 * math.pi**2))


def rounded_cloud(sigma_px: float, q: float, seed: int = 7, step: int = 97) -> tuple[np.ndarray, np.ndarray]:
    pix = np.arange(H * W)[::step]
    x, y = normalised(pix)
    rng = np.random.default_rng(seed)
    d = V_TRUE[0] * x + V_TRUE[1] * y + V_TRUE[2] + sigma_px * rng.standard_normal(pix.size)
    return cloud(pix, np.round(d / q) * q), pix


@pytest.mark.parametrize(("factor", "corrected"), [(1.0 - 1e-6, True), (1.0 + 1e-6, False)])
def test_the_rounding_pattern_is_removed_below_its_threshold(factor: float, corrected: bool) -> None:
    """At σ_d just below / above the threshold: the fit removes the rounding's mean error, or is plain least squares."""
    q = 0.25
    sigma_d = S_CORRECT * q * factor
    p, pix = rounded_cloud(sigma_d, q)
    fit = fit_disparity(p, pix, (H, W), model(2, sigma_d), FullFrameSettings())
    a, d = measured(p)
    mask = fit.inliers
    assert mask.sum() >= 0.99 * mask.size
    if corrected:
        v, r = corrected_fit(a[mask], d[mask], sigma_d, q)
    else:
        v = np.linalg.lstsq(a[mask], d[mask], rcond=None)[0]
        r = d[mask] - a[mask] @ v
    assert np.allclose(fit.disparity, v, rtol=1e-9, atol=1e-9)
    assert fit.residual_rms_px == pytest.approx(math.sqrt(float(np.mean(r * r))), rel=1e-7)
    plain = np.linalg.lstsq(a[mask], d[mask], rcond=None)[0]
    assert (np.max(np.abs(fit.disparity - plain)) > 1e-6) == corrected


@pytest.mark.parametrize(("sigma_over_q", "bits", "step"), [(0.2, 0, 13), (0.3, 2, 13), (0.2, 0, 1), (0.25, 3, 1),
                                                          (0.51, 5, 13), (S_SYSTEMATIC * (1 - 1e-4), 0, 13)])
def test_the_rounding_left_after_its_correction_widens_the_intervals(sigma_over_q: float, bits: int,
                                                                     step: int) -> None:
    """Half the bias ``(q/π)·exp(-2π²σ²/q²)`` as a pattern of unknown phase: its RMS effect enters the variances.

    What the spatial correlation (the design effect) already added is not added twice; every pixel of
    the image (``step`` 1) makes the rounding's residuals correlated, every 13th does not.
    """
    q = 2.0**-bits
    sigma_d = sigma_over_q * q
    p, pix = rounded_cloud(sigma_d, q, step=step)
    fit = fit_disparity(p, pix, (H, W), model(bits, sigma_d), FullFrameSettings())
    a, d = measured(p)
    inl = fit.inliers
    a_in = a[inl]
    assert inl.mean() > 0.99 and fit.band_px > q                  # band 3 sigma: a cut at c = 3
    removed = sigma_over_q < S_CORRECT                            # the mean error is removed first
    v, r = corrected_fit(a_in, d[inl], sigma_d, q, passes=3 if removed else 0)
    assert np.allclose(fit.disparity, v, rtol=1e-9, atol=1e-9)
    prob, m2 = truncated(3.0)
    observed = math.sqrt(float(r @ r) / (r.size - 3) / (m2 / prob))
    sigma_model = math.sqrt(sigma_d**2 + q * q / 12.0)
    assert fit.sigma_used_px == pytest.approx(max(observed, sigma_model), rel=1e-7)
    deff = design_effect(r, pix[inl], (H, W))
    assert fit.design_effect == pytest.approx(deff, rel=1e-6)
    b = 0.5 * q / math.pi * math.exp(-2.0 * (math.pi * sigma_over_q) ** 2)
    sys_var = sys_var_by_phase(a_in, fit.disparity, b, q)
    ata_inv = np.linalg.inv(a_in.T @ a_in)
    iid = np.diag(ata_inv) * fit.sigma_used_px**2 * (prob / m2)
    base = ata_inv * fit.sigma_used_px**2 * (prob / m2) * fit.design_effect
    expected = base + np.diag(np.maximum(sys_var - (fit.design_effect - 1.0) * iid, 0.0))
    assert np.allclose(fit.disparity_cov, expected, rtol=1e-9, atol=0)
    notes = []
    if observed > 1.05 * sigma_model:
        notes.append(f"disparity residuals {observed / sigma_model:.3g}x the model's {sigma_model:.3g} px: "
                     "intervals widened by that factor")
    if deff > 1.05:
        notes.append(f"spatially correlated residuals: variance x{deff:.3g} (about {r.size / deff:.0f} independent "
                     f"points of {r.size})")
    if np.any(sys_var > 0.1 * np.diag(expected)):
        notes.append(f"disparity rounding weakly dithered (sigma_d {sigma_d:.2g} px for steps of {q:.3g} px): its "
                     f"pattern removed, up to {b:.2g} px left in the intervals")
    assert fit.notes == tuple(notes)


def test_the_systematic_rounding_term_and_the_correlation_note_are_reached() -> None:
    """The case above with every pixel: both notes, and a variance the correlation factor alone would understate."""
    p, pix = rounded_cloud(0.2, 1.0, step=1)
    fit = fit_disparity(p, pix, (H, W), model(0, 0.2), FullFrameSettings())
    assert fit.design_effect > 1.3
    assert [note.split(" ")[0] for note in fit.notes] == ["spatially", "disparity"]
    a, _ = measured(p)
    a_in = a[fit.inliers]
    prob, m2 = truncated(3.0)
    base = np.linalg.inv(a_in.T @ a_in) * fit.sigma_used_px**2 * (prob / m2) * fit.design_effect
    extra = np.diag(fit.disparity_cov) - np.diag(base)
    assert extra[1] > 2.0 * np.diag(base)[1]                      # β: the rounding's pattern dominates
    assert abs(extra[0]) < 1e-12 * base[0, 0] and abs(extra[2]) < 1e-12 * base[2, 2]   # α, γ: the correlation
    # factor covers it


def test_no_systematic_term_once_the_noise_dithers_the_rounding() -> None:
    q = 1.0
    sigma_d = S_SYSTEMATIC * (1 + 1e-4)
    p, pix = rounded_cloud(sigma_d, q, step=13)
    fit = fit_disparity(p, pix, (H, W), model(0, sigma_d), FullFrameSettings())
    a, _ = measured(p)
    a_in = a[fit.inliers]
    prob, m2 = truncated(fit.band_px / max(math.sqrt(sigma_d**2 + 1 / 12.0), fit.band_px / 3.0))
    base = np.linalg.inv(a_in.T @ a_in) * fit.sigma_used_px**2 * (prob / m2) * fit.design_effect
    assert np.allclose(fit.disparity_cov, base, rtol=1e-11, atol=0)
    assert not any("weakly dithered" in note for note in fit.notes)


# ---------------------------------------------------------------------- the rounding's mean error
@pytest.mark.parametrize("sigma_over_q", [0.0, 0.1, 0.2, 0.4])
def test_rounding_bias_is_the_first_harmonic_of_the_mean_error(sigma_over_q: float) -> None:
    """Fourier amplitude of the exact mean rounding error over one step, against ``(q/π)·exp(-2π²σ²/q²)``."""
    q = 0.125
    x = (np.arange(4096) + 0.5) / 4096 * q                      # true values over one step
    # the mean error of each true value: the sawtooth without noise, the Gaussian-weighted levels with it
    err = np.round(x / q) * q - x if sigma_over_q == 0.0 else exact_rounding_mean(x, sigma_over_q * q, q)
    first = 2.0 * abs(np.mean(err * np.exp(-2j * math.pi * x / q)))
    assert rounding_bias_px(sigma_over_q * q, q) == pytest.approx(first, rel=1e-5)


@pytest.mark.parametrize(("sigma_over_q", "q"), [(0.2, 1.0), (0.25, 0.125), (0.5, 0.5)])
def test_rounding_mean_is_the_exact_mean_error(sigma_over_q: float, q: float) -> None:
    d = np.linspace(30.0, 30.0 + 3 * q, 301)
    exact = exact_rounding_mean(d, sigma_over_q * q, q)
    assert np.allclose(rounding_mean_px(d, sigma_over_q * q, q), exact, atol=2e-8 * q, rtol=0)
    assert np.max(np.abs(exact)) > 1e-4 * q                      # not a trivial agreement on zeros


def test_rounding_mean_of_weak_noise_keeps_four_harmonics() -> None:
    """σ = 0.15 q: the 5th harmonic (7e-5 q) is left out, the 4th (1.1e-3 q) is not."""
    q, sigma = 1.0, 0.15
    d = np.linspace(10.0, 12.0, 2001)
    exact = exact_rounding_mean(d, sigma, q)
    out = rounding_mean_px(d, sigma, q)
    fifth = q / math.pi / 5 * math.exp(-2 * (math.pi * 5 * sigma) ** 2)
    assert np.max(np.abs(out - exact)) == pytest.approx(fifth, rel=0.1)
    assert np.max(np.abs(rounding_mean_px(d, sigma, q, harmonics=5) - exact)) < 0.2 * fifth


# ---------------------------------------------------------------------- design effect
def design_effect_by_loops(r: np.ndarray, pix: np.ndarray, shape: tuple[int, int], sizes: tuple[int, ...]) -> float:
    """The docstring's ``mean(n_k m_k²) / mean(r²)`` over blocks at least half full, sizes with 8 such blocks."""
    h, w = shape
    var = float(np.mean(r * r))
    rows, cols = pix // w, pix % w
    best = 1.0
    for b in sizes:
        terms = []
        for by in range(0, h, b):
            for bx in range(0, w, b):
                sel = (rows >= by) & (rows < by + b) & (cols >= bx) & (cols < bx + b)
                n = int(sel.sum())
                if n >= b * b / 2:
                    terms.append(n * float(np.mean(r[sel])) ** 2)
        if len(terms) >= 8:
            best = max(best, float(np.mean(terms)) / var)
    return best


def test_design_effect_on_an_image_that_blocks_do_not_tile() -> None:
    """100 x 72 px, some pixels missing, residuals correlated over ~12 px: the loops agree for every block size."""
    h, w = 72, 100
    rng = np.random.default_rng(11)
    rows, cols = np.mgrid[0:h, 0:w]
    field = np.sin(rows / 5.0) + np.cos(cols / 7.0) + 0.5 * rng.standard_normal((h, w))
    keep = rng.random(h * w) < 0.7
    pix = np.arange(h * w)[keep]
    r = field.reshape(-1)[keep]
    for sizes in [(8,), (16,), (32,), (8, 16, 32)]:
        assert design_effect(r, pix, (h, w), sizes) == pytest.approx(design_effect_by_loops(r, pix, (h, w), sizes),
                                                                      rel=1e-12)
    assert design_effect(r, pix, (h, w)) == pytest.approx(design_effect_by_loops(r, pix, (h, w), (8, 16, 32)),
                                                          rel=1e-12)
    assert design_effect(r, pix, (h, w)) > 5.0


def test_design_effect_of_block_patterns() -> None:
    """Residuals constant over 8 x 8 blocks in a checkerboard of signs: 64 at 8 px, 0 at 16 and 32 px (means vanish)."""
    h, w = 64, 96
    rows, cols = np.mgrid[0:h, 0:w]
    check = np.where(((rows // 8) + (cols // 8)) % 2 == 0, 1.0, -1.0).reshape(-1)
    pix = np.arange(h * w)
    assert design_effect(check, pix, (h, w)) == pytest.approx(64.0, rel=1e-12)
    assert design_effect(check, pix, (h, w), (16, 32)) == 1.0
    # six 32 px blocks are too few to count, and a size after them is still tried
    assert design_effect(check, pix, (h, w), (32, 8)) == pytest.approx(64.0, rel=1e-12)
    # constant over 32 x 32 blocks with alternating sign: the largest size sees 1024
    tall, wide = 128, 128
    r2, c2 = np.mgrid[0:tall, 0:wide]
    big = np.where(((r2 // 32) + (c2 // 32)) % 2 == 0, 2.0, -2.0).reshape(-1)
    assert design_effect(big, np.arange(tall * wide), (tall, wide)) == pytest.approx(1024.0, rel=1e-12)
    assert design_effect(np.zeros(h * w), pix, (h, w)) == 1.0


def test_design_effect_counts_blocks_exactly_half_full_and_needs_eight_of_them() -> None:
    """16 x 32 px: eight 8 x 8 blocks. Half-full blocks count; seven usable blocks are not enough."""
    h, w = 16, 32
    rows, cols = np.mgrid[0:h, 0:w]
    r = np.where(((rows // 8) + (cols // 8)) % 2 == 0, 1.0, -1.0).reshape(-1)
    left_half = (cols % 8 < 4).reshape(-1)                      # 32 of each block's 64 pixels
    pix = np.arange(h * w)[left_half]
    assert design_effect(r[left_half], pix, (h, w), (8,)) == pytest.approx(32.0, rel=1e-12)
    short = left_half & ~((rows < 8) & (cols < 8) & (rows % 8 == 0)).reshape(-1)   # block 0: 28 of 64
    pix = np.arange(h * w)[short]
    assert design_effect(r[short], pix, (h, w), (8,)) == 1.0


# ---------------------------------------------------------------------- the lattice of depth levels
def lattice_depths(levels_k: np.ndarray, counts: np.ndarray, fb_over_q: float) -> np.ndarray:
    return np.repeat(fb_over_q / levels_k, counts)


def test_lattice_needs_four_populated_levels_of_sixteen_depths() -> None:
    fbq = 33.0 * 8                                               # f·B/q, px·m: 1/8 px steps
    k = np.array([300.0, 301.0, 303.0, 306.0])
    assert disparity_lattice(lattice_depths(k, np.full(4, 16), fbq)) == pytest.approx(fbq, rel=1e-4)
    assert disparity_lattice(lattice_depths(k, np.array([16, 16, 16, 15]), fbq)) is None    # one level too thin
    assert disparity_lattice(lattice_depths(k[:3], np.full(3, 40), fbq)) is None             # three levels
    assert disparity_lattice(lattice_depths(k[:3], np.full(3, 40), fbq), min_levels=3) == pytest.approx(fbq,
                                                                                                         rel=1e-4)


def test_lattice_populated_share_is_two_per_mille() -> None:
    """20 000 depths: a level needs 40 of them (0.2 %); 39 leaves three levels, too few."""
    fbq = 33.0
    k = np.array([40.0, 41.0, 42.0, 44.0])
    filler = np.full(20_000 - 40 * 3 - 40, 0.5) + np.random.default_rng(3).uniform(0, 1e-3, 20_000 - 160)
    counts_ok = np.array([40, 40, 40, 40])
    z = np.concatenate([lattice_depths(k, counts_ok, fbq), filler])
    assert disparity_lattice(z) == pytest.approx(fbq, rel=1e-4)
    z = np.concatenate([lattice_depths(k, np.array([40, 40, 40, 39]), fbq), filler, [0.5]])
    assert disparity_lattice(z) is None


#: 40 levels: two adjacent ones on the lattice (the smallest gap, one step), 38 every other step alternately
#: ``±j`` steps off it; RMS ``j·sqrt(38/40)``, so the tenth-of-a-step limit is at ``j = 0.1·sqrt(40/38)``.
J_LIMIT = 0.1 * math.sqrt(40.0 / 38.0)


@pytest.mark.parametrize(("jitter", "found"), [(0.97 * J_LIMIT, True), (1.03 * J_LIMIT, False)])
def test_lattice_levels_must_sit_within_a_tenth_of_a_step(jitter: float, found: bool) -> None:
    fbq = 25.0
    k_off = 63.0 + 2.0 * np.arange(38)
    k_off += jitter * np.where(np.arange(38) % 2 == 0, 1.0, -1.0)   # alternating: no change of scale absorbs it
    k = np.concatenate([[60.0, 61.0], k_off])
    out = disparity_lattice(lattice_depths(k, np.full(k.size, 20), fbq))
    assert (out is not None) == found
    if found:
        assert out == pytest.approx(fbq, rel=1e-3)


def test_lattice_pitch_is_exact_when_two_levels_are_adjacent() -> None:
    """Levels exactly on the lattice, two of them one step apart: the first guess is the answer, to rounding."""
    fbq = 33.0 * 32                                              # 1/32 px steps
    z = lattice_depths(np.array([1400.0, 1401.0, 1404.0, 1409.0, 1416.0]), np.full(5, 20), fbq)
    assert disparity_lattice(z) == pytest.approx(fbq, rel=1e-9)


def test_lattice_of_levels_with_one_reciprocal_is_none() -> None:
    """Two depths one float apart with the same ``1/Z``: a gap of zero tells no pitch."""
    z0 = 0.70814
    assert 1.0 / z0 == 1.0 / np.nextafter(z0, 2.0)
    z = np.repeat([z0, np.nextafter(z0, 2.0), 0.69, 0.67, 0.65], 20)
    assert disparity_lattice(z) is None


@pytest.mark.parametrize("bits", [0, 2, 3])
def test_lattice_of_float32_depths_is_that_of_their_values(bits: int) -> None:
    """A camera's float32 depths give the answer of the same values in float64 (the pitch needs the precision)."""
    rng = np.random.default_rng(60 + bits)
    pix = np.arange(H * W)
    x, y = normalised(pix)
    d = np.round((V_TRUE[0] * x + V_TRUE[1] * y + V_TRUE[2] + 0.3 * rng.standard_normal(pix.size)) * 2**bits)
    z32 = (FB / (d / 2**bits)).astype(np.float32)
    out = disparity_lattice(z32)
    assert out == disparity_lattice(z32.astype(np.float64))
    assert out == pytest.approx(FB * 2**bits, rel=1e-4)


def test_lattice_ignores_missing_depths() -> None:
    fbq = 33.0
    z = lattice_depths(np.array([40.0, 41.0, 42.0, 43.0, 45.0]), np.full(5, 30), fbq)
    holes = np.concatenate([z, np.zeros(500), np.full(300, np.nan), np.full(200, -1.0), np.full(100, np.inf)])
    assert disparity_lattice(holes) == pytest.approx(disparity_lattice(z), rel=1e-15)
    assert disparity_lattice(np.zeros(100)) is None
    assert disparity_lattice(np.full(10, np.nan)) is None
    out = disparity_lattice(z.astype(np.float32).reshape(5, 30))
    assert type(out) is float and out == pytest.approx(fbq, rel=1e-4)


# ---------------------------------------------------------------------- the geometry of disparity planes
def test_disparity_of_a_plane_is_the_pinhole_disparity_of_its_points() -> None:
    """``α x + β y + γ`` equals ``f·B/Z`` where each pixel's ray meets the plane ``n·X + c = 0``."""
    n = np.array([0.2, -0.3, -1.0])
    n /= np.linalg.norm(n)
    plane = Plane(n, 0.75)
    v = disparity_from_plane(plane, FB)
    for x, y in [(0.0, 0.0), (0.3, -0.2), (-0.4, 0.25)]:
        ray = np.array([x, y, 1.0])
        z = -plane.offset_m / float(n @ ray)                      # the ray X = Z·(x, y, 1) meets the plane
        assert v @ ray == pytest.approx(FB / z, rel=1e-12)
    back = plane_from_disparity(v, FB)
    assert np.allclose(back.normal, n, atol=1e-12) and back.offset_m == pytest.approx(0.75, rel=1e-12)
    flipped = plane_from_disparity(-v, FB)                       # the sign of v decides the normal's
    assert np.allclose(flipped.normal, -n, atol=1e-12) and flipped.offset_m == pytest.approx(0.75, rel=1e-12)


# ---------------------------------------------------------------------- what is refused, in the user's words
def test_points_on_one_image_row_define_no_plane() -> None:
    pix = np.arange(50) * 3 + (H // 2) * W                        # one row
    x, _ = normalised(pix)
    p = cloud(pix, 40.0 + 3.0 * x)
    p[1] = 0.0                                                   # exactly on the optical axis's row: y/z = 0
    with pytest.raises(CalibrationError) as err:
        fit_disparity(p, pix, (H, W), model(3, 0.1), FullFrameSettings())
    assert str(err.value) == "full-frame fit: the points are collinear or coincident; no plane is defined"


def test_normal_equations_that_span_no_plane_are_refused() -> None:
    """Unreachable from ``fit_disparity`` (its inliers always hold the start's non-collinear triplet): the text."""
    with pytest.raises(CalibrationError) as err:
        _solve(np.zeros((3, 3)), np.ones(3))
    assert str(err.value) == "full-frame fit is degenerate: the inliers do not span a plane"
    v, inv = _solve(np.diag([2.0, 4.0, 8.0]), np.array([2.0, 2.0, 2.0]))
    assert np.allclose(inv, np.diag([0.5, 0.25, 0.125])) and np.allclose(v, [1.0, 0.5, 0.25])


def test_one_point_off_a_line_of_points_defines_the_plane() -> None:
    """40 points on the image row y = 0 and the first point off it: only triplets with that point span a plane."""
    pix = np.concatenate([[30 * W + 250], np.arange(40) * 7 + (H // 2) * W])
    x, y = normalised(pix)
    y[1:] = 0.0                                                  # the row through the principal point
    d = 40.0 + 3.0 * x + 5.0 * y
    z = FB / d
    p = np.stack([x * z, y * z, z]).astype(np.float32)
    fit = fit_disparity(p, pix, (H, W), model(0, 1.0), FullFrameSettings())
    assert fit.inliers.all()
    assert np.allclose(fit.disparity, [3.0, 5.0, 40.0], atol=1e-4)


@pytest.mark.parametrize("n_plane", [16, 15])
def test_sixteen_points_within_the_band_are_enough_and_fifteen_are_not(n_plane: int) -> None:
    rng = np.random.default_rng(40 + n_plane)
    pix = rng.choice(H * W, size=n_plane + 25, replace=False)
    x, y = normalised(pix)
    d = V_TRUE[0] * x + V_TRUE[1] * y + V_TRUE[2]
    d[n_plane:] += rng.uniform(10.0, 40.0, 25)                    # 25 points far off the plane, scattered
    p = cloud(pix, d)
    settings = FullFrameSettings(hypotheses=2000)
    if n_plane == 16:
        fit = fit_disparity(p, pix, (H, W), model(0, 1.0), settings)
        assert fit.inliers.sum() == 16 and fit.inliers[:16].all()
        assert np.allclose(fit.disparity, V_TRUE, atol=1e-4)
    else:
        with pytest.raises(CalibrationError) as err:
            fit_disparity(p, pix, (H, W), model(0, 1.0), settings)
        band = 3.0 * math.sqrt(1.0 + 1.0 / 12.0)                  # 3 sigma of 1 px noise rounded to 1 px: 3.12 px
        assert str(err.value) == (f"full-frame fit: only 15 of 40 points lie within {band:.3g} px of the plane; "
                                  "no plane is defined")


def test_a_plane_fifty_metres_away_with_disparities_below_one_pixel_is_fitted() -> None:
    """|(α, β, γ)| < 1 px (a plane beyond f·B = 32 m): still a plane, fitted within its interval."""
    v_far = np.array([0.05, -0.03, 0.64])
    q = 1.0 / 32
    pix = np.arange(H * W)[::5]
    x, y = normalised(pix)
    rng = np.random.default_rng(90)
    d = np.round((v_far[0] * x + v_far[1] * y + v_far[2] + 0.02 * rng.standard_normal(pix.size)) / q) * q
    fit = fit_disparity(cloud(pix, d), pix, (H, W), model(5, 0.02), FullFrameSettings())
    assert fit.inliers.mean() > 0.99
    assert np.all(np.abs(fit.disparity - v_far) < 4.0 * np.sqrt(np.diag(fit.disparity_cov)))
    assert fit.plane.offset_m == pytest.approx(FB / np.linalg.norm(v_far), rel=0.01)   # about 50 m
    # without noise every triplet is that plane itself, |v| = 0.64 px: recovered exactly
    exact = fit_disparity(cloud(pix, v_far[0] * x + v_far[1] * y + v_far[2]), pix, (H, W), model(5, 0.02),
                          FullFrameSettings())
    assert np.allclose(exact.disparity, v_far, atol=1e-6)


@pytest.mark.parametrize("seed", [0, 3])
def test_a_step_of_half_a_pixel_is_fitted_on_one_side_not_across_it(seed: int) -> None:
    """A band 0.5 px nearer (60 % of the image) across a floor: the fit is the band's plane, not a blend.

    The same scoring names the plane a refusal reports: the band's, not a blend.

    The start scores a triplet by its squared residuals truncated at the band (a few hundredths of a
    pixel here): the far side counts as a constant, so the plane of the most points wins.
    """
    pix = np.arange(H * W)[::7]
    x, y = normalised(pix)
    top = np.abs(y) < 0.15
    rng = np.random.default_rng(seed)
    d = 0.5 * x - 0.3 * y + 40.0 + np.where(top, 0.5, 0.0) + 0.014 * rng.standard_normal(x.size)
    d = np.round(d * 32) / 32
    p = cloud(pix, d)
    fit = fit_disparity(p, pix, (H, W), model(5, 0.014), FullFrameSettings())
    assert np.mean(fit.inliers == top) > 0.99
    assert np.allclose(fit.disparity, [0.5, -0.3, 40.5], atol=0.01)
    # and with an expected plane 30 degrees and 100 mm off the band: the refusal names the band's plane
    truth = plane_from_disparity(np.array([0.5, -0.3, 40.5]), FB)
    n0 = np.asarray(truth.normal)
    tilt = np.array([1.0, 0.0, 0.0]) - n0[0] * n0
    n_exp = n0 * math.cos(math.radians(30.0)) + tilt / np.linalg.norm(tilt) * math.sin(math.radians(30.0))
    expected = ExpectedPlane(Plane(n_exp, truth.offset_m + 0.1), math.radians(5.0), 0.05)
    with pytest.raises(CalibrationQualityError) as err:
        fit_disparity(p, pix, (H, W), model(5, 0.014), FullFrameSettings(), expected=expected)
    assert math.degrees(err.value.value) == pytest.approx(30.0, abs=0.2)    # a noisy triplet of the band's points
    found_mm = re.search(r"the dominant plane found is [0-9.]+ deg and ([0-9.]+) mm away", str(err.value))
    assert found_mm is not None and float(found_mm.group(1)) == pytest.approx(100.0, abs=1.0)


def test_a_tof_or_unknown_camera_is_refused_in_one_line() -> None:
    p = small_cloud(0.0)
    for m, kind in ((MeasurementModel(kind="tof", sigma_at_1m_m=0.003), "tof"), (MeasurementModel(), "unknown")):
        with pytest.raises(CalibrationError) as err:
            fit_disparity(p, PIX, (H, W), m, FullFrameSettings())
        assert str(err.value) == f"fit_disparity needs a stereo or structured-light model, got '{kind}'"


def test_no_plane_near_the_expected_one_names_the_dominant_plane() -> None:
    """Half the points on a plane, half scattered: the text names the plane of the most points, 20° and 99.5 mm away."""
    rng = np.random.default_rng(50)
    pix = rng.choice(H * W, size=80, replace=False)
    x, y = normalised(pix)
    d = V_TRUE[0] * x + V_TRUE[1] * y + V_TRUE[2]
    d[40:] += rng.uniform(8.0, 30.0, 40)                         # 40 points far off it, on no common plane
    p = cloud(pix, d)
    truth = plane_from_disparity(V_TRUE, FB)
    n0 = np.asarray(truth.normal)
    tilt = np.array([1.0, 0.0, 0.0]) - n0[0] * n0               # a tangent direction
    n_exp = n0 * math.cos(math.radians(20.0)) + tilt / np.linalg.norm(tilt) * math.sin(math.radians(20.0))
    expected = ExpectedPlane(Plane(n_exp, truth.offset_m + 0.0995), math.radians(5.0), 0.0625)
    with pytest.raises(CalibrationQualityError) as err:
        fit_disparity(p, pix, (H, W), model(0, 1.0), FullFrameSettings(), expected=expected)
    head = ("no plane within 5 deg and 62.5 mm of the expected one; the dominant plane found is 20 deg and 99.5 mm "
            "away")
    assert str(err.value) == f"quality gate 'expected_plane' failed: 20 deg vs threshold 5 deg; {head} from it"
    assert err.value.gate == "expected_plane" and err.value.threshold == math.radians(5.0)
    assert err.value.value == pytest.approx(math.radians(20.0), abs=1e-6)
    # an expected plane 3 degrees and 20 mm from it: that plane is fitted
    n_near = n0 * math.cos(math.radians(3.0)) + tilt / np.linalg.norm(tilt) * math.sin(math.radians(3.0))
    near = ExpectedPlane(Plane(n_near, truth.offset_m + 0.02), math.radians(5.0), 0.05)
    fit = fit_disparity(p, pix, (H, W), model(0, 1.0), FullFrameSettings(), expected=near)
    assert np.array_equal(fit.inliers, np.arange(80) < 40)
    assert np.allclose(fit.disparity, V_TRUE, atol=1e-4)


def test_no_seed_is_a_fixed_seed_and_a_given_seed_is_used() -> None:
    """Three planes of 60 points each and 8 hypotheses: which plane the start finds is up to the triplets.

    Without a seed the triplets are always the same ones (the fixed seed's): the same answer on
    every call. A given seed draws its own triplets: over ten seeds more than one answer appears.
    """
    rng = np.random.default_rng(70)
    pix = rng.choice(H * W, size=180, replace=False)
    x, y = normalised(pix)
    planes = np.array([[3.0, -2.0, 40.0], [-5.0, 4.0, 55.0], [8.0, 6.0, 30.0]])
    d = np.einsum("ij,ij->i", planes[np.arange(180) % 3], np.stack([x, y, np.ones_like(x)], axis=1))
    p = cloud(pix, d)

    def outcome(seed: int | None) -> tuple[float, ...] | str:
        try:
            fit = fit_disparity(p, pix, (H, W), model(0, 1.0), FullFrameSettings(hypotheses=8, seed=seed))
        except CalibrationError as exc:
            return str(exc)
        return tuple(np.round(fit.disparity, 6))

    fixed = outcome(FIXED_SEED)
    assert all(outcome(None) == fixed for _ in range(5))
    assert len({outcome(seed) for seed in range(10)}) > 1


@pytest.mark.statistical
@pytest.mark.parametrize("k_sig", [2.0, 3.0])
def test_the_stated_covariance_is_the_scatter_of_repeated_fits(k_sig: float) -> None:
    """A Monte Carlo of the camera: 1500 fits of 400 pixels with 1 px Gaussian noise, cut at ``k_sig`` sigma.

    The variance of each of (α, β, γ) over the fits against the mean of what each fit states. The cut
    estimator's variance is σ²/(N (p - 2cφ(c))) and the fit scales (AᵀA)⁻¹ ≈ 1/(N p) by the
    truncation-corrected σ², so its factor is p / (p - 2cφ(c)): 1.29 at a cut of 2 sigma, 1.027 at 3
    (squared, as the range fit's sandwich needs for its uncorrected meat, it stated 29 % / 2.7 % too much).
    """
    rng = np.random.default_rng(11)
    pix = np.sort(rng.choice(H * W, size=400, replace=False))
    x, y = normalised(pix)
    clean = V_TRUE[0] * x + V_TRUE[1] * y + V_TRUE[2]
    settings = FullFrameSettings(inlier_threshold_sigma=k_sig)
    cam = model(8, 1.0)                                          # steps of 1/256 px: the rounding is negligible
    fits, stated = [], []
    for _ in range(1500):
        d = np.round((clean + rng.standard_normal(pix.size)) * 256.0) / 256.0
        fit = fit_disparity(cloud(pix, d), pix, (H, W), cam, settings)
        fits.append(fit.disparity)
        stated.append(np.diag(fit.disparity_cov))
    ratio = np.var(np.array(fits), axis=0, ddof=1) / np.mean(stated, axis=0)
    # each ratio's own scatter is sqrt(2/1500) = 3.7 %: 4 of them either way
    assert np.all(np.abs(ratio - 1.0) < 0.15), ratio
    assert abs(float(np.mean(ratio)) - 1.0) < 0.1, ratio
