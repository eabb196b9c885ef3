"""``--decimate``: every k-th pixel keeps the same measurements on a coarser grid; ``auto`` picks k by pixel count."""

from __future__ import annotations

import numpy as np
import pytest

from cellcal.core.calibration.calibrator import build_camera
from cellcal.core.track.decimate import auto_decimation, decimated


def _frame(kind: str, width: int, height: int) -> object:
    doc = {"camera": {"backend": "sim", "kind": kind, "width": width, "height": height, "distortion": False,
                      "noise": False}, "sim": {}}
    if kind == "stereo":
        doc["camera"].pop("distortion")
    with build_camera(doc) as camera:
        return camera.capture(5.0)


def test_the_kept_pixels_are_the_same_points_on_the_coarser_grid() -> None:
    frame = _frame("tof", 224, 172)
    coarse = decimated(frame, 3)
    assert coarse.shape == (58, 75) and coarse.intrinsics.width == 75 and coarse.intrinsics.height == 58
    np.testing.assert_array_equal(coarse.xyz, frame.xyz[::3, ::3])
    np.testing.assert_array_equal(coarse.valid, frame.valid[::3, ::3])
    np.testing.assert_array_equal(coarse.distance, frame.distance[::3, ::3])
    # a kept pixel (u', v') = (u / 3, v / 3): the pinhole of the coarse grid projects its point there
    i = coarse.intrinsics
    v, u = np.nonzero(coarse.valid)
    p = coarse.xyz[v, u].astype(np.float64)
    np.testing.assert_allclose(i.fx * p[:, 0] / p[:, 2] + i.cx, u, atol=1e-3)
    np.testing.assert_allclose(i.fy * p[:, 1] / p[:, 2] + i.cy, v, atol=1e-3)
    assert coarse.timestamp == frame.timestamp and coarse.measurement == frame.measurement
    assert decimated(frame, 1) is frame


@pytest.mark.parametrize("k", [0, -1, 1.5, "2"])
def test_a_decimation_that_is_not_a_positive_integer_is_refused(k: object) -> None:
    with pytest.raises(ValueError, match="decimation must be a positive integer"):
        decimated(_frame("tof", 32, 24), k)  # type: ignore[arg-type]


@pytest.mark.parametrize(("kind", "width", "height", "k"), [
    ("tof", 224, 172, 1), ("tof", 640, 400, 1), ("tof", 1280, 800, 2),
    ("stereo", 320, 200, 1), ("stereo", 640, 400, 2), ("stereo", 1280, 800, 3)])
def test_auto_keeps_at_most_115k_pixels_for_stereo_and_300k_for_tof(kind: str, width: int, height: int,
                                                                   k: int) -> None:
    frame = _frame(kind, width, height)
    assert auto_decimation(frame) == k
    budget = 115_000 if kind == "stereo" else 300_000
    assert width * height / k**2 <= budget < width * height / max(k - 1, 1) ** 2 or k == 1
