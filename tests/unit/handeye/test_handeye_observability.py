"""The observability report: plans that hide each part of the mount in turn, named in words."""

from __future__ import annotations

import math

import numpy as np
import pytest
from handeye_views import NOMINAL_MOUNT, TABLE, plane_views
from repo_paths import REPO_ROOT

from cellcal.core.calibration.config import load_config, parse_config, plan_flange_poses
from cellcal.core.handeye import Observability, auto_plan, estimate_mount, observability, view_pose
from cellcal.devices.errors import CalibrationQualityError
from cellcal.devices.pose import Pose

TARGET = np.array([0.3, 0.0, 0.0])


def views(inclinations: list[float], rolls: list[float]) -> list[Pose]:
    """Flange poses viewing the target at 0.45 m at each inclination x roll about the tool axis (deg)."""
    return [view_pose(TARGET, 0.45, math.radians(i), math.radians(r), NOMINAL_MOUNT)
            for i in inclinations for r in rolls]


def seen(flanges: list[Pose], given: tuple[str, ...] = ()) -> Observability:
    return observability(plane_views(flanges, None), NOMINAL_MOUNT, TABLE, given=given)


def test_the_automatic_plan_sees_every_parameter() -> None:
    report = seen(auto_plan(load_config(REPO_ROOT / "configs" / "sim_handeye.toml")))
    assert report.observable and report.rank == 9 and not report.unseen
    assert 1 < report.condition < 1e3 and len(report.singular_values) == 9


def test_one_orientation_hides_rotation_height_and_sideways_translation() -> None:
    # the paper's plan: three heights along the optical axis, one flange orientation
    report = seen(plan_flange_poses(load_config(None)))
    assert report.rank == 4 and report.n_parameters == 9
    words = [d.what for d in report.unseen]
    assert any(w.startswith("mount rotation") for w in words)
    assert any("vs the plane's height" in w for w in words)
    assert any(w.startswith("mount translation across") and "parallel to the plane" in w for w in words)


def test_turning_about_the_plane_normal_hides_the_rotation_about_it() -> None:
    # azimuths about the normal through the target leave the normal fixed in the flange frame
    doc = {"camera": {"backend": "sim"}, "arm": {"backend": "sim"}, "mount": {"translation_m": [0, 0.04, 0.06],
           "rpy_deg": [0, 0, 90]}, "reference": {}, "plan": {"heights_m": [0.46, 0.55], "inclination_deg": 75.0,
                                                             "azimuths_deg": [0.0, 90.0, 180.0, 270.0]}}
    report = seen(plan_flange_poses(parse_config(doc, "azimuths.toml")))
    rotation = [d for d in report.unseen if d.part == "rotation"]
    assert len(rotation) == 1 and "(= the plane normal)" in rotation[0].what
    u = plane_views(plan_flange_poses(parse_config(doc, "azimuths.toml")), None)[0].flange.rotation.inv().apply(
        [0.0, 0.0, 1.0])
    assert abs(abs(np.asarray(rotation[0].axis) @ u) - 1.0) < 1e-6  # the axis is the normal seen from the flange


def test_rolls_at_one_inclination_confound_mount_height_with_plane_height() -> None:
    flanges = views([70.0], [0.0, 90.0, 180.0, 270.0])
    report = seen(flanges)
    assert report.rank == 8
    (only,) = report.unseen
    assert only.part == "translation" and "vs the plane's height" in only.what and "flange z" in only.what
    assert "given" in only.fix and "plane_offset" in report.message()
    assert seen(flanges, given=("plane_offset",)).observable  # giving the plane height fixes it
    with pytest.raises(CalibrationQualityError, match=r"observability.*cannot see 1 of 9") as info:
        estimate_mount(plane_views(flanges, None), NOMINAL_MOUNT, TABLE)
    assert "\n" not in str(info.value) and len(str(info.value)) < 330


def test_inclinations_without_rolls_hide_a_rotation_and_the_translation_across_the_tilt_plane() -> None:
    # every pose pitches the tool about one axis (flange y): a mount turn about it is a plane tilt,
    # and a mount shift along it is parallel to the plane at every pose
    flanges = views([85.0, 70.0, 55.0], [0.0])
    report = seen(flanges)
    assert report.rank == 7
    words = [d.what for d in report.unseen]
    assert "mount rotation about flange y (traded with the plane's tilt)" in words
    assert seen(flanges, given=("mount_rot_y",)).unseen[0].what == \
        "mount translation along flange y (parallel to the plane)"
    u = np.stack([o.flange.rotation.inv().apply([0.0, 0.0, 1.0]) for o in plane_views(flanges, None)])
    assert np.max(np.abs(u[:, 1])) < 1e-9  # edge-on at every pose
    assert seen(flanges, given=("mount_rot_y", "mount_y")).observable


@pytest.mark.parametrize("given", [("mount_rot_x",), ("mount_x", "mount_y"), ("plane_tilt_a", "plane_offset")])
def test_each_given_parameter_leaves_the_estimate(given: tuple[str, ...]) -> None:
    report = seen(views([80.0, 65.0], [0.0, 90.0, 180.0, 270.0]), given)
    assert report.observable and report.n_parameters == 9 - len(given) == report.rank
