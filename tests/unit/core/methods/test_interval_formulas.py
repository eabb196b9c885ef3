"""Direct checks of the uncertainty formulas: OLS / TLS plane covariances and the full-frame intervals.

Each expected value is computed here from the textbook formula with numpy (regression
covariance ``s^2 (X^T X)^-1`` with ``s^2 = RSS / (n - 3)``, first-order propagation by finite
differences), on small clouds where a wrong number of degrees of freedom moves the sigma by
10-30 %, so no Monte Carlo run is needed to see a wrong formula.
"""

from __future__ import annotations

import math
from statistics import NormalDist

import numpy as np
import pytest
from numpy.typing import NDArray

from cellcal.core.geometry.planes import Plane, fit_plane_ols, fit_plane_tls
from cellcal.core.methods.fullframe import FullFrameSettings, fit_plane_points

F64 = NDArray[np.float64]


def cloud(n: int, seed: int, noise_m: float = 0.002) -> F64:
    """n points near the plane z = 0.8 + 0.1 x - 0.05 y, x, y in [-0.3, 0.3] m, noise along z."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-0.3, 0.3, (n, 2))
    z = 0.8 + 0.1 * xy[:, 0] - 0.05 * xy[:, 1] + rng.normal(0.0, noise_m, n)
    return np.column_stack([xy, z])


def oriented(normal: F64, offset: float) -> tuple[F64, float]:
    """A plane n.p + d = 0 with d >= 0 (the camera-facing sign the fits report)."""
    return (normal, offset) if offset >= 0 else (-normal, -offset)


def regression_normal_offset(beta: F64) -> F64:
    """(unit normal, offset) of z = a x + b y + c, camera-facing, as one vector of 4."""
    a, b, c = beta
    s = math.sqrt(a * a + b * b + 1.0)
    n, d = oriented(np.array([a, b, -1.0]) / s, c / s)
    return np.append(n, d)


def jacobian(f: object, x: F64, h: float = 1e-7) -> F64:
    """Central finite-difference Jacobian of f at x."""
    fx = np.asarray(f(x))  # type: ignore[operator]
    out = np.zeros((fx.size, x.size))
    for i in range(x.size):
        dx = np.zeros_like(x)
        dx[i] = h
        out[:, i] = (np.asarray(f(x + dx)) - np.asarray(f(x - dx))) / (2 * h)  # type: ignore[operator]
    return out


@pytest.mark.parametrize(("n", "seed"), [(4, 1), (5, 2), (7, 3), (12, 4)])
def test_ols_plane_uncertainty_is_the_regression_covariance_with_n_minus_3_dof(n: int, seed: int) -> None:
    pts = cloud(n, seed)
    X = np.column_stack([pts[:, 0], pts[:, 1], np.ones(n)])
    beta, rss, _, _ = np.linalg.lstsq(X, pts[:, 2], rcond=None)
    s2 = float(rss[0]) / (n - 3)                       # three parameters: a, b, c
    cov_beta = s2 * np.linalg.inv(X.T @ X)
    J = jacobian(regression_normal_offset, beta)
    cov = J @ cov_beta @ J.T
    fit = fit_plane_ols(pts)
    n_ref, d_ref = regression_normal_offset(beta)[:3], regression_normal_offset(beta)[3]
    assert fit.plane.normal == pytest.approx(n_ref, abs=1e-12) and fit.plane.offset_m == pytest.approx(d_ref)
    assert fit.normal_covariance is not None and fit.normal_sigma_rad is not None
    np.testing.assert_allclose(fit.normal_covariance, cov[:3, :3], rtol=1e-5, atol=1e-14)
    assert fit.normal_sigma_rad == pytest.approx(math.sqrt(np.trace(cov[:3, :3])), rel=1e-6)
    assert fit.offset_sigma_m == pytest.approx(math.sqrt(cov[3, 3]), rel=1e-6)


def test_three_points_have_no_uncertainty() -> None:
    for fit in (fit_plane_ols(cloud(3, 5)), fit_plane_tls(cloud(3, 5))):
        assert fit.normal_sigma_rad is None and fit.offset_sigma_m is None and fit.normal_covariance is None


def tls_normal_offset(flat: F64) -> F64:
    """Unit normal and offset of the TLS plane (smallest principal axis), camera-facing."""
    p = flat.reshape(-1, 3)
    c = p.mean(axis=0)
    _, _, vt = np.linalg.svd(p - c)
    n = vt[2]
    n, d = oriented(n, -float(n @ c))
    return np.append(n, d)


@pytest.mark.parametrize(("n", "seed"), [(5, 6), (8, 7), (15, 8)])
def test_tls_plane_uncertainty_propagates_isotropic_noise_with_n_minus_3_dof(n: int, seed: int) -> None:
    pts = cloud(n, seed, noise_m=0.0005)
    ref = tls_normal_offset(pts.ravel())
    resid = pts @ ref[:3] + ref[3]
    s2 = float(resid @ resid) / (n - 3)                # isotropic point noise from the orthogonal residuals
    J = jacobian(tls_normal_offset, pts.ravel(), h=1e-8)
    cov = s2 * J @ J.T                                  # each coordinate of each point: variance s2
    fit = fit_plane_tls(pts)
    assert fit.normal_sigma_rad == pytest.approx(math.sqrt(np.trace(cov[:3, :3])), rel=0.02)
    assert fit.offset_sigma_m == pytest.approx(math.sqrt(cov[3, 3]), rel=0.02)
    assert fit.rms_m == pytest.approx(math.sqrt(float(resid @ resid) / n), rel=1e-9)


def ray_cloud(n_side: int, seed: int, sigma_m: float) -> tuple[F64, Plane]:
    """A grid of rays through a 40 x 30 deg field onto a tilted plane, range noise sigma_m along each ray."""
    plane = Plane(np.array([0.0, math.sin(math.radians(12.0)), -math.cos(math.radians(12.0))]), 0.7)
    u, v = np.meshgrid(np.linspace(-0.36, 0.36, n_side), np.linspace(-0.27, 0.27, n_side))
    rays = np.column_stack([u.ravel(), v.ravel(), np.ones(u.size)])
    rays /= np.linalg.norm(rays, axis=1)[:, None]
    t = -plane.offset_m / (rays @ plane.normal)         # range to the plane along each ray
    t += np.random.default_rng(seed).normal(0.0, sigma_m, t.size)
    return rays * t[:, None], plane


@pytest.mark.parametrize("confidence", [0.95, 0.68, 0.999])
def test_full_frame_intervals_are_value_plus_minus_the_normal_quantile_times_sigma(confidence: float) -> None:
    pts, _ = ray_cloud(12, 1, 0.001)
    res = fit_plane_points(pts, np.full(len(pts), 0.001), FullFrameSettings(confidence=confidence))
    z = NormalDist().inv_cdf(0.5 + confidence / 2.0)
    assert z == pytest.approx({0.95: 1.959964, 0.68: 0.994458, 0.999: 3.290527}[confidence], abs=1e-6)
    for name in ("tilt_x", "tilt_y", "height", "angle"):
        value, sigma = getattr(res, f"{name}_rad" if name != "height" else "height_m"), getattr(
            res, f"{name}_sigma_rad" if name != "height" else "height_sigma_m")
        lo, hi = getattr(res, f"{name}_ci_rad" if name != "height" else "height_ci_m")
        assert sigma > 0
        assert lo == pytest.approx(value - z * sigma, rel=1e-12) and hi == pytest.approx(value + z * sigma, rel=1e-12)
    assert res.confidence == confidence


def test_full_frame_sigmas_match_the_regression_covariance_of_the_same_points() -> None:
    """With known, equal range noise the robust fit's sigmas are the least-squares ones (within 15 %)."""
    sigma = 0.002
    ratios = []
    for seed in range(4):
        pts, truth = ray_cloud(14, seed, sigma)
        res = fit_plane_points(pts, np.full(len(pts), sigma))
        # independent: regression of z on (x, y) with covariance s^2 (X^T X)^-1, propagated to the
        # normal's tilt about x and to the height along the optical axis (-c for z = a x + b y + c ... at x=y=0)
        X = np.column_stack([pts[:, 0], pts[:, 1], np.ones(len(pts))])
        beta, rss, _, _ = np.linalg.lstsq(X, pts[:, 2], rcond=None)
        cov_beta = float(rss[0]) / (len(pts) - 3) * np.linalg.inv(X.T @ X)
        height_sigma = math.sqrt(cov_beta[2, 2])               # z at the optical axis is c
        tilt_sigma = math.sqrt(cov_beta[1, 1]) / (1.0 + beta[1] ** 2)   # atan(b): tilt about x
        ratios.append((res.height_sigma_m / height_sigma, res.tilt_x_sigma_rad / tilt_sigma))
        assert abs(res.height_m - truth.offset_m / abs(truth.normal[2])) < 4 * res.height_sigma_m
    mean = np.mean(ratios, axis=0)
    assert 0.85 < mean[0] < 1.15 and 0.85 < mean[1] < 1.15, ratios
