"""The pixel ray grid: one projection check instead of Newton over every pixel, same rays (ADR 0021)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from cellcal.devices.geometry import camera_model
from cellcal.devices.geometry.camera_model import UNDISTORT_FAIL_PX, pixel_grid_rays, project
from cellcal.sims.camera import SimCameraConfig, o3r222_intrinsics


def _pixels(h: int, w: int) -> np.ndarray:
    vv, uu = np.mgrid[0:h, 0:w]
    return np.column_stack((uu.ravel(), vv.ravel())).astype(np.float64)


def test_the_sim_cameras_rays_are_opencvs_converged_undistortion() -> None:
    intr = SimCameraConfig().intrinsics()
    rays = pixel_grid_rays(intr).reshape(-1, 3)
    uv = _pixels(intr.height, intr.width)
    # OpenCV's own iteration run far past convergence, independently of the grid's code path
    ref = cv2.undistortPointsIter(uv.reshape(-1, 1, 2), intr.camera_matrix, intr.distortion, None, None,
                                  (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)).reshape(-1, 2)
    ref_rays = np.column_stack((ref, np.ones(len(ref))))
    ref_rays /= np.linalg.norm(ref_rays, axis=1, keepdims=True)
    assert np.abs(rays - ref_rays).max() < 1e-12
    assert np.abs(project(intr, rays) - uv).max() < 1e-9  # every ray images its pixel


@pytest.mark.parametrize("distortion", [
    {"k1": -0.4, "k2": 0.2, "k3": -0.05, "p1": 1e-3, "p2": -1e-3},   # folds over near the corners
    {"k1": 0.2, "k4": 0.1, "k5": 0.05, "k6": 0.01, "s1": 0.01, "s3": -0.01},
])
def test_strong_lenses_keep_only_rays_that_image_their_pixel(distortion: dict[str, float]) -> None:
    intr = o3r222_intrinsics(224, 172, 100.0, 80.0, **distortion)
    rays = pixel_grid_rays(intr).reshape(-1, 3)
    uv = _pixels(intr.height, intr.width)
    ok = np.all(np.isfinite(rays), axis=1)
    assert 0 < np.count_nonzero(ok) <= len(ok)
    assert np.abs(project(intr, rays[ok]) - uv[ok]).max() < UNDISTORT_FAIL_PX
    # where no ray was kept, OpenCV's converged iteration does not image the pixel either
    bad = ~ok
    if np.any(bad):
        guess = cv2.undistortPointsIter(uv[bad].reshape(-1, 1, 2), intr.camera_matrix, intr.distortion, None, None,
                                        (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)).reshape(-1, 2)
        back = camera_model.normalized_to_pixels(intr, guess)
        assert np.all(np.hypot(*(back - uv[bad]).T) > UNDISTORT_FAIL_PX)


def test_trimmed_distortion_and_chunks_give_the_same_pixels() -> None:
    intr = SimCameraConfig().intrinsics()
    assert len(camera_model._short_distortion(intr)) == 4           # k1 k2 p1 p2 (the rest zero)
    rng = np.random.default_rng(0)
    xy = rng.uniform(-0.6, 0.6, size=(camera_model._PROJECT_CHUNK + 1000, 2))  # two chunks
    obj = np.column_stack((xy, np.ones(len(xy)))).reshape(-1, 1, 3)
    full, _ = cv2.projectPoints(obj, np.zeros(3), np.zeros(3), intr.camera_matrix, intr.distortion)
    pixels, jac = camera_model._project_normalized(intr, xy, jacobian=True)
    assert np.array_equal(pixels, full.reshape(-1, 2))             # bit for bit
    assert jac is not None and jac.shape == (len(xy), 2, 2)
    assert np.allclose(jac[:, 0, 0], intr.fx, rtol=0.5) and np.all(np.abs(jac[:, 1, 0]) < 0.1 * intr.fx)
