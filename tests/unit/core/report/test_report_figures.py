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
