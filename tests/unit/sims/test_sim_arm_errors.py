"""The sim arm's kinematic errors, ``[sim.arm_errors]`` (issue #39, ADR 0055)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cellcal.devices.base import BackendContext
from cellcal.devices.pose import Pose
from cellcal.sims.arm import SimArm
from cellcal.sims.kinematics import ArmErrorsConfig, rms_error
from cellcal.sims.world import world_from_context

DOWN = Pose.from_xyz_rpy(np.array([0.35, 0.1, 0.4]), np.radians([180.0, 10.0, 0.0]))


def world(arm_errors: dict[str, object] | None):
    doc = {"sim": {"seed": 3, **({} if arm_errors is None else {"arm_errors": arm_errors})}}
    return world_from_context(BackendContext(document=doc))


def test_off_the_camera_hangs_on_the_reported_flange_exactly() -> None:
    w = world({"enabled": False})
    w.arm.set_flange_pose(DOWN)
    assert w.arm_errors is None
    assert w.true_flange_pose() is w.arm.flange_pose()
    assert np.array_equal(w.camera_pose().as_matrix(), (DOWN @ w.mount).as_matrix())


def test_on_by_default_the_flange_stands_off_by_about_half_a_millimetre() -> None:
    w = world(None)
    w.arm.set_flange_pose(DOWN)
    true = w.true_flange_pose()
    distance = float(np.linalg.norm(true.translation - DOWN.translation))
    angle = float(np.linalg.norm(DOWN.rotvec_to(true)))
    assert 1e-4 < distance < 1e-3 and math.radians(0.02) < angle < math.radians(0.1)
    assert w.true_flange_pose().as_matrix().tolist() == true.as_matrix().tolist()  # the same every time
    d, a = rms_error(w.arm_errors)  # the default's figure over the workspace sample
    assert d == pytest.approx(4.77e-4, abs=1e-5) and math.degrees(a) == pytest.approx(0.0493, abs=1e-3)


def test_a_base_joint_offset_turns_the_flange_about_the_base_axis() -> None:
    errors = ArmErrorsConfig(True, (0.1, 0.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0)).errors()
    assert errors is not None
    turned = Pose.from_xyz_rotvec(np.zeros(3), (0.0, 0.0, math.radians(0.1))) @ DOWN
    assert np.allclose(errors.true_pose(DOWN).as_matrix(), turned.as_matrix(), atol=1e-12)


def test_a_link_error_moves_the_flange_by_its_length_at_most() -> None:
    errors = ArmErrorsConfig(True, (0.0,) * 5, (0.0, 1.0, 0.0, 0.0)).errors()  # upper arm 1 mm long
    assert errors is not None
    d, a = errors.error_of(DOWN)
    assert d == pytest.approx(1e-3, abs=1e-9) and a == pytest.approx(0.0, abs=1e-12)


def test_the_error_varies_smoothly_with_the_pose() -> None:
    errors = ArmErrorsConfig().errors()
    assert errors is not None
    near = DOWN.with_translation(DOWN.translation + np.array([1e-3, 0.0, 0.0]))
    a, b = errors.true_pose(DOWN), errors.true_pose(near)
    shift_a, shift_b = a.translation - DOWN.translation, b.translation - near.translation
    assert np.linalg.norm(shift_a - shift_b) < 2e-6  # 1 mm apart: the errors differ by about a micrometre


def test_the_sim_arm_reports_the_believed_pose_and_states_the_error() -> None:
    doc = {"sim": {"seed": 3}, "arm": {"backend": "sim", "time_scale": 0.0, "repeatability_m": 0.0}}
    arm = SimArm.from_config({"time_scale": 0.0, "repeatability_m": 0.0},
                             BackendContext(document=doc, section="arm"))
    with arm:
        arm.move_linear(DOWN, speed=0.5, acceleration=2.0)
        assert np.allclose(arm.get_pose().as_matrix(), DOWN.as_matrix(), atol=1e-12)
        assert not np.allclose(arm.physical_flange_pose().translation, DOWN.translation, atol=1e-4)
    model = arm.arm_model()
    assert model.source == "sim" and model.accuracy_m == pytest.approx(4.77e-4, abs=1e-5)
