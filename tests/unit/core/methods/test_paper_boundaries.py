"""Exact boundaries of the paper's grid (85.5 px at 224x172) and of the sampling window at the image edge.

Pixel centres are at integers, so a 224x172 image spans columns 0..223 and rows 0..171 and
its centre is (111.5, 85.5): the largest perimeter puts P1-P9 on rows 0 and 171 exactly. A
sample window may touch the outermost pixel centres but not go one step (or a hair) past
them: past the edge the bilinear weights would extrapolate.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from cellcal.core.geometry.sampling import sample_points, sample_window
from cellcal.core.methods.grid import camera_grid, grid_pixels, grid_points, max_perimeter_px, sample_grid
from cellcal.devices import CalibrationError, Frame, Intrinsics

PAPER = Intrinsics(width=224, height=172, fx=190.0, fy=200.0, cx=111.5, cy=85.5)


def test_the_largest_perimeter_at_224x172_is_85_5_px_exactly() -> None:
    assert max_perimeter_px(224, 172) == 85.5
    assert max_perimeter_px(172, 224) == 85.5  # portrait: the width limits
    points = grid_points(85.5)
    assert {(g.dx_px, g.dy_px) for g in points} == {(sx * 85.5, sy * 85.5) for sx in (-1, 0, 1) for sy in (-1, 0, 1)}
    uv = grid_pixels(PAPER, 85.5)
    assert uv[:, 1].min() == 0.0 and uv[:, 1].max() == 171.0  # the top and bottom rows' centres
    assert uv[:, 0].min() == 26.0 and uv[:, 0].max() == 197.0
    for too_far in (math.nextafter(85.5, 86.0), 85.6, 86.0):
        with pytest.raises(CalibrationError) as info:
            grid_points(too_far)
        assert str(info.value) == (f"perimeter {too_far:g} px puts points outside the 224x172 image "
                                   "(at most 85.5 px from the centre)")


def test_the_limit_follows_an_off_centre_principal_point() -> None:
    # 4.25 px from the left edge, 10.75 from the top: those distances are the limit
    assert max_perimeter_px(64, 48, cx=4.25, cy=30.0) == 4.25
    assert max_perimeter_px(64, 48, cx=30.0, cy=10.75) == 10.75
    assert max_perimeter_px(64, 48, cx=59.5, cy=30.0) == 3.5  # 63 - 59.5 to the right edge
    assert max_perimeter_px(64, 48, cx=30.0, cy=44.0) == 3.0  # 47 - 44 to the bottom edge
    off = Intrinsics(width=64, height=48, fx=50.0, fy=50.0, cx=30.0, cy=44.0)
    assert len(camera_grid(off, 3.0)) == 9
    with pytest.raises(CalibrationError, match=r"\(at most 3 px from the centre\)"):
        camera_grid(off, 3.25)


def test_any_positive_perimeter_below_the_limit_is_a_grid() -> None:
    for p in (1e-6, 0.5, 1.0, 20.0):
        assert [(g.name, g.dx_px, g.dy_px) for g in grid_points(p)][:2] == [("P1", p, p), ("P2", 0.0, p)]
    for bad in (0, -1.0, -0.0, float("nan"), float("inf")):
        with pytest.raises(CalibrationError) as info:
            grid_points(bad)
        assert str(info.value) == f"perimeter must be a positive number of pixels, got {bad!r}"
    with pytest.raises(CalibrationError, match=r"^perimeter must be a number of pixels, got 'abc'$"):
        grid_points("abc")  # type: ignore[arg-type]


def test_the_limit_uses_the_given_centre_and_the_camera_s_own_image_size() -> None:
    # a principal point 4.25 px from the left edge of a 64x48 image: 4.25 px fits, 4.5 does not
    assert len(grid_points(4.25, width_px=64, height_px=48, cx=4.25, cy=30.0)) == 9
    with pytest.raises(CalibrationError, match=r"outside the 64x48 image \(at most 4\.25 px"):
        grid_points(4.5, width_px=64, height_px=48, cx=4.25, cy=30.0)
    with pytest.raises(CalibrationError, match=r"outside the 64x48 image \(at most 3\.5 px"):
        grid_points(4.0, width_px=64, height_px=48, cx=59.5, cy=24.0)
    # camera_grid takes width, height and centre from the intrinsics
    right = Intrinsics(width=64, height=48, fx=50.0, fy=50.0, cx=59.5, cy=24.0)
    with pytest.raises(CalibrationError, match=r"outside the 64x48 image \(at most 3\.5 px"):
        camera_grid(right, 4.0)
    uv = grid_pixels(right, 3.5)
    assert uv[:, 0].max() == 63.0 and uv[:, 0].min() == 56.0 and uv[:, 1].min() == 20.5


def test_sample_grid_names_each_sample_after_its_point() -> None:
    frame = ramp_frame(24, 18)
    intr = frame.intrinsics  # centre (11.5, 8.5)
    samples = sample_grid([frame, frame], camera_grid(intr, 5.0))
    assert list(samples) == ["P1", "P2", "P3", "P4", "P5", "P6", "P7", "P8", "P9"]
    assert samples["P1"].xyz_m[:2] == pytest.approx([16.5, 13.5]) and samples["P9"].xyz_m[:2] == pytest.approx(
        [6.5, 3.5])
    assert samples["P6"].xyz_m[:2] == pytest.approx([6.5, 8.5]) and samples["P8"].xyz_m[:2] == pytest.approx(
        [11.5, 3.5])
    assert all(s.n_valid == 2 * 9 for s in samples.values())  # default 3x3 window, two frames pooled
    assert all(s.n_valid == 2 * 25 for s in sample_grid([frame, frame], camera_grid(intr, 5.0), 5).values())
    with pytest.raises(CalibrationError, match=r"leaves the 24x18 image"):
        sample_grid([frame], camera_grid(intr, 8.5))  # the grid fits, a 3x3 window around P1 does not


def ramp_frame(width: int = 12, height: int = 9) -> Frame:
    """Distance a + b*u + c*v and XYZ (u, v, distance): bilinear sampling reproduces it exactly."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    d = (1.0 + 0.01 * u + 0.002 * v).astype(np.float32)
    xyz = np.stack([u, v, d], axis=2).astype(np.float32)
    intr = Intrinsics(width=width, height=height, fx=10.0, fy=10.0, cx=(width - 1) / 2, cy=(height - 1) / 2)
    return Frame(d, xyz, np.ones_like(d), np.ones(d.shape, bool), intr, 0.0, 0)


