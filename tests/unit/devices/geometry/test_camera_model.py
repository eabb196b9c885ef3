"""Camera model: projection / undistortion against OpenCV, nominal FOV model, triangulation."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cellcal.devices.errors import CalibrationError
from cellcal.devices.geometry.camera_model import (
    NominalFovModel,
    normalized_to_pixels,
    pixel_grid_rays,
    pixel_rays,
    pixels_to_normalized,
    project,
    triangulate,
    undistort_pixels,
)
from cellcal.devices.pose import Pose
from cellcal.devices.types import Intrinsics


def random_intrinsics(rng: np.random.Generator) -> Intrinsics:
    """A realistic lens: ToF-like resolution, moderate Brown–Conrady + thin prism."""
    w, h = 224, 172
    return Intrinsics(
        width=w, height=h,
        fx=rng.uniform(180, 230), fy=rng.uniform(180, 230),
        cx=w / 2 + rng.uniform(-4, 4), cy=h / 2 + rng.uniform(-4, 4),
        k1=rng.uniform(-0.3, 0.3), k2=rng.uniform(-0.1, 0.1), k3=rng.uniform(-0.02, 0.02),
        p1=rng.uniform(-2e-3, 2e-3), p2=rng.uniform(-2e-3, 2e-3),
        s1=rng.uniform(-1e-3, 1e-3), s2=rng.uniform(-1e-4, 1e-4),
        s3=rng.uniform(-1e-3, 1e-3), s4=rng.uniform(-1e-4, 1e-4),
    )


def random_points_in_view(rng: np.random.Generator, n: int) -> np.ndarray:
    z = rng.uniform(0.2, 3.0, n)
    x = rng.uniform(-0.5, 0.5, n) * z
    y = rng.uniform(-0.38, 0.38, n) * z
    return np.column_stack((x, y, z))


@pytest.mark.parametrize("seed", range(5))
def test_project_matches_opencv(seed: int) -> None:
    rng = np.random.default_rng(seed)
    intr = random_intrinsics(rng)
    pts = random_points_in_view(rng, 500)
    ours = project(intr, pts)
    # OpenCV with a non-trivial extrinsic: move the points into another frame and back
    rvec = rng.normal(size=3) * 0.3
    tvec = rng.normal(size=3) * 0.1
    r = Rotation.from_rotvec(rvec)
    pts_obj = r.inv().apply(pts - tvec)
    ref, _ = cv2.projectPoints(pts_obj, rvec, tvec, intr.camera_matrix, intr.distortion)
    assert np.max(np.abs(ours - ref.reshape(-1, 2))) < 1e-6


def test_project_pinhole_formula() -> None:
    intr = Intrinsics(width=640, height=480, fx=500.0, fy=510.0, cx=320.5, cy=240.25)
    pts = np.array([[0.1, -0.2, 2.0], [0.0, 0.0, 1.0]])
    uv = project(intr, pts)
    np.testing.assert_allclose(uv[0], [500 * 0.05 + 320.5, 510 * -0.1 + 240.25], atol=1e-12)
    np.testing.assert_allclose(uv[1], [320.5, 240.25], atol=1e-12)


@pytest.mark.parametrize("seed", range(8))
def test_undistort_round_trip_and_opencv(seed: int) -> None:
    rng = np.random.default_rng(100 + seed)
    intr = random_intrinsics(rng)
    uv = np.column_stack((rng.uniform(0, intr.width - 1, 2000),
                          rng.uniform(0, intr.height - 1, 2000)))
    rays = pixel_rays(intr, uv)
    np.testing.assert_allclose(np.linalg.norm(rays, axis=1), 1.0, atol=1e-12)
    assert np.all(rays[:, 2] > 0)
    back = project(intr, rays)
    assert np.max(np.hypot(*(back - uv).T)) < 1e-6
    # agreement with OpenCV's undistortPoints (given enough iterations), in pixels
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)
    src = uv.reshape(-1, 1, 2)
    if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4.x
        ref = cv2.undistortPointsIter(src, intr.camera_matrix, intr.distortion, None, None, crit)
    else:  # OpenCV 5 folds the criteria into undistortPoints
        ref = cv2.undistortPoints(src, intr.camera_matrix, intr.distortion, None, None, None, crit)
    ref = np.asarray(ref).reshape(-1, 2)
    ours = pixels_to_normalized(intr, uv)
    assert np.max(np.abs(ours - ref)) * max(intr.fx, intr.fy) < 1e-6
    ideal = undistort_pixels(intr, uv)
    np.testing.assert_allclose(ideal, ref * [intr.fx, intr.fy] + [intr.cx, intr.cy], atol=1e-6)
    np.testing.assert_allclose(normalized_to_pixels(intr, ours), uv, atol=1e-6)


def test_rational_model_round_trip() -> None:
    intr = Intrinsics(width=320, height=240, fx=250, fy=250, cx=160, cy=120, k1=0.2, k2=-0.05,
                      k4=0.1, k5=-0.02, k6=0.01, p1=1e-3)
    uv = np.array([[0.0, 0.0], [319.0, 239.0], [160.0, 120.0], [10.5, 200.25]])
    back = project(intr, pixel_rays(intr, uv))
    assert np.max(np.abs(back - uv)) < 1e-6


def test_pixel_grid_rays_cached_and_consistent() -> None:
    intr = random_intrinsics(np.random.default_rng(7))
    grid = pixel_grid_rays(intr)
    assert grid.shape == (intr.height, intr.width, 3)
    assert pixel_grid_rays(intr) is grid
    assert not grid.flags.writeable
    v, u = 37, 150
    np.testing.assert_allclose(grid[v, u], pixel_rays(intr, [u, v])[0], atol=1e-12)
    back = project(intr, grid.reshape(-1, 3))
    vv, uu = np.mgrid[0:intr.height, 0:intr.width]
    assert np.max(np.abs(back - np.column_stack((uu.ravel(), vv.ravel())))) < 1e-6


def test_pixel_rays_without_distortion_is_exact() -> None:
    intr = Intrinsics(width=224, height=172, fx=200, fy=210, cx=111.5, cy=85.5)
    ray = pixel_rays(intr, [111.5 + 200 * 0.25, 85.5 - 210 * 0.5])[0]
    expected = np.array([0.25, -0.5, 1.0]) / math.sqrt(0.25**2 + 0.25 + 1)
    np.testing.assert_allclose(ray, expected, atol=1e-15)


@pytest.mark.parametrize(
    "bad",
    [np.array([[0.0, 0.0, -1.0]]), np.array([[0.1, 0.1, 0.0]]), np.array([[np.nan, 0, 1]]),
     np.zeros((3, 2)), "abc"],
)
def test_project_rejects_bad_points(bad: object) -> None:
    intr = Intrinsics(width=10, height=10, fx=10, fy=10, cx=5, cy=5)
    with pytest.raises(CalibrationError):
        project(intr, bad)  # type: ignore[arg-type]


def test_pixel_rays_rejects_bad_input() -> None:
    intr = Intrinsics(width=10, height=10, fx=10, fy=10, cx=5, cy=5)
    with pytest.raises(CalibrationError, match="NaN"):
        pixel_rays(intr, [[1.0, np.inf]])
    with pytest.raises(CalibrationError, match="shape"):
        pixel_rays(intr, [[1.0, 2.0, 3.0]])


def test_nominal_fov_model_matches_paper_table1() -> None:
    m = NominalFovModel.o3r222()
    phi, theta = m.phi_theta([20, 0, 20, 0], [0, 20, 20, 0])
    # phi_x = 20 * 60/224, phi_y = 20 * 45/172, corner = atan(hypot(tan, tan))
    np.testing.assert_allclose(np.degrees(phi[:2]), [20 * 60 / 224, 20 * 45 / 172], atol=1e-12)
    tx, ty = math.tan(math.radians(20 * 60 / 224)), math.tan(math.radians(20 * 45 / 172))
    assert phi[2] == pytest.approx(math.atan(math.hypot(tx, ty)), abs=1e-14)
    assert math.degrees(phi[2]) == pytest.approx(7.46740, abs=1e-5)  # spec's value at 20 px
    assert phi[3] == 0.0
    np.testing.assert_allclose(theta[:2], [0.0, math.pi / 2], atol=1e-15)
    _, th = m.phi_theta([0, -5, 3], [-5, 0, -3])
    np.testing.assert_allclose(th[:2], [1.5 * math.pi, math.pi], atol=1e-15)
    assert 1.5 * math.pi < th[2] < 2 * math.pi
    rays = m.rays(np.array([20, -10]), np.array([20, 4]))
    np.testing.assert_allclose(np.linalg.norm(rays, axis=-1), 1.0)
    np.testing.assert_allclose(np.arccos(rays[0, 2]), phi[2], atol=1e-12)


def test_nominal_fov_model_validates() -> None:
    with pytest.raises(CalibrationError):
        NominalFovModel(0, 10, 1.0, 1.0)
    with pytest.raises(CalibrationError):
        NominalFovModel(10, 10, 4.0, 1.0)
    with pytest.raises(CalibrationError):
        NominalFovModel.o3r222().phi_theta([1000], [0])


@pytest.mark.parametrize("n_views", [2, 3, 6])
def test_triangulation_exact(n_views: int) -> None:
    rng = np.random.default_rng(n_views)
    intr = random_intrinsics(rng)
    target = np.array([0.1, -0.05, 1.2])
    poses, pixels, intrs = [], [], []
    for _ in range(n_views):
        # cameras around the target, each looking roughly at it
        centre = target + rng.normal(size=3) * 0.3 + [0, 0, -1.0]
        z_axis = target - centre
        z_axis /= np.linalg.norm(z_axis)
        x_axis = np.cross([0, 1.0, 0], z_axis)
        x_axis /= np.linalg.norm(x_axis)
        y_axis = np.cross(z_axis, x_axis)
        rot = Rotation.from_matrix(np.column_stack((x_axis, y_axis, z_axis)))
        tilt = Rotation.from_rotvec(rng.normal(size=3) * 0.05)
        pose = Pose(rot * tilt, centre)
        poses.append(pose)
        intrs.append(intr)
        pixels.append(project(intr, pose.inv().apply(target))[0])
    np.testing.assert_allclose(triangulate(intr, poses, pixels), target, atol=1e-9)
    np.testing.assert_allclose(triangulate(intrs, poses, pixels), target, atol=1e-9)


def test_triangulation_rejects_degenerate() -> None:
    intr = Intrinsics(width=100, height=100, fx=100, fy=100, cx=50, cy=50)
    p = Pose.identity()
    with pytest.raises(CalibrationError, match="at least 2"):
        triangulate(intr, [p], [[50, 50]])
    with pytest.raises(CalibrationError, match="parallel"):
        triangulate(intr, [p, Pose(Rotation.identity(), [0, 0, 1.0])], [[50, 50], [50, 50]])
    with pytest.raises(CalibrationError, match="pixels"):
        triangulate(intr, [p, p], [[50, 50]])
