"""The synthetic stereo camera of the disparity fit's pinned tests (tests/unit/core/methods/test_disparity_*).

An ``H`` x ``W`` px image with the principal point at its centre, focal length ``F`` px and baseline ``B`` m;
``V_TRUE`` a tilted plane about 0.8 m away in disparity space. Camera points of pixels measured at given
disparities, what the fit sees of them, the stereo measurement model, and the truncated unit Gaussian's
integrals by numerical integration.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import integrate

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
