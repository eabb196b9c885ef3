"""The report's pictures, decoded: size, content, the plane's colour where the plane is, failed gates marked."""

from __future__ import annotations

import itertools
from typing import Any

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")
pytest.importorskip("matplotlib")

from report_runs import decode, rgb, share_of_class_in_colour  # noqa: E402

from cellcal.core.report import figures  # noqa: E402
from cellcal.core.report.arrays import decode_array  # noqa: E402
from cellcal.core.report.capture import CLASS_INLIER, CLASS_OUTLIER  # noqa: E402


def assert_not_blank(image: np.ndarray) -> None:
    grey = image.mean(axis=2)
    assert grey.std() > 10 and np.count_nonzero(grey < 200) > 0.02 * grey.size


def test_pose_image_has_the_plane_colour_where_the_plane_is(passing: dict[str, Any]) -> None:
    for pose in passing["calibrate"]["poses"]:
        image = decode(figures.pose_image_figure(pose, "sim"))
        w_in, h_in = figures.IMAGE_FIGSIZE_IN
        assert image.shape[:2] == (round(h_in * figures.DPI), round(w_in * figures.DPI))
        assert_not_blank(image)
        classes = decode_array(pose["pictures"]["classes"]) & 3
        assert share_of_class_in_colour(image, classes, CLASS_INLIER, figures.CLASS_COLORS[CLASS_INLIER]) > 0.97


def test_a_refused_pose_shows_the_table_as_outliers_and_its_failed_gate(refused: dict[str, Any],
                                                                        passing: dict[str, Any]) -> None:
    [pose] = refused["calibrate"]["poses"]
    image = decode(figures.pose_image_figure(pose, "sim"))
    classes = decode_array(pose["pictures"]["classes"]) & 3
    assert share_of_class_in_colour(image, classes, CLASS_OUTLIER, figures.CLASS_COLORS[CLASS_OUTLIER]) > 0.97
    assert share_of_class_in_colour(image, classes, CLASS_INLIER, figures.CLASS_COLORS[CLASS_INLIER]) > 0.97
    failed_red = rgb(figures.FAILED)

    def red_pixels(png: bytes) -> int:
        return int(np.count_nonzero(np.all(np.abs(decode(png).astype(int) - failed_red) <= 3, axis=2)))

    assert red_pixels(figures.pose_fit_figure(pose, "sim")) > 200  # the failed gate's bar and its label
    assert red_pixels(figures.pose_fit_figure(passing["calibrate"]["poses"][0], "sim")) == 0


def _panel(image: np.ndarray, axes: tuple[float, float, float, float]) -> tuple[int, int, int, int]:
    """The pixel box (x0, y0, x1, y1) of a panel given in figure fractions."""
    left, bottom, width, height = axes
    h_img, w_img = image.shape[:2]
    return (int(left * w_img), int((1 - bottom - height) * h_img), int((left + width) * w_img),
            int((1 - bottom) * h_img))


def _at(image: np.ndarray, axes: tuple[float, float, float, float], mask: np.ndarray) -> np.ndarray:
    """The panel's drawn colours (N, 3) at the map pixels of ``mask`` (cell centres)."""
    x0, y0, x1, y1 = _panel(image, axes)
    rows, cols = np.nonzero(mask)
    hm, wm = mask.shape
    ys = np.floor(y0 + (rows + 0.5) / hm * (y1 - y0)).astype(int)
    xs = np.floor(x0 + (cols + 0.5) / wm * (x1 - x0)).astype(int)
    return image[ys, xs].astype(int)


