"""The disparity fit's rounding and spatially correlated residuals pinned against independent computations (#32).

The rounding's mean error from the Gaussian's CDF and its first harmonic (the bias) by a Fourier sum; planes
rounded to 1/4 px without noise, fitted by hand with that mean error removed; the pattern's removal on both
sides of its threshold and its systematic part, averaged over the unknown phase, in the intervals; the design
effect by looping over pixel blocks. The notes a user reads are pinned whole. The camera is
tests/support/disparity_camera.py.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from disparity_camera import V_TRUE, H, W, cloud, measured, model, normalised, truncated

from cellcal.core.methods.fullframe.disparity import design_effect, fit_disparity, rounding_bias_px, rounding_mean_px
from cellcal.core.methods.fullframe.settings import FullFrameSettings


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


# ---------------------------------------------------------------------- planes rounded without noise, fitted by hand
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
