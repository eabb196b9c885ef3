"""calibrate's error budget: per pose and for the consensus, judged at the allowance, the next step (ADR 0059)."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest

from cellcal.core.calibration.budget import (
    budget_line,
    budget_table,
    error_budget,
    handeye_budget_line,
    pose_budget_line,
)
from cellcal.core.calibration.report import format_full_frame, summarize_poses
from cellcal.core.methods.fullframe import fit_full_frame
from cellcal.devices.arm_model import ArmModel
from cellcal.devices.pose import Pose
from tests.support.systematic_frames import stereo_frame, stereo_model, tof_frame, tof_model, truth_plane

ACCURATE = ArmModel(accuracy_m=0.0002, accuracy_rad=0.0002)


def _poses(frame, model) -> list[dict]:  # type: ignore[no-untyped-def]
    out = []
    for i, (tx, ty) in enumerate([(5.0, 0.0), (-5.0, 3.0)]):
        res = fit_full_frame(frame(truth_plane(0.7, tx, ty), None, model, np.random.default_rng(i)))
        cam = Pose(translation=[0.4, 0.1 * i, 0.7])
        out.append({"index": i, "camera_pose": cam.to_dict(), "measurements": [], "full_frame": res.to_dict()})
    return out


@pytest.fixture(scope="module")
def poses() -> list[dict]:
    return _poses(stereo_frame, stereo_model())


@pytest.fixture(scope="module")
def tof_poses() -> list[dict]:
    return _poses(tof_frame, tof_model())


def test_a_depth_scale_dominates_a_stereo_camera_on_an_accurate_arm(poses: list[dict]) -> None:
    b = error_budget(poses, ACCURATE)
    assert b is not None and len(b["poses"]) == 2
    cons = b["consensus"]
    assert abs(cons["depth_scale_1pct"]["height_m"]) == pytest.approx(0.007, rel=0.05)   # 1 % of 0.7 m
    assert abs(cons["depth_offset_1mm"]["height_m"]) == pytest.approx(0.001, rel=0.1)
    at = cons["at_allowance"]
    assert at["depth_scale"]["stated"] == "1 %" and at["depth_offset"]["stated"] == "0.1 px"
    assert at["depth_scale"]["height_m"] == pytest.approx(abs(cons["depth_scale_1pct"]["height_m"]), rel=0.02)
    assert cons["judged"] == "allowance"
    assert cons["dominant"]["height"] == "depth_scale" and cons["next"] == "run cellcal depthcal"
    line = budget_line(b)
    assert line.startswith("error budget, height: depth scale dominates (1 % scale: 7 mm;")
    assert f"per 1 % scale {abs(cons['depth_scale_1pct']['height_m']) * 1000:.3g} mm" in line
    assert "; tilt: depth field dominates (0.5 px field: " in line and line.endswith("run cellcal depthcal")
    table = budget_table(b)
    assert table[1][0] == "depth scale *" and len(table) == 5


def test_a_tof_camera_is_judged_at_its_allowance_not_at_1_percent(tof_poses: list[dict]) -> None:
    """The issue's case: per unit the scale is 7x the offset, at 0.2 % and 5 mm the offset is 4x the scale."""
    b = error_budget(tof_poses, ACCURATE)
    assert b is not None
    cons = b["consensus"]
    per_scale, per_offset = abs(cons["depth_scale_1pct"]["height_m"]), abs(cons["depth_offset_1mm"]["height_m"])
    assert per_scale > 5 * per_offset
    at = cons["at_allowance"]
    assert at["depth_scale"]["height_m"] == pytest.approx(0.2 * per_scale, rel=0.01)        # 0.2 % of 1 %
    assert at["depth_offset"]["height_m"] == pytest.approx(5.0 * per_offset, rel=0.01)      # 5 mm of 1 mm
    assert cons["dominant"]["height"] == "depth_offset" and cons["next"] == "run cellcal depthcal"
    assert all(r["dominant"]["height"] == "depth_offset" for r in b["poses"])
    line = budget_line(b)
    assert line.startswith(f"error budget, height: depth offset dominates (5 mm offset: "
                           f"{at['depth_offset']['height_m'] * 1000:.2g} mm; 0.2 % scale: "
                           f"{at['depth_scale']['height_m'] * 1000:.2g} mm;")
    assert f"per 1 % scale {per_scale * 1000:.3g} mm" in line