def test_a_pose_refused_as_not_flat_shows_the_plate_in_the_residual_map(not_flat: dict[str, Any]) -> None:
    [pose] = not_flat["calibrate"]["poses"]
    gate = pose["full_frame"]["gates"]["flatness"]
    assert not gate["passed"] and gate["value"] > gate["threshold"] == pytest.approx(0.001)
    image = decode(figures.pose_image_figure(pose, "sim"))
    residual = decode_array(pose["pictures"]["residual_mm"]).astype(float)
    # the 8 mm plate stands toward the camera: its pixels are red (+), the table's pale (near zero)
    plate = np.nan_to_num(residual, nan=0.0) > 5.0
    table = np.abs(np.nan_to_num(residual, nan=99.0)) < 0.3
    assert plate.sum() > 200 and table.sum() > 2000
    plate_rgb = _at(image, figures.PANEL_AXES[2], plate).mean(axis=0)
    table_rgb = _at(image, figures.PANEL_AXES[2], table).mean(axis=0)
    assert plate_rgb[0] - plate_rgb[2] > 80, plate_rgb  # red: far above zero on the diverging map
    assert abs(table_rgb[0] - table_rgb[2]) < 40 and table_rgb.min() > 180, table_rgb  # pale
    # the panel's title says it is not flat, in the failed colour (above the panel)
    x0, y0, x1, _ = _panel(image, figures.PANEL_AXES[2])
    title = image[max(0, y0 - 60):y0, x0 - 40:x1 + 40].astype(int)
    reddish = (title[..., 0] > 120) & (title[..., 1] < 110) & (title[..., 2] < 120)  # anti-aliased text of FAILED
    assert np.count_nonzero(reddish) > 50


def test_a_pose_refused_for_coverage_marks_the_cells_without_plane(not_covered: dict[str, Any],
                                                                   passing: dict[str, Any]) -> None:
    [pose] = not_covered["calibrate"]["poses"]
    gate = pose["full_frame"]["gates"]["coverage"]
    cover = pose["pictures"]["coverage"]
    uncovered = np.asarray(cover["uncovered"], dtype=bool)
    # the gate's value is the share of covered cells the picture draws
    assert gate["value"] == pytest.approx(1.0 - uncovered.sum() / np.asarray(cover["counted"]).sum())
    assert 1 <= uncovered.sum() <= 4
    image = decode(figures.pose_image_figure(pose, "sim"))
    x0, y0, x1, y1 = _panel(image, figures.CLASS_AXES)
    red = np.all(np.abs(image.astype(int) - rgb(figures.FAILED)) <= 3, axis=2)
    h, w = pose["pictures"]["shape_px"]
    rows, cols = [*cover["row_edges_px"], h], [*cover["col_edges_px"], w]
    inside = np.zeros_like(red)
    for r, c in zip(*np.nonzero(uncovered), strict=True):  # the uncovered cells' boxes in the panel
        ya, yb = y0 + rows[r] / h * (y1 - y0), y0 + rows[r + 1] / h * (y1 - y0)
        xa, xb = x0 + cols[c] / w * (x1 - x0), x0 + cols[c + 1] / w * (x1 - x0)
        inside[max(0, int(ya) - 2):int(yb) + 3, max(0, int(xa) - 2):int(xb) + 3] = True
    panel = np.zeros_like(red)
    panel[y0:y1, x0:x1] = True
    assert np.count_nonzero(red & inside) > 100  # outlined and hatched in the failed colour ...
    assert np.count_nonzero(red & panel & ~inside) < 20  # ... and nowhere else in the panel
    # a passing pose has no such marks in its pixel panel
    ok = decode(figures.pose_image_figure(passing["calibrate"]["poses"][0], "sim"))[y0:y1, x0:x1]
    assert np.count_nonzero(np.all(np.abs(ok.astype(int) - rgb(figures.FAILED)) <= 3, axis=2)) == 0


def test_across_pose_pictures_are_drawn(passing: dict[str, Any]) -> None:
    poses = passing["calibrate"]["poses"]
    for png in (figures.poses_figure(poses, "sim"),
                figures.consistency_figure(passing["calibrate"]["result"]["summary"]["plane_consistency"], "sim")):
        assert_not_blank(decode(png))


def test_consensus_is_the_weighted_mean_with_its_interval() -> None:
    mean, half = figures.weighted_consensus([1.0, 3.0], [1.0, 1.0]) or (0.0, 0.0)
    assert mean == pytest.approx(2.0) and half == pytest.approx(1.959963984540054 / np.sqrt(2.0))
    assert figures.weighted_consensus([1.0], [float("nan")]) is None


def test_pixel_classes_differ_in_lightness_so_they_survive_greyscale() -> None:
    luma = sorted(float(rgb(c) @ np.array([0.299, 0.587, 0.114])) / 255 for c in figures.CLASS_COLORS.values())
    assert min(b - a for a, b in itertools.pairwise(luma)) > 0.1, luma
