"""The stereo sim's noise and speckle defaults against real OAK frames (see tests/data/real/NOTICE.md).

The frames have integer disparity (subpixel off). The disparity noise before rounding is
read from how level boundaries blur: in 15 x 15 windows on smooth surfaces that cross a
boundary, the integer disparities are fitted by an affine function and the sigma of a
Gaussian rounded to whole pixels is found by maximum likelihood. Speckle: pixels more than
5 cm from their 5 x 5 median, in connected blobs of at most 30 px.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from numpy.lib.stride_tricks import sliding_window_view
from scipy.optimize import minimize_scalar
from scipy.stats import norm

from cellcal.sims.stereo import SimStereoConfig
from tests.support.repo_paths import OAK_DATA

FRAME = OAK_DATA / "19443010813B771300_1_depth.npy"  # committed with its NOTICE.md
R = 7  # window half-width, px


def real_z_m() -> np.ndarray:
    return np.load(FRAME).astype(np.float64) / 1000.0


def level_spacing_fb(inv_z: np.ndarray) -> float:
    """f·B (px·m) that puts the frame's 1/Z values nearest whole disparities."""
    cands = np.linspace(25.0, 35.0, 4001)
    sample = inv_z[::37]
    return float(cands[int(np.argmax([np.mean(np.cos(2 * np.pi * c * sample)) for c in cands]))])


def disparity_sigma_px(k: np.ndarray) -> float:
    """ML sigma (px) of the noise before rounding, from integer disparities ``k`` (NaN: no depth)."""
    yy, xx = np.mgrid[-R:R + 1, -R:R + 1]
    design = np.column_stack([xx.ravel(), yy.ravel(), np.ones(xx.size)]).astype(np.float64)
    win = sliding_window_view(k, (2 * R + 1, 2 * R + 1))[::6, ::6].reshape(-1, design.shape[0])
    win = win[np.all(np.isfinite(win), axis=1)]
    # affine fit per window; keep smooth windows that cross a level boundary
    coef = win @ np.linalg.pinv(design).T
    fit = coef @ design.T
    keep = (np.max(np.abs(win - fit), axis=1) < 1.6) & (np.hypot(coef[:, 0], coef[:, 1]) > 0.03)
    kf, mu = win[keep].ravel(), fit[keep].ravel()

    def nll(sigma: float) -> float:  # P(k) of N(mu, sigma) rounded to whole px
        p = norm.cdf((kf + 0.5 - mu) / sigma) - norm.cdf((kf - 0.5 - mu) / sigma)
        return float(-np.sum(np.log(np.maximum(p, 1e-300))))

    return float(minimize_scalar(nll, bounds=(0.005, 2.0), method="bounded").x)


def test_real_oak_disparity_noise_matches_the_sims_default() -> None:
    z = real_z_m()
    valid = z > 0
    inv_z = np.where(valid, 1.0 / np.where(valid, z, 1.0), np.nan)
    fb = level_spacing_fb(inv_z[valid])
    assert fb == pytest.approx(30.0, abs=0.5)  # an OAK-D (B = 75 mm) at this resolution
    sigma = disparity_sigma_px(np.round(fb * inv_z))
    assert 0.2 < sigma < 0.3  # 0.244 px on this frame, 0.23-0.26 on all seven
    assert SimStereoConfig().disparity_sigma_px == pytest.approx(sigma, abs=0.03)


def test_real_oak_speckle_matches_the_sims_default() -> None:
    z = real_z_m()
    valid = z > 0
    med = cv2.medianBlur(np.where(valid, z * 1000.0, 0).astype(np.uint16), 5).astype(np.float64) / 1000.0
    odd = valid & (np.abs(z - med) > 0.05) & (med > 0)
    _n, _, stats, _ = cv2.connectedComponentsWithStats(odd.astype(np.uint8), connectivity=8)
    small = stats[1:, 4][stats[1:, 4] <= 30]
    fraction = small.sum() / z.size
    assert small.size > 200 and 2 <= np.median(small) <= 5
    # the sim's fraction is of the same order (the real count includes some edge pixels)
    assert 0.3 < SimStereoConfig().speckle_fraction / fraction < 3.0
