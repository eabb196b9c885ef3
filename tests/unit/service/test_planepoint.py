"""pixel_to_base's geometry against PlaneMap, and its first-order propagation against finite differences."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cellcal.core.geometry.planemap import PlaneMap
from cellcal.core.geometry.planes import Plane, tangent_basis
from cellcal.core.geometry.relative import perturb
from cellcal.core.service.planepoint import MAX_PIXELS, PlaneCalibration, pixel_rays, pixel_to_base
from cellcal.devices.errors import CalibrationError
from cellcal.devices.pose import Pose
from cellcal.devices.types import Intrinsics

#: A ToF-like lens with every term of the Brown model the rays invert (rational and thin prism too).
LENS = Intrinsics(width=224, height=172, fx=194.0, fy=207.6, cx=111.5, cy=85.5, k1=-0.06, k2=0.015, k3=-0.002,
                  p1=0.0004, p2=-0.0002, k4=0.01, k5=-0.003, k6=0.001, s1=0.0005, s2=-0.0001, s3=0.0003, s4=0.0001)
MOUNT = Pose.from_xyz_rpy([0.0, 0.04, 0.06], np.radians([0.0, 0.0, 90.0]))
FLANGE = Pose.from_xyz_rpy([0.3, 0.05, 0.5], np.radians([180.0, 8.0, 5.0]))  # looking down at the table
PLANE = Plane.from_point_normal([0.0, 0.0, 0.002], [0.01, -0.02, 1.0])


def calibration(cov: np.ndarray | None = None) -> PlaneCalibration:
    if cov is None:
        a = np.random.default_rng(3).normal(size=(9, 9)) * 1e-3
        cov = a @ a.T
    return PlaneCalibration(LENS, MOUNT, PLANE, PLANE.point_m, cov)


def pixels(n: int, seed: int = 0, margin: float = 0.0) -> np.ndarray:
    lo, hi = np.array([-margin, -margin]), np.array([LENS.width - 1 + margin, LENS.height - 1 + margin])
    return np.random.default_rng(seed).uniform(lo, hi, (n, 2))


def moved(cal: PlaneCalibration, theta: np.ndarray) -> PlaneMap:
    """The exact PlaneMap of the calibration moved by the 9 parameters ``theta`` (the module's parameterisation)."""
    mount = perturb(cal.mount, theta[:6])
    axes = tangent_basis(np.array(cal.plane.normal))
    normal = Rotation.from_rotvec(axes @ theta[6:8]).apply(np.array(cal.plane.normal))
    plane = Plane.from_point_normal(cal.anchor_m + theta[8] * np.array(cal.plane.normal), normal)
    return PlaneMap.from_base_plane(cal.intrinsics, plane, FLANGE @ mount)


def test_rays_are_the_lens_models_own_inverse_inside_and_around_the_image() -> None:
    uv = pixels(5000, margin=20.0)  # 20 px beyond the border too (the seed table is clamped there)
    want = PlaneMap(LENS, PLANE).rays_cam(uv)
    got = pixel_rays(LENS, uv)
    assert np.all(np.isfinite(got))
    assert np.max(np.abs(got - want)) < 1e-12


def test_points_are_planemaps_to_a_nanometre() -> None:
    uv = pixels(20000, seed=1)
    points, sigma = pixel_to_base(calibration(), FLANGE, uv)
    want = calibration().plane_map(FLANGE).pixel_to_base(uv)
    assert np.max(np.abs(points - want)) < 1e-9
    assert np.all(sigma > 0)


def test_a_ray_that_misses_the_plane_gives_nan() -> None:
    away = Pose.from_xyz_rpy([0.3, 0.0, 0.5], [0.0, 0.0, 0.0])  # looking up: every ray leaves the table
    points, sigma = pixel_to_base(calibration(), away, pixels(10))
    assert np.all(np.isnan(points)) and np.all(np.isnan(sigma))


@pytest.mark.parametrize("k", range(9))
def test_each_parameters_column_is_the_exact_maps_derivative(k: int) -> None:
    """One parameter's 1-sigma alone is |dp/dtheta_k| sigma_k: compared with central differences of PlaneMap."""
    sig = np.array([2e-3, 1e-3, 3e-3, 1e-3, 2e-3, 5e-4, 1e-3, 2e-3, 1e-3])
    cov = np.zeros((9, 9))
    cov[k, k] = sig[k] ** 2
    cal = calibration(cov)
    uv = pixels(50, seed=2)
    _, sigma = pixel_to_base(cal, FLANGE, uv)
    step = np.zeros(9)
    step[k] = 1e-6
    derivative = (moved(cal, step).pixel_to_base(uv) - moved(cal, -step).pixel_to_base(uv)) / 2e-6
    want = np.abs(derivative) * sig[k]
    assert np.allclose(sigma, want, rtol=1e-4, atol=1e-12)


def test_too_many_pixels_or_a_wrong_shape_is_refused() -> None:
    with pytest.raises(CalibrationError, match="more than"):
        pixel_to_base(calibration(), FLANGE, np.zeros((MAX_PIXELS + 1, 2)))
    with pytest.raises(CalibrationError, match=r"shape \(N, 2\)"):
        pixel_to_base(calibration(), FLANGE, np.zeros((3, 3)))
