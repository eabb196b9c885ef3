"""The automatic plan, the arm classes' reach, and the simulated xArm 5 refusing what a real one cannot do."""

from __future__ import annotations

import math
import tomllib

import numpy as np
import pytest
from repo_paths import REPO_ROOT

from cellcal.core.calibration.config import load_config, parse_config, plan_flange_poses
from cellcal.core.handeye import arm_reach, auto_plan, check_observability, check_plan, plan_poses
from cellcal.devices.errors import ConfigError, SafetyError, VendorError
from cellcal.devices.geometry.reach import orientation_violation, radial_flange_rotation, sideways_tilt_rad
from cellcal.devices.pose import Pose
from cellcal.sims.arm import SimArm, SimArmConfig

CONFIG = REPO_ROOT / "configs" / "sim_handeye.toml"


def document(**handeye: object) -> dict:
    doc = tomllib.loads(CONFIG.read_text())
    doc["handeye"] = {**doc["handeye"], **handeye}
    return doc


def test_auto_plan_views_the_target_at_every_inclination_and_roll_within_the_xarm5_reach() -> None:
    config = load_config(CONFIG)
    poses = auto_plan(config)
    assert len(poses) == 8 <= 12 and arm_reach(config) == "xarm5"
    mount = config.mount.pose()
    inclinations, rolls = [], []
    for flange in poses:
        assert sideways_tilt_rad(flange) < 1e-9  # the tool stays in the base's vertical plane
        camera = flange @ mount
        axis = camera.rotation.apply([0.0, 0.0, 1.0])
        hit = camera.translation + 0.45 * axis  # the optical axis meets the target at the planned distance
        np.testing.assert_allclose(hit, [0.3, 0.0, 0.0], atol=1e-9)
        inclinations.append(round(math.degrees(math.asin(-axis[2])), 6))
        rolls.append(flange.rotation.inv().apply([0.0, 0.0, 1.0]))  # the table normal in the flange frame
    assert sorted(set(inclinations)) == [65.0, 80.0]
    # the rolls turn the normal (seen from the flange) round the tool axis: four directions per inclination
    azimuths = {round(math.degrees(math.atan2(u[1], u[0]))) % 360 for u in rolls}
    assert len(azimuths) == 4
    assert check_observability(config, poses).observable


def test_a_plan_outside_the_envelope_is_refused_naming_the_pose() -> None:
    doc = document()
    doc["safety"]["workspace_max_m"] = [0.45, 0.5, 0.9]  # the low inclination's flange lies beyond x = 0.45 m
    with pytest.raises(SafetyError, match="pose"):
        auto_plan(parse_config(doc, "tight.toml"))


def test_the_paper_plan_is_out_of_reach_of_an_xarm5() -> None:
    # the default cell tilts the camera sideways (about its x axis): a 5-axis arm cannot
    config = load_config(None)
    poses = plan_flange_poses(config)
    assert all(math.degrees(sideways_tilt_rad(p)) > 9.0 for p in poses)
    doc = tomllib.loads((REPO_ROOT / "configs" / "sim.toml").read_text())
    doc["handeye"] = {"reach": "xarm5"}
    with pytest.raises(SafetyError, match=r"plan pose 1 .* out of reach of a 'xarm5' arm: tool axis tilted"):
        check_plan(parse_config(doc, "sim.toml"), poses)
    taken = plan_poses(config, "config")  # a 6-axis arm takes it
    assert all(np.allclose(a.as_matrix(), b.as_matrix()) for a, b in zip(taken, poses, strict=True))


@pytest.mark.parametrize(("arm", "reach"), [({"backend": "sim"}, "any"),
                                            ({"backend": "sim", "reach": "xarm5"}, "xarm5"),
                                            ({"backend": "xarm", "port": "/dev/null"}, "xarm5"),
                                            ({"backend": "xarm", "axes": 6}, "any"), ({"backend": "ur"}, "any"),
                                            # the emulator's simulated arm refuses what its own reach key says
                                            ({"backend": "xarm-emulated"}, "any"),
                                            ({"backend": "xarm-emulated", "reach": "xarm5"}, "xarm5")])
def test_the_arm_class_comes_from_the_arm(arm: dict, reach: str) -> None:
    doc = document()
    doc["arm"] = arm
    doc["handeye"].pop("reach", None)
    assert arm_reach(parse_config(doc, "arm.toml")) == reach


def test_the_automatic_plan_needs_a_horizontal_reference() -> None:
    doc = document()
    doc["reference"]["plane_normal"] = [0.0, 1.0, 1.0]
    with pytest.raises(ConfigError, match="horizontal reference plane"):
        auto_plan(parse_config(doc, "tilted.toml"))


def test_reach_classes() -> None:
    radial = Pose(radial_flange_rotation(0.4, 0.3, 1.2).rotation, np.array([0.4 * math.cos(0.4),
                                                                           0.4 * math.sin(0.4), 0.5]))
    assert orientation_violation(radial, "xarm5") is None and orientation_violation(radial, "any") is None
    sideways = Pose(radial_flange_rotation(0.4 + 0.1, 0.3, 1.2).rotation, radial.translation)
    why = orientation_violation(sideways, "xarm5")
    expected = math.degrees(math.asin(math.sin(0.3) * math.sin(0.1)))  # pitch 0.3 rad seen 0.1 rad off the plane
    assert why is not None and why.startswith(f"tool axis tilted {expected:.3f} deg sideways")
    assert orientation_violation(sideways, "any") is None
    with pytest.raises(ValueError, match="unknown reach class"):
        orientation_violation(radial, "scara")


def test_the_simulated_xarm5_refuses_a_sideways_tilt_and_does_not_move() -> None:
    arm = SimArm(SimArmConfig(reach="xarm5", time_scale=0.0))
    start = Pose(radial_flange_rotation(0.0, 0.0, 0.0).rotation, np.array([0.3, 0.0, 0.5]))
    with arm:
        arm.move_linear(start, speed=0.2, acceleration=1.0, timeout=5.0)
        tilted = Pose(radial_flange_rotation(math.radians(90.0), 0.2, 0.0).rotation, start.translation)
        assert arm.workspace_violation(tilted) is not None
        with pytest.raises(VendorError, match="21"):
            arm.move_linear(tilted, speed=0.2, acceleration=1.0, timeout=5.0)
        np.testing.assert_allclose(arm.true_flange_pose().translation, start.translation, atol=1e-12)
        arm.clear_errors()
        toward_base = Pose(radial_flange_rotation(0.0, 0.2, 2.0).rotation, start.translation)
        arm.move_linear(toward_base, speed=0.2, acceleration=1.0, timeout=5.0)  # pitch + roll: fine
    free = SimArm(SimArmConfig(time_scale=0.0))  # the default class takes any orientation
    assert free.workspace_violation(tilted) is None