@pytest.mark.parametrize("window", [1, 3, 5])
def test_a_window_may_touch_each_image_edge_but_not_pass_it(window: int) -> None:
    frame = ramp_frame()
    half = window // 2
    w, h = 12, 9
    edges = [(half, 4.0), (w - 1 - half, 4.0), (5.0, half), (5.0, h - 1 - half)]
    for u, v in edges:
        s = sample_window([frame], u, v, window)
        assert s.n_valid == window * window
        # the median of a symmetric window on a ramp is its centre: exact, not extrapolated
        assert s.xyz_m[0] == pytest.approx(u, abs=1e-6) and s.xyz_m[1] == pytest.approx(v, abs=1e-6)
        assert s.distance_m == pytest.approx(1.0 + 0.01 * u + 0.002 * v, abs=1e-6)
    past = [(half - 1e-9, 4.0), (w - 1 - half + 1e-9, 4.0), (5.0, half - 1e-9), (5.0, h - 1 - half + 1e-9),
            (w - half, 4.0), (5.0, h - half)]
    for u, v in past:
        with pytest.raises(CalibrationError) as info:
            sample_window([frame], u, v, window)
        assert str(info.value) == (f"sample window at pixel ({u:.1f}, {v:.1f}) leaves the 12x9 image; "
                                   "use a smaller perimeter")


