"""calibrate's error budget: per pose and for the consensus, the dominant term and the next step (ADR 0059)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cellcal.core.calibration.budget import budget_line, budget_table, error_budget
from cellcal.core.calibration.report import format_full_frame, summarize_poses
from cellcal.core.methods.fullframe import fit_full_frame
from cellcal.devices.arm_model import ArmModel
from cellcal.devices.pose import Pose
from tests.support.systematic_frames import stereo_frame, stereo_model, truth_plane


@pytest.fixture(scope="module")
def poses() -> list[dict]:
    out = []
    for i, (tx, ty) in enumerate([(5.0, 0.0), (-5.0, 3.0)]):
        res = fit_full_frame(stereo_frame(truth_plane(0.7, tx, ty), None, stereo_model(), np.random.default_rng(i)))
        cam = Pose(translation=[0.4, 0.1 * i, 0.7])
        out.append({"index": i, "camera_pose": cam.to_dict(), "measurements": [], "full_frame": res.to_dict()})
    return out


def test_a_depth_scale_dominates_a_stereo_camera_on_an_accurate_arm(poses: list[dict]) -> None:
    b = error_budget(poses, ArmModel(accuracy_m=0.0002, accuracy_rad=0.0002))
    assert b is not None and len(b["poses"]) == 2
    cons = b["consensus"]
    assert abs(cons["depth_scale_1pct"]["height_m"]) == pytest.approx(0.007, rel=0.05)   # 1 % of 0.7 m
    assert abs(cons["depth_offset_1mm"]["height_m"]) == pytest.approx(0.001, rel=0.1)
    assert cons["dominant"]["height"] == "depth_scale_1pct" and cons["next"] == "run cellcal depthcal"
    line = budget_line(b)
    assert line.startswith("error budget: depth scale dominates the height") and line.endswith("run cellcal depthcal")
    assert len(budget_table(b)) == 4


def test_an_inaccurate_arm_dominates(poses: list[dict]) -> None:
    b = error_budget(poses, ArmModel(accuracy_m=0.02, accuracy_rad=0.01))
    assert b is not None and b["consensus"]["dominant"] == {"tilt": "arm_accuracy", "height": "arm_accuracy"}
    assert b["consensus"]["arm_accuracy"]["tilt_rad"] == 0.01
    assert b["consensus"]["arm_accuracy"]["height_m"] == pytest.approx(math.hypot(0.02, 0.01 * 0.7), rel=0.01)
    assert "arm" in budget_line(b)


def test_the_summary_and_the_terminal_carry_it(poses: list[dict]) -> None:
    summary = summarize_poses(poses)
    assert summary["error_budget"]["arm_model"]["source"] == "unstated"
    text = format_full_frame({"poses": poses, "summary": summary})
    assert "error budget:" in text
    assert error_budget([{"index": 0, "camera_pose": Pose().to_dict()}]) is None
