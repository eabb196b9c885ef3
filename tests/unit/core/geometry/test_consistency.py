"""The plane in the base frame and its consistency across poses (a check of the hand-eye transform)."""

from __future__ import annotations

import copy
import math
import tomllib
from importlib import resources
from typing import Any

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cellcal.core.calibration.calibrator import Calibrator, build_devices
from cellcal.core.calibration.config import look_at_pose, parse_config
from cellcal.core.geometry.consistency import PosePlane, plane_consistency, plane_in_base
from cellcal.core.geometry.planes import Plane, fit_plane_tls
from cellcal.devices.errors import CalibrationError
from cellcal.devices.pose import Pose

SIM = tomllib.loads(resources.files("cellcal.configs").joinpath("sim.toml").read_text())
TRUE_MOUNT = Pose.from_xyz_rpy(SIM["mount"]["translation_m"], np.radians(SIM["mount"]["rpy_deg"]))


def varied_camera_poses() -> list[Pose]:
    """Camera poses (base frame) looking at (0.3, 0, 0) from two heights and four azimuths."""
    target = np.array([0.3, 0.0, 0.0])
    out = []
    for h in (0.46, 0.6):
        for yaw_deg in (-40.0, -15.0, 15.0, 40.0):
            about_target = (Pose(translation=target) @ Pose(Rotation.from_euler("z", yaw_deg, degrees=True))
                            @ Pose(translation=-target))
            out.append(about_target @ look_at_pose(target, np.array([0.0, 0.0, 1.0]), h, math.radians(75.0), "x"))
    return out


def plan_document(config_mount: Pose, poses: list[Pose], seed: int = 7) -> dict[str, Any]:
    """sim.toml with flange poses (planned with the configured mount), the true mount in [sim], ideal devices."""
    doc = copy.deepcopy(SIM)
    flange = [c @ config_mount.inv() for c in poses]
    doc["plan"]["poses"] = [{"xyz_m": f.translation.tolist(),
                             "rpy_deg": np.degrees(f.rotation.as_euler("xyz")).tolist()} for f in flange]
    doc["mount"] = {"translation_m": config_mount.translation.tolist(),
                    "rpy_deg": np.degrees(config_mount.rotation.as_euler("xyz")).tolist()}
    # an ideal camera on an exact arm: the figures below are the noise's (the camera's systematic error and the
    # arm's accuracy in the test are tests/unit/core/geometry/test_consistency_systematic.py's)
    doc["sim"] = {**SIM["sim"], "mount": dict(SIM["mount"]), "systematic": {"enabled": False},
                  "arm_errors": {"enabled": False}}
    doc["cell"] = {**SIM["cell"], "seed": seed}
    return doc


def measure(doc: dict[str, Any]) -> list[PosePlane]:
    """Drive the sim through the plan; per pose a TLS plane over the whole frame, mapped to the base frame."""
    config = parse_config(doc, "<test>")
    camera, arm = build_devices(config)
    out = []
    with arm, camera:
        for target in [p.pose() for p in config.plan.poses]:
            arm.move_linear(target, speed=0.3, acceleration=1.5, timeout=10.0)
            frame = camera.capture(2.0)
            reported = arm.get_pose()
            fit = fit_plane_tls(frame.xyz[frame.valid].astype(np.float64))
            base = plane_in_base(fit.plane, reported, config.mount.pose())
            pp = PosePlane.from_camera(fit.plane, reported @ config.mount.pose(),
                                       normal_sigma_rad=fit.normal_sigma_rad, offset_sigma_m=fit.offset_sigma_m)
            assert np.allclose(pp.plane_base.normal, base.normal) and pp.plane_base.offset_m == pytest.approx(
                base.offset_m)
            out.append(pp)
    return out


def test_true_mount_gives_noise_level_spread_and_a_wrong_mount_does_not() -> None:
    poses = varied_camera_poses()
    good = plane_consistency(measure(plan_document(TRUE_MOUNT, poses)))
    # the table is z = 0 in the base frame
    assert good.verdict == "consistent", good.interpretation
    assert math.degrees(math.acos(good.consensus.normal[2])) < 0.02
    assert abs(good.consensus.signed_distance(good.reference_point_m)) < 1e-12
    assert abs(good.reference_point_m[2]) < 0.5e-3
    assert math.degrees(good.normal_spread_rad) < 0.03  # measured ~0.01 deg
    assert good.height_spread_m < 0.3e-3  # measured ~0.1 mm
    assert good.expected_normal_rms_rad is not None and good.normal_rms_rad < 4 * good.expected_normal_rms_rad
    assert math.degrees(good.orientation_span_rad or 0.0) > 60.0

    # a 1 deg roll and 3 mm error in the configured hand-eye transform
    wrong = TRUE_MOUNT @ Pose.from_xyz_rpy([0.003, 0.0, 0.0], [math.radians(1.0), 0.0, 0.0])
    bad = plane_consistency(measure(plan_document(wrong, poses)))
    assert bad.verdict == "inconsistent"
    assert "hand-eye transform" in bad.interpretation
    assert bad.normal_spread_rad > 20 * good.normal_spread_rad
    assert math.degrees(bad.normal_spread_rad) > 0.5
    assert bad.height_spread_m > 5 * good.height_spread_m  # measured 6.9x (7-15x over seeds 7-12)


