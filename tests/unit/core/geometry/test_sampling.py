"""Robust window sampling of frames."""

from __future__ import annotations

import numpy as np
import pytest

from cellcal.core.geometry.planes import Plane
from cellcal.core.geometry.sampling import sample_window
from cellcal.devices import CalibrationError, Frame, Intrinsics
from cellcal.devices.geometry.camera_model import pixel_grid_rays

INTR = Intrinsics(40, 30, 35.0, 35.0, 19.5, 14.5, k1=-0.05)
PLANE = Plane(np.array([0.0, -0.17364817766693033, -0.984807753012208]), 0.5)


def plane_frame() -> Frame:
    pts = PLANE.intersect_rays(pixel_grid_rays(INTR)).astype(np.float32)
    d = np.linalg.norm(pts, axis=2).astype(np.float32)
    return Frame(d, pts, np.ones_like(d), np.isfinite(d), INTR, 0.0, 0)


def test_subpixel_sample_lies_on_the_plane_and_on_the_ray() -> None:
    frame = plane_frame()
    s = sample_window([frame], INTR.cx, INTR.cy, 3)
    assert abs(PLANE.signed_distance(s.xyz_m)) < 1e-6
    # at the principal point the ray is the optical axis: x, y ~ 0
    assert abs(s.xyz_m[0]) < 1e-6 and abs(s.xyz_m[1]) < 2e-4
    assert s.n_valid == 9 and s.pixel == (20, 15)


def test_invalid_pixels_and_outliers_are_skipped() -> None:
    frame = plane_frame()
    clean = sample_window([frame], 10.0, 10.0, 5)
    frame.valid[10, 10] = False
    frame.xyz[10, 11] = (9.0, 9.0, 9.0)  # a flying pixel, still flagged valid
    s = sample_window([frame], 10.0, 10.0, 5)
    assert s.n_valid == 24
    np.testing.assert_allclose(s.xyz_m, clean.xyz_m, atol=2e-3)


def test_window_outside_image_and_all_invalid() -> None:
    frame = plane_frame()
    with pytest.raises(CalibrationError, match="leaves the 40x30 image; use a smaller perimeter"):
        sample_window([frame], 39.5, 10.0, 3)
    frame.valid[:] = False
    with pytest.raises(CalibrationError, match=r"only 0 valid samples \(need 1\) around pixel \(10.0, 10.0\)"):
        sample_window([frame], 10.0, 10.0, 3)
    with pytest.raises(CalibrationError, match="window_px must be a positive odd number"):
        sample_window([frame], 10.0, 10.0, 2)
