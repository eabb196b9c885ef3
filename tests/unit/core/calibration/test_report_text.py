"""The calibrate summary speaks mm and deg, and states a base-frame plane by one sign convention.

A plane is ``n·x + offset_m = 0`` (core/geometry/planes.py); the summary prints its height above the base
origin along ``n`` (``-offset_m``, in mm) and says once what "above" means (ADR 0042).
"""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from cellcal.core.calibration.report import ABOVE_NOTE, format_full_frame, format_table, plane_height_mm, plane_summary
from cellcal.core.geometry.planes import Plane
from cellcal.devices.pose import Pose

TABLE_Z_M = 0.000078  # the table 0.078 mm above the base origin (the user's report: +0.078 beside -0.078)


@pytest.mark.parametrize(("point_z_m", "normal", "expected_mm"),
                         [(0.005, (0, 0, 1), 5.0), (0.005, (0, 0, -1), -5.0), (-0.002, (0, 0, 1), -2.0)])
def test_the_height_is_where_the_plane_crosses_its_normal_through_the_origin(
        point_z_m: float, normal: tuple[int, int, int], expected_mm: float) -> None:
    plane = Plane.from_point_normal([0.1, -0.2, point_z_m], normal)
    height_mm = plane_height_mm(plane.to_dict())
    assert height_mm == pytest.approx(expected_mm, abs=1e-9)
    assert float(plane.signed_distance(height_mm / 1000.0 * plane.normal)) == pytest.approx(0.0, abs=1e-12)


def _pose_record(camera_x_m: float) -> dict[str, object]:
    """A pose record whose camera looks straight down from 0.5 m at the table z = TABLE_Z_M."""
    camera = Pose.from_xyz_rpy([camera_x_m, 0.0, 0.5], [math.pi, 0.0, 0.0])
    table = Plane.from_point_normal([0.0, 0.0, TABLE_Z_M], [0.0, 0.0, 1.0])
    in_camera = table.transformed(camera.inv()).oriented_toward_origin()
    return {"index": 0, "camera_pose": camera.to_dict(), "measurements": [],
            "full_frame": {"plane_cam": {**in_camera.to_dict(), "offset_sigma_m": 1e-5},
                           "normal_covariance": (np.eye(3) * 1e-10).tolist()}}


def test_the_consensus_plane_and_the_reference_check_agree_in_sign_and_unit() -> None:
    cons = plane_summary([_pose_record(0.25), _pose_record(0.35)], reference=Plane([0.0, 0.0, 1.0], 0.0))
    assert cons is not None and cons["consensus_plane_base"]["offset_m"] == pytest.approx(-TABLE_Z_M, abs=1e-12)
    lines = format_full_frame({"summary": {"plane_consistency": cons}}).splitlines()

    assert lines[0].startswith("plane in the base frame (full_frame, 2 poses): normal [")
    assert lines[0].endswith("+1.00000], +0.078 mm above the base origin")
    reference = next(line for line in lines if "vs [reference] plane" in line)
    found = re.fullmatch(r"  vs \[reference\] plane: 0\.0000 deg apart, \+0\.078 mm above it at "
                         r"\[\+(\d+\.\d{3}), [+-]0\.000, \+0\.078\] mm", reference)
    assert found is not None, reference
    assert 250.0 <= float(found[1]) <= 350.0  # between the two cameras, in mm
    assert lines[-1] == ABOVE_NOTE
    assert not any(re.search(r"\d m\b|offset", line) for line in lines[:-1])  # no metres, no offset


def test_each_pose_prints_its_height_and_its_base_frame_plane_in_mm_with_the_note_once() -> None:
    ff = {"tilt_x_deg": 10.0, "tilt_x_ci_deg": [9.99, 10.01], "tilt_y_deg": 0.0, "tilt_y_ci_deg": [-0.01, 0.01],
          "height_m": 0.46, "height_ci_m": [0.45998, 0.46003], "gates": {},
          "plane_base": Plane.from_point_normal([0.0, 0.0, -0.000124], [0.0, 0.0, 1.0]).to_dict()}
    poses = [{"index": i, "full_frame": ff, "expected": {"tilt_x_deg": 10.0, "tilt_y_deg": 0.0, "height_m": 0.45998}}
             for i in range(2)]
    text = format_full_frame({"poses": poses})
    assert ("  pose 1: tilt_x 10.0000 [9.9900, 10.0100] deg, tilt_y 0.0000 [-0.0100, 0.0100] deg, "
            "height 460.00 [459.98, 460.03] mm (expected tilt_x 10.0000, tilt_y 0.0000 deg, height 459.98 mm)") in text
    plane_line = "plane in base frame: normal [+0.00000, +0.00000, +1.00000], -0.124 mm above the base origin"
    assert text.count(plane_line) == 2
    assert text.count(ABOVE_NOTE) == 1 and text.endswith(ABOVE_NOTE)


def test_the_table_gives_heights_in_mm() -> None:
    row = {"pose_index": 0, "height_m": 0.45874714, "perimeter_px": 20, "method": "law_of_cosines",
           "angle_deg": 78.2686, "expected_angle_deg": 80.0, "error_pct": 2.164, "tilt_x_deg": 11.731,
           "tilt_y_deg": 2.762, "residual_rms_m": None}
    header, _rule, line = format_table([row]).splitlines()
    assert header.split()[:2] == ["pose", "height_mm"]
    assert line.split() == ["1", "458.7", "20", "law_of_cosines", "78.269", "80.00", "2.16", "11.73", "2.76", "-"]