def test_an_inaccurate_arm_dominates(poses: list[dict]) -> None:
    b = error_budget(poses, ArmModel(accuracy_m=0.02, accuracy_rad=0.01))
    # the tilt: 0.57 deg of the arm against 1.3 deg of a 0.5 px field on this 320 px camera
    assert b is not None and b["consensus"]["dominant"] == {"tilt": "depth_field", "height": "arm_accuracy"}
    assert b["consensus"]["arm_accuracy"]["tilt_rad"] == 0.01
    assert b["consensus"]["arm_accuracy"]["height_m"] == pytest.approx(math.hypot(0.02, 0.01 * 0.7), rel=0.01)
    assert b["consensus"]["next"].startswith("calibrate the arm's kinematics")
    assert "arm accuracy dominates (arm 21 mm;" in budget_line(b)


def test_an_ideal_camera_leaves_the_arm_and_without_an_allowance_the_sensitivities_judge() -> None:
    ideal = _poses(stereo_frame, stereo_model(zero=True))
    b = error_budget(ideal, ACCURATE)
    assert b is not None and b["consensus"]["judged"] == "allowance"
    assert b["consensus"]["dominant"]["height"] == "arm_accuracy"
    assert b["consensus"]["at_allowance"]["depth_scale"]["height_m"] == 0.0
    exact = error_budget(ideal, ArmModel(accuracy_m=0.0, accuracy_rad=0.0))
    assert exact is not None and exact["consensus"]["judged"] == "per unit"
    assert exact["consensus"]["dominant"]["height"] == "depth_scale"
    old = copy.deepcopy(ideal)                                     # a document from before the allowance
    for p in old:
        del p["full_frame"]["error_budget"]["allowance"]
    legacy = error_budget(old, ACCURATE)
    assert legacy is not None and legacy["consensus"]["at_allowance"] is None
    assert legacy["consensus"]["judged"] == "per unit" and legacy["consensus"]["dominant"]["height"] == "depth_scale"
    assert "dominates per unit" in budget_line(legacy) and "states no allowance" in budget_line(legacy)
    assert pose_budget_line(legacy, 0) == ""


def test_a_field_as_one_worst_shape_or_as_independent_shapes(poses: list[dict]) -> None:
    """``field`` (one shape) and ``field:<shape>`` (independent shapes): the latter's root sum of squares."""
    one = copy.deepcopy(poses)
    split = copy.deepcopy(poses)
    for p1, p2 in zip(one, split, strict=True):
        for p in (p1, p2):
            sh = p["full_frame"]["error_budget"]["allowance_shifts"]
            for k in [k for k in sh if k.startswith("field")]:
                del sh[k]
        base = {"tilt_rad": 0.003, "height_m": 0.0004, "offset_m": 0.0004, "normal_cam": [0.0, 0.003, 0.0]}
        p1["full_frame"]["error_budget"]["allowance_shifts"]["field"] = base
        p2["full_frame"]["error_budget"]["allowance_shifts"]["field:u"] = base
        p2["full_frame"]["error_budget"]["allowance_shifts"]["field:v"] = {
            **base, "height_m": -0.0003, "normal_cam": [0.003, 0.0, 0.0]}
    b1, b2 = error_budget(one, ACCURATE), error_budget(split, ACCURATE)
    assert b1 is not None and b2 is not None
    assert b1["poses"][0]["at_allowance"]["depth_field"]["height_m"] == pytest.approx(0.0004)
    assert b2["poses"][0]["at_allowance"]["depth_field"]["height_m"] == pytest.approx(0.0005)
    assert b2["poses"][0]["at_allowance"]["depth_field"]["tilt_rad"] == pytest.approx(0.003 * math.sqrt(2))
    assert b2["consensus"]["at_allowance"]["depth_field"]["tilt_rad"] == pytest.approx(0.003 * math.sqrt(2), rel=1e-6)


