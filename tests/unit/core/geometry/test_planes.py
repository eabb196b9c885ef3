"""Plane type and the OLS / TLS / robust fits, with honest uncertainty."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from cellcal.core.geometry.planes import (
    Plane,
    PlaneFit,
    fit_plane_ols,
    fit_plane_tls,
)
from cellcal.core.geometry.robust_fit import fit_plane_robust
from cellcal.devices.errors import CalibrationError
from cellcal.devices.pose import Pose


def plane_scene(rng: np.random.Generator, n: int, noise_m: float, *, max_tilt_rad: float = 0.6,
                distance_m: float = 1.0, half_size_m: float = 0.4
                ) -> tuple[np.ndarray, np.ndarray, float]:
    """Points on a random plane in front of the camera: (points, true normal, true offset).

    The true normal is oriented toward the camera origin.
    """
    axis = rng.normal(size=3)
    axis[2] = 0.0
    axis /= np.linalg.norm(axis)
    rot = Rotation.from_rotvec(axis * rng.uniform(0, max_tilt_rad))
    centre = np.array([rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1), distance_m])
    uv = rng.uniform(-half_size_m, half_size_m, (n, 2))
    local = np.column_stack((uv, rng.normal(0.0, noise_m, n)))
    pts = rot.apply(local) + centre
    normal = -rot.apply([0.0, 0.0, 1.0])  # faces the camera (the camera is at -z)
    offset = -float(normal @ centre)
    assert offset > 0
    return pts, normal, offset


def normal_error_rad(fit: PlaneFit, normal: np.ndarray) -> float:
    return math.acos(min(1.0, float(fit.plane.normal @ normal)))


FITS: dict[str, Callable[[np.ndarray], PlaneFit]] = {
    "ols": fit_plane_ols,
    "tls": fit_plane_tls,
    "robust": lambda p: fit_plane_robust(p, threshold_m=0.02, seed=3),
}


# ---------------------------------------------------------------------- Plane
def test_plane_normalises_and_orients() -> None:
    pl = Plane(np.array([0.0, 0.0, 2.0]), -3.0)  # z = 1.5, normal +z: camera on negative side
    np.testing.assert_allclose(pl.normal, [0, 0, 1])
    assert pl.offset_m == pytest.approx(-1.5)
    o = pl.oriented_toward_origin()
    np.testing.assert_allclose(o.normal, [0, 0, -1])
    assert o.offset_m == pytest.approx(1.5)
    assert o.signed_distance([0.0, 0.0, 0.0]) == pytest.approx(1.5)
    np.testing.assert_allclose(o.signed_distance([[0, 0, 2.0], [5, -3, 1.5]]), [-0.5, 0.0])
    np.testing.assert_allclose(o.point_m, [0, 0, 1.5])
    with pytest.raises(CalibrationError):
        Plane(np.zeros(3), 1.0)
    with pytest.raises(CalibrationError):
        Plane(np.array([0, 0, np.nan]), 1.0)


def test_single_axis_tilt_angles() -> None:
    """Camera tilted by 10 deg about x: plane at 80 deg to the optical axis (the paper)."""
    alpha = math.radians(10.0)
    h = 0.46
    pl = Plane(np.array([0.0, -math.sin(alpha), -math.cos(alpha)]), h)
    assert math.degrees(pl.tilt_about_x_rad()) == pytest.approx(10.0, abs=1e-12)
    assert pl.tilt_about_y_rad() == pytest.approx(0.0, abs=1e-15)
    assert math.degrees(pl.angle_to_optical_axis_rad()) == pytest.approx(80.0, abs=1e-12)
    ang = pl.angles_to_camera_planes_rad()
    assert math.degrees(ang.xoy_rad) == pytest.approx(10.0, abs=1e-12)
    assert math.degrees(ang.xoz_rad) == pytest.approx(80.0, abs=1e-12)
    assert math.degrees(ang.yoz_rad) == pytest.approx(90.0, abs=1e-12)
    assert pl.distance_along_normal_m() == pytest.approx(h)
    assert pl.distance_along_optical_axis_m() == pytest.approx(h / math.cos(alpha))
    # the same tilt about y, opposite sign
    pl_y = Plane(np.array([math.sin(-alpha), 0.0, -math.cos(alpha)]), h)
    assert math.degrees(pl_y.tilt_about_y_rad()) == pytest.approx(-10.0, abs=1e-12)


def test_tilt_sign_matches_a_rotated_camera() -> None:
    """Rotate a camera about its own x by +alpha above a floor: tilt_about_x == +alpha."""
    alpha = 0.2
    floor_in_world = Plane(np.array([0.0, 0.0, -1.0]), 1.0)  # z = 1 in a frontal camera frame
    t_world_cam = Pose(Rotation.from_rotvec([alpha, 0.0, 0.0]), np.zeros(3))
    in_cam = floor_in_world.transformed(t_world_cam.inv())
    assert in_cam.tilt_about_x_rad() == pytest.approx(alpha, abs=1e-12)
    t_world_cam = Pose(Rotation.from_rotvec([0.0, -alpha, 0.0]), np.zeros(3))
    assert floor_in_world.transformed(t_world_cam.inv()).tilt_about_y_rad() == pytest.approx(-alpha)


def test_optical_axis_errors() -> None:
    with pytest.raises(CalibrationError, match="parallel"):
        Plane(np.array([1.0, 0, 0]), 1.0).distance_along_optical_axis_m()
    with pytest.raises(CalibrationError, match="behind"):
        Plane(np.array([0, 0, 1.0]), 1.0).distance_along_optical_axis_m()  # plane at z = -1


def test_intersect_rays_and_transform() -> None:
    rng = np.random.default_rng(4)
    pts, normal, offset = plane_scene(rng, 50, 0.0)
    pl = Plane(normal, offset)
    rays = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    np.testing.assert_allclose(pl.intersect_rays(rays), pts, atol=1e-12)
    grid = rays.reshape(5, 10, 3)
    assert pl.intersect_rays(grid).shape == (5, 10, 3)
    behind = pl.intersect_rays(-rays[:3])
    assert np.all(np.isnan(behind))
    pose = Pose(Rotation.random(random_state=2), rng.normal(size=3))
    moved = pl.transformed(pose)
    np.testing.assert_allclose(moved.signed_distance(pose.apply(pts)), 0.0, atol=1e-12)
    back = moved.transformed(pose.inv())
    np.testing.assert_allclose(back.normal, pl.normal, atol=1e-12)
    assert back.offset_m == pytest.approx(pl.offset_m, abs=1e-12)
    q = np.array([0.3, -0.2, 0.4])
    assert moved.signed_distance(pose.apply(q)) == pytest.approx(pl.signed_distance(q), abs=1e-12)
    np.testing.assert_allclose(pl.signed_distance(pl.project_points(q)), 0.0, atol=1e-12)


# ---------------------------------------------------------------------- fits
@pytest.mark.parametrize("method", FITS)
def test_exact_points_give_exact_plane(method: str) -> None:
    pts, normal, offset = plane_scene(np.random.default_rng(0), 30, 0.0)
    fit = FITS[method](pts)
    np.testing.assert_allclose(fit.plane.normal, normal, atol=1e-10)
    assert fit.plane.offset_m == pytest.approx(offset, abs=1e-10)
    assert fit.rms_m < 1e-10
    assert fit.n_points == 30
    assert fit.method == method


def test_three_points_have_no_uncertainty() -> None:
    fit = fit_plane_tls([[0, 0, 1.0], [1, 0, 1.0], [0, 1, 1.0]])
    np.testing.assert_allclose(fit.plane.normal, [0, 0, -1], atol=1e-15)
    assert fit.plane.offset_m == pytest.approx(1.0)
    assert fit.normal_sigma_rad is None and fit.offset_sigma_m is None
    assert fit_plane_ols([[0, 0, 1.0], [1, 0, 1.0], [0, 1, 1.0]]).normal_sigma_rad is None


@given(seed=st.integers(0, 2**32 - 1), noise_mm=st.floats(0.5, 10.0),
       method=st.sampled_from(sorted(FITS)))
@settings(max_examples=40, deadline=None)
def test_fits_recover_normal_within_noise_bound(seed: int, noise_mm: float, method: str) -> None:
    rng = np.random.default_rng(seed)
    n, half = 400, 0.4
    noise = noise_mm * 1e-3
    pts, normal, offset = plane_scene(rng, n, noise, half_size_m=half)
    fit = FITS[method](pts)
    # Theory: angular error ~ noise / (spread * sqrt(n)), spread = half / sqrt(3) per axis
    # (the tilt stretches OLS's vertical-noise model by at most 1/cos(0.6)).
    bound = 6.0 * noise / (half / math.sqrt(3.0) * math.sqrt(n)) / math.cos(0.6)
    assert normal_error_rad(fit, normal) < bound
    assert abs(fit.plane.offset_m - offset) < 6.0 * noise
    assert fit.rms_m == pytest.approx(noise, rel=0.3)


@pytest.mark.parametrize("method", sorted(FITS))
def test_reported_sigma_is_honest(method: str) -> None:
    """True error within 3 sigma in >= 99 % of seeded trials, and sigma not inflated."""
    trials, inside_n, inside_d, ratios = 300, 0, 0, []
    for seed in range(trials):
        rng = np.random.default_rng(10_000 + seed)
        noise = rng.uniform(0.001, 0.008)
        pts, normal, offset = plane_scene(rng, int(rng.integers(30, 300)), noise)
        fit = FITS[method](pts)
        assert fit.normal_sigma_rad is not None and fit.offset_sigma_m is not None
        err = normal_error_rad(fit, normal)
        inside_n += err <= 3.0 * fit.normal_sigma_rad
        inside_d += abs(fit.plane.offset_m - offset) <= 3.0 * fit.offset_sigma_m
        ratios.append(err / fit.normal_sigma_rad)
    assert inside_n / trials >= 0.99
    assert inside_d / trials >= 0.99
    # honest, not merely conservative: the typical error is of the order of sigma
    assert 0.5 < float(np.mean(ratios)) < 1.5


def test_angle_sigma_is_honest() -> None:
    inside = 0
    for seed in range(200):
        rng = np.random.default_rng(seed)
        pts, normal, _ = plane_scene(rng, 100, 0.005)
        fit = fit_plane_tls(pts)
        true = Plane(normal, 1.0).angle_to_optical_axis_rad()
        sig = fit.angle_to_optical_axis_sigma_rad()
        assert sig is not None and sig > 0
        inside += abs(fit.plane.angle_to_optical_axis_rad() - true) <= 3 * sig
    assert inside >= 198


@given(seed=st.integers(0, 2**32 - 1))
@settings(max_examples=25, deadline=None)
def test_robust_fit_ignores_40_percent_outliers(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n, noise = 1000, 0.003
    pts, normal, offset = plane_scene(rng, n, noise)
    n_out = int(0.4 * n)
    # gross outliers: boxes standing on the plane and random clutter in front of it
    pts[:n_out // 2] -= normal * rng.uniform(0.05, 0.4, n_out // 2)[:, None]
    clutter = rng.uniform([-0.5, -0.5, 0.3], [0.5, 0.5, 1.5], (n_out - n_out // 2, 3))
    pts[n_out // 2:n_out] = clutter
    fit = fit_plane_robust(pts, threshold_m=5 * noise, seed=seed % 1000)
    assert fit.inliers is not None and fit.inliers.shape == (n,)
    true_dist = np.abs(Plane(normal, offset).signed_distance(pts))
    # every clear inlier kept, every clear outlier rejected (only the band around the
    # threshold may go either way, since the fitted plane differs slightly from truth)
    assert np.all(fit.inliers[true_dist < 4 * noise])
    assert not np.any(fit.inliers[true_dist > 6 * noise])
    assert 0.55 < fit.inlier_fraction < 0.65
    assert normal_error_rad(fit, normal) < 6.0 * noise / (0.4 / math.sqrt(3) * math.sqrt(600))
    assert fit.normal_sigma_rad is not None
    assert normal_error_rad(fit, normal) < 4 * fit.normal_sigma_rad
    # the non-robust fits are ruined by the same data
    assert normal_error_rad(fit_plane_tls(pts), normal) > 5 * fit.normal_sigma_rad


def test_robust_fit_is_seeded_and_large_clouds_work() -> None:
    rng = np.random.default_rng(1)
    pts, normal, _ = plane_scene(rng, 38_000, 0.005)
    pts[:15_000, 2] += rng.uniform(0.05, 0.3, 15_000)
    a = fit_plane_robust(pts, 0.02, seed=7)
    b = fit_plane_robust(pts, 0.02, seed=7)
    assert a.inliers is not None and b.inliers is not None
    assert np.array_equal(a.inliers, b.inliers)
    np.testing.assert_array_equal(a.plane.normal, b.plane.normal)
    assert normal_error_rad(a, normal) < 1e-3


@pytest.mark.parametrize("method", sorted(FITS))
@pytest.mark.parametrize(
    ("points", "match"),
    [
        (np.zeros((2, 3)), "at least 3"),
        (np.ones((10, 3)), "coincident"),
        (np.outer(np.arange(10.0), [1.0, 2.0, 3.0]), "collinear"),
        (np.array([[0, 0, 1.0], [1, 0, 1], [0, 1, np.nan], [1, 1, 1]]), "NaN or inf .*row 2"),
        (np.array([[0, 0, 1.0], [1, 0, np.inf], [0, 1, 1], [1, 1, 1]]), "NaN or inf"),
        (np.zeros((5, 2)), "shape"),
        ("not points", "numeric|shape"),
    ],
)
def test_bad_input_is_one_line_calibration_error(method: str, points: object, match: str) -> None:
    with pytest.raises(CalibrationError, match=match) as info:
        FITS[method](points)  # type: ignore[arg-type]
    assert "\n" not in str(info.value)


def test_ols_rejects_vertical_plane_and_robust_rejects_bad_threshold() -> None:
    rng = np.random.default_rng(0)
    wall = np.column_stack((rng.uniform(-1, 1, 20), np.zeros(20), rng.uniform(0.5, 2, 20)))
    with pytest.raises(CalibrationError, match="collinear in x-y"):
        fit_plane_ols(wall)
    fit = fit_plane_tls(wall)  # TLS handles it
    assert abs(fit.plane.normal[1]) == pytest.approx(1.0)
    pts, _, _ = plane_scene(rng, 20, 0.001)
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(CalibrationError, match="threshold_m"):
            fit_plane_robust(pts, bad)
