"""Tests of a user's cell code (table_probe.py) on the simulated cell of cell.toml, with injected faults.

Only the documented fixtures of cellcal's pytest plugin are used (docs/testing.md).
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from cellcal.devices import Camera3D, RobotArm
from cellcal.devices.errors import DeviceConnectionError, DeviceTimeoutError, VendorError
from cellcal.testing import CellFaults, SimCell
from table_probe import TableNotSeenError, lower_by, table_distance_m


def true_distance_m(cell: SimCell) -> float:
    """Where the camera's optical axis meets the table (z = 0), from the simulation's ground truth."""
    pose = cell.world.camera_pose()
    return float(-pose.translation[2] / pose.rotation_matrix[2, 2])


def accuracy_m(camera: Camera3D, distance_m: float) -> float:
    """What the camera promises for one reading at ``distance_m``: twice its stated systematic
    allowance (offset plus scale, 1-sigma each) and 1 mm of noise, metres."""
    scale, offset, _ = camera.capture(1.0).measurement.allowance  # ToF: relative, metres
    return 2.0 * (offset + scale * distance_m) + 0.001


def test_the_probe_measures_the_table_within_the_cameras_accuracy(
        cellcal_sim_cell: SimCell, cellcal_sim_camera: Camera3D, cellcal_sim_arm: RobotArm) -> None:
    # the simulated camera errs as a real one does (by default a 3 mm range offset, 0.1 % scale):
    # a reading is as good as the camera's stated accuracy, a difference of two readings much better
    before = table_distance_m(cellcal_sim_camera)
    assert abs(before - true_distance_m(cellcal_sim_cell)) < accuracy_m(cellcal_sim_camera, before)
    lower_by(cellcal_sim_arm, 0.05)
    after = table_distance_m(cellcal_sim_camera)
    assert abs(after - true_distance_m(cellcal_sim_cell)) < accuracy_m(cellcal_sim_camera, after)
    assert before - after == pytest.approx(0.05, abs=0.003)  # the camera looks straight down here


@pytest.mark.parametrize("cellcal_sim_tables", [{"sim": {"systematic": {"enabled": False}}}])
def test_an_ideal_camera_gives_the_table_to_3_mm(cellcal_sim_cell: SimCell, cellcal_sim_camera: Camera3D) -> None:
    # the same probe on a camera without systematic error: what is left is the noise
    assert abs(table_distance_m(cellcal_sim_camera) - true_distance_m(cellcal_sim_cell)) < 0.003


def test_a_lost_frame_is_tried_again(cellcal_sim_cell: SimCell, cellcal_sim_camera: Camera3D,
                                     cellcal_faults: CellFaults) -> None:
    cellcal_faults.camera_timeout(capture=1)
    distance = table_distance_m(cellcal_sim_camera, attempts=2)
    assert cellcal_faults.fired["camera_timeout"] == 1
    assert abs(distance - true_distance_m(cellcal_sim_cell)) < accuracy_m(cellcal_sim_camera, distance)


def test_a_camera_that_keeps_timing_out_is_reported(cellcal_sim_camera: Camera3D, cellcal_faults: CellFaults) -> None:
    cellcal_faults.camera_timeout(capture=1, count=2)
    with pytest.raises(DeviceTimeoutError):
        table_distance_m(cellcal_sim_camera, attempts=2)


def test_a_lost_camera_is_not_retried(cellcal_sim_camera: Camera3D, cellcal_faults: CellFaults) -> None:
    cellcal_faults.camera_disconnect(capture=1)
    with pytest.raises(DeviceConnectionError, match="connection lost"):
        table_distance_m(cellcal_sim_camera, attempts=3)
    assert cellcal_faults.fired["camera_disconnect"] == 1


def test_an_empty_frame_is_refused_by_name(cellcal_sim_camera: Camera3D, cellcal_faults: CellFaults) -> None:
    cellcal_faults.blank_frame(capture=1)
    with pytest.raises(TableNotSeenError, match="only 0% of the central"):
        table_distance_m(cellcal_sim_camera)
    assert table_distance_m(cellcal_sim_camera) > 0.3  # the next frame sees the table again


def test_a_blocked_arm_times_out_at_the_timeout_given(cellcal_sim_arm: RobotArm, cellcal_faults: CellFaults) -> None:
    cellcal_faults.arm_stall(move=1)
    start = time.monotonic()
    with pytest.raises(DeviceTimeoutError):
        lower_by(cellcal_sim_arm, 0.05, timeout_s=0.5)
    assert 0.5 <= time.monotonic() - start < 5.0


def test_a_protective_stop_reaches_the_caller(cellcal_sim_arm: RobotArm, cellcal_faults: CellFaults) -> None:
    start = cellcal_sim_arm.get_pose()
    cellcal_faults.arm_error(code=31, move=1)
    with pytest.raises(VendorError, match="31"):
        lower_by(cellcal_sim_arm, 0.05)
    assert cellcal_sim_arm.get_pose().distance_to(start) < 0.05  # stopped short of the target


def test_the_cell_calibrates_with_the_true_angle_inside_its_interval(cellcal_sim_cell: SimCell) -> None:
    result = cellcal_sim_cell.calibrator().run()
    rows = [row for pose in result["poses"] for row in pose["measurements"] if row["method"] == "full_frame"]
    assert len(rows) == 3
    # the 95 % interval carries the camera's systematic allowance as well as the noise
    intervals = [pose["full_frame"]["angle_ci_deg"] for pose in result["poses"]]
    assert all(lo < row["expected_angle_deg"] < hi for row, (lo, hi) in zip(rows, intervals, strict=True)), intervals
    errors = np.array([row["angle_deg"] - row["expected_angle_deg"] for row in rows])
    assert np.all(np.abs(errors) < 0.5), errors