def test_one_orientation_cannot_see_a_mount_error() -> None:
    """The paper's plan (three heights, one orientation) is blind to a mount rotation error."""
    target = np.array([0.3, 0.0, 0.0])
    poses = [look_at_pose(target, np.array([0.0, 0.0, 1.0]), h, math.radians(80.0), "x") for h in (0.46, 0.59, 0.61)]
    wrong = TRUE_MOUNT @ Pose.from_xyz_rpy([0.0, 0.0, 0.0], [math.radians(1.0), 0.0, 0.0])
    result = plane_consistency(measure(plan_document(wrong, poses)))
    assert result.verdict == "blind" and "same camera orientation" in result.interpretation
    # the error is there (the consensus is tilted by ~1 deg) but it is not a spread
    assert math.degrees(math.acos(result.consensus.normal[2])) == pytest.approx(1.0, abs=0.05)
    assert math.degrees(result.normal_spread_rad) < 0.05


def test_consensus_and_spread_figures_on_constructed_planes() -> None:
    z = Plane.from_point_normal([0.0, 0.0, 0.0], [0.0, 0.0, 1.0])
    tilt = math.radians(0.2)
    tilted = Plane.from_point_normal([0.3, 0.0, 0.002], [math.sin(tilt), 0.0, math.cos(tilt)])
    poses = [PosePlane(z, np.array([0.3, 0.0, 0.0])), PosePlane(tilted, np.array([0.3, 0.0, 0.002]))]
    r = plane_consistency(poses)
    # equal weights: the consensus normal bisects, each deviates by half the angle
    assert [math.degrees(v) for v in r.normal_deviation_rad] == pytest.approx([0.1, 0.1], abs=1e-9)
    assert r.height_deviation_m == pytest.approx((-0.001, 0.001), abs=1e-8)  # x cos(0.1 deg)
    assert r.height_spread_m == pytest.approx(0.002, abs=1e-8)
    assert r.reference_point_m == pytest.approx([0.3, 0.0, 0.001], abs=1e-8)
    assert r.verdict == "inconsistent" and r.orientation_span_rad is None
    d = r.to_dict()
    assert d["normal_spread_deg"] == pytest.approx(0.1) and d["n_poses"] == 2
    # inverse-variance weights pull the consensus to the precise pose
    precise = [PosePlane(z, np.array([0.3, 0.0, 0.0]), normal_sigma_rad=1e-5, offset_sigma_m=1e-5),
               PosePlane(tilted, np.array([0.3, 0.0, 0.002]), normal_sigma_rad=1e-3, offset_sigma_m=1e-3)]
    w = plane_consistency(precise)
    assert math.degrees(w.normal_deviation_rad[0]) < 1e-3 and w.reference_point_m[2] == pytest.approx(0.0, abs=1e-6)
    # flipped normals are the same plane
    same = plane_consistency([PosePlane(z, np.zeros(3)), PosePlane(Plane(np.array([0.0, 0.0, -1.0]), 0.0),
                                                                   np.zeros(3))])
    assert same.normal_spread_rad == 0.0 and same.height_spread_m == 0.0
    assert plane_consistency(poses[:1]).verdict == "single pose"


def test_errors() -> None:
    with pytest.raises(CalibrationError, match="at least one pose"):
        plane_consistency([])
    z = Plane(np.array([0.0, 0.0, 1.0]), 0.0)
    wall = Plane(np.array([1.0, 0.0, 0.0]), 0.0)
    with pytest.raises(CalibrationError, match="not one plane"):
        plane_consistency([PosePlane(z, np.zeros(3)), PosePlane(wall, np.zeros(3))])
    with pytest.raises(CalibrationError, match="reference_point_m"):
        plane_consistency([PosePlane(z, np.zeros(3))], reference_point_m=[1.0, 2.0])


def test_the_calibrators_summary_flags_a_wrong_mount() -> None:
    """Through the whole calibrator (full_frame only): the document's verdict and figures."""
    poses = varied_camera_poses()
    figures = {}
    for name, mount in (("true", TRUE_MOUNT),
                        ("wrong", TRUE_MOUNT @ Pose.from_xyz_rpy([0.0, 0.0, 0.0], [0.0, math.radians(0.5), 0.0]))):
        doc = plan_document(mount, poses)
        doc["plan"]["methods"] = ["full_frame"]
        config = parse_config(doc, "<test>")
        camera, arm = build_devices(config)
        cons = Calibrator(config, camera, arm).run()["summary"]["plane_consistency"]
        assert cons["source_method"] == "full_frame" and cons["n_poses"] == len(poses)
        figures[name] = cons
    assert figures["true"]["verdict"] == "consistent"
    assert figures["wrong"]["verdict"] == "inconsistent"
    assert figures["wrong"]["normal_spread_deg"] > 20 * figures["true"]["normal_spread_deg"]
    assert figures["wrong"]["normal_spread_deg"] > 0.25