def test_a_pose_line_only_when_it_says_something_new(tof_poses: list[dict]) -> None:
    b = error_budget(tof_poses, ACCURATE)
    assert b is not None and pose_budget_line(b, 0) == "" and pose_budget_line(b, 1) == ""
    odd = copy.deepcopy(b)
    odd["poses"][1]["dominant"]["height"] = "arm_accuracy"
    line = pose_budget_line(odd, 1)
    assert line.startswith("error budget, height: arm accuracy dominates (arm ") and "tilt" not in line
    assert pose_budget_line(odd, 0) == "" and pose_budget_line(odd, 7) == ""


def test_the_summary_and_the_terminal_carry_it(poses: list[dict]) -> None:
    summary = summarize_poses(poses)
    assert summary["error_budget"]["arm_model"]["source"] == "unstated"
    text = format_full_frame({"poses": poses, "summary": summary})
    assert "error budget, height:" in text
    assert error_budget([{"index": 0, "camera_pose": Pose().to_dict()}]) is None


def test_the_handeye_line() -> None:
    assert handeye_budget_line({"mount": {}}) == ""
    doc = {"error_budget": {
        "terms": {"depth_scale_1pct": {"tx_m": 0.001, "ty_m": -0.002, "tz_m": 0.006, "roll_rad": 0.001,
                                       "pitch_rad": 0.0, "yaw_rad": 0.0, "plane_offset_m": 0.005},
                  "depth_offset_1mm": {"tx_m": 0.0, "ty_m": 0.0, "tz_m": 0.001, "roll_rad": 0.0,
                                       "pitch_rad": 0.0, "yaw_rad": 0.0, "plane_offset_m": 0.001},
                  "arm_accuracy": {"tx_m": 0.0005, "ty_m": 0.0005, "tz_m": 0.0005, "roll_rad": 0.002,
                                   "pitch_rad": 0.002, "yaw_rad": 0.002, "plane_offset_m": 0.0005}},
        "dominant": "depth_scale_1pct", "next": "run cellcal depthcal"}}
    assert handeye_budget_line(doc) == (
        "error budget of the mount: depth scale (1 %) dominates (depth scale (1 %) 6 mm, 0.057 deg; "
        "depth offset (1 mm) 1 mm, 0 deg; arm accuracy 0.5 mm, 0.11 deg): run cellcal depthcal")


def test_cellcal_handeye_prints_the_line_when_the_result_has_a_budget(monkeypatch: pytest.MonkeyPatch,
                                                                        capsys: pytest.CaptureFixture[str]) -> None:
    import argparse

    from cellcal.core.cli import handeye
    from cellcal.core.handeye import result

    monkeypatch.setattr(result, "format_report", lambda doc: "mount: ...")
    doc = {"error_budget": {"terms": {"arm_accuracy": {"tx_m": 0.0005, "roll_rad": 0.002}},
                            "dominant": "arm_accuracy", "next": "calibrate the arm"}}
    handeye._print_result(argparse.Namespace(quiet=False, out="out"), doc)
    assert capsys.readouterr().out.splitlines()[:2] == [
        "mount: ...", "error budget of the mount: arm accuracy dominates (arm accuracy 0.5 mm, 0.11 deg): "
                      "calibrate the arm"]
    handeye._print_result(argparse.Namespace(quiet=False, out="out"), {})
    assert "error budget" not in capsys.readouterr().out