def test_the_edge_pixel_itself_is_sampled_not_its_neighbour() -> None:
    frame = ramp_frame()
    # the bottom-right pixel centre, and a sub-pixel point in the last cell
    s = sample_window([frame], 11.0, 8.0, 1)
    assert s.pixel == (11, 8) and s.distance_m == pytest.approx(1.0 + 0.11 + 0.016, abs=1e-6)
    s = sample_window([frame], 10.75, 7.5, 1)
    assert s.pixel == (11, 8) and s.xyz_m == pytest.approx([10.75, 7.5, 1.0 + 0.1075 + 0.015], abs=1e-6)
    # a neighbour with zero weight may be invalid; one with weight may not
    frame.valid[8, 10] = False
    assert sample_window([frame], 11.0, 8.0, 1).n_valid == 1
    with pytest.raises(CalibrationError, match=r"only 0 valid samples \(need 1\) around pixel \(10\.5, 8\.0\)"):
        sample_window([frame], 10.5, 8.0, 1)


def test_several_locations_are_checked_and_named_individually() -> None:
    frame = ramp_frame()
    samples = sample_points([frame], np.array([[1.0, 1.0], [10.0, 7.0], [5.5, 4.25]]), 3)
    assert [s.pixel for s in samples] == [(1, 1), (10, 7), (6, 4)]
    assert [s.xyz_m[0] for s in samples] == pytest.approx([1.0, 10.0, 5.5], abs=1e-6)
    with pytest.raises(CalibrationError, match=r"at pixel \(10\.5, 7\.0\) leaves"):
        sample_points([frame], np.array([[1.0, 1.0], [10.5, 7.0], [0.5, 1.0]]), 3)
    frame.valid[1:4, 0:3] = False
    with pytest.raises(CalibrationError, match=r"only 0 valid samples \(need 1\) around pixel \(1\.0, 2\.0\) "
                                               r"in 2 frame\(s\)"):
        sample_points([frame, frame], np.array([[5.0, 5.0], [1.0, 2.0]]), 3)
    with pytest.raises(CalibrationError, match=r"only 6 valid samples \(need 7\) around pixel \(3\.0, 2\.0\)"):
        sample_window([frame], 3.0, 2.0, 3, min_valid=7)


@pytest.mark.parametrize(("bad", "edge"), [((5.0, 0.5), "top"), ((5.0, 7.5), "bottom"), ((0.5, 4.0), "left"),
                                           ((10.5, 4.0), "right")])
def test_the_window_that_leaves_is_the_one_named(bad: tuple[float, float], edge: str) -> None:
    frame = ramp_frame()
    uv = np.array([[5.0, 4.0], [6.0, 4.0], bad, [2.0, 2.0]])
    with pytest.raises(CalibrationError) as info:
        sample_points([frame], uv, 3)
    assert str(info.value) == f"sample window at pixel ({bad[0]:.1f}, {bad[1]:.1f}) leaves the 12x9 image; " \
                              "use a smaller perimeter", edge


def test_defaults_bad_arguments_and_the_location_short_of_samples() -> None:
    frame = ramp_frame()
    assert sample_window([frame], 5.0, 4.0).n_valid == 9  # a 3x3 window by default
    assert [s.n_valid for s in sample_points([frame], np.array([[5.0, 4.0]]))] == [9]
    with pytest.raises(CalibrationError, match=r"^no frames to sample$"):
        sample_window([], 5.0, 4.0)
    with pytest.raises(CalibrationError, match=r"^sample positions must be finite$"):
        sample_points([frame], np.array([[5.0, np.nan]]))
    # exactly min_valid positions is enough; the location named is the first with fewer
    frame.valid[0:3, 0:2] = False  # around (1, 1): 3 of 9 positions left; around (2, 5): 9
    samples = sample_points([frame], np.array([[2.0, 5.0], [2.0, 1.0]]), 3, min_valid=6)
    assert [s.n_valid for s in samples] == [9, 6]
    with pytest.raises(CalibrationError, match=r"only 3 valid samples \(need 6\) around pixel \(1\.0, 1\.0\)"):
        sample_points([frame], np.array([[2.0, 5.0], [2.0, 1.0], [1.0, 1.0]]), 3, min_valid=6)
