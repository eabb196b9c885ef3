"""The plane-constraint estimator on synthetic views: accuracy, intervals, given parameters, OpenCV cross-check."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from handeye_views import NOMINAL_MOUNT, TABLE, TRUE_MOUNT, TRUE_TABLE, TRUE_TABLE_TILT, board_views, plane_views
from repo_paths import REPO_ROOT

from cellcal.core.calibration.config import load_config
from cellcal.core.handeye import PARAMETERS, auto_plan, estimate_mount
from cellcal.devices.errors import CalibrationError, CalibrationQualityError
from cellcal.devices.pose import Pose

CONFIG = REPO_ROOT / "configs" / "sim_handeye.toml"


@pytest.fixture(scope="module")
def flanges() -> list[Pose]:
    """The automatic plan of the hand-eye sim cell (8 poses)."""
    return auto_plan(load_config(CONFIG))


def truth_vector() -> np.ndarray:
    """The 9 parameters of the truth, as steps from the nominal mount and table."""
    turn = (TRUE_MOUNT.rotation * NOMINAL_MOUNT.rotation.inv()).as_rotvec()  # about the flange axes
    return np.concatenate([turn, TRUE_MOUNT.translation - NOMINAL_MOUNT.translation, TRUE_TABLE_TILT,
                           [TRUE_TABLE.offset_m - TABLE.offset_m]])


def test_noise_free_views_give_the_truth(flanges: list[Pose]) -> None:
    est = estimate_mount(plane_views(flanges, None), NOMINAL_MOUNT, TABLE)
    np.testing.assert_allclose(est.mount.translation, TRUE_MOUNT.translation, atol=1e-9)
    assert np.linalg.norm((TRUE_MOUNT.inv() @ est.mount).rotation.as_rotvec()) < 1e-9
    np.testing.assert_allclose(est.plane.normal, TRUE_TABLE.normal, atol=1e-9)
    assert est.plane.offset_m == pytest.approx(TRUE_TABLE.offset_m, abs=1e-9)
    assert est.chi2 < 1e-12 and est.dof == 3 * len(flanges) - 9
    assert all(r.normal_deg < 1e-6 and abs(r.offset_m) < 1e-9 for r in est.residuals)


def test_noisy_views_meet_the_targets_within_their_sigmas(flanges: list[Pose]) -> None:
    est = estimate_mount(plane_views(flanges, np.random.default_rng(3)), NOMINAL_MOUNT, TABLE)
    err_t = est.mount.translation - TRUE_MOUNT.translation
    err_rot = (est.mount.rotation * TRUE_MOUNT.rotation.inv()).as_rotvec()
    assert np.all(np.abs(err_t) < 1e-3) and math.degrees(np.linalg.norm(err_rot)) < 0.05  # the targets
    assert np.all(np.abs(err_t) < 4 * est.translation_sigma_m)
    assert np.all(np.abs(err_rot) < 4 * est.rotation_sigma_rad)
    rpy, rpy_sigma = est.rpy_and_sigma_deg()
    assert np.all(np.abs(rpy - np.degrees(TRUE_MOUNT.as_xyz_rpy()[3:])) < 4 * rpy_sigma)
    assert 0 < est.p_value < 1 and est.observability.observable


@pytest.mark.statistical
def test_intervals_hold_the_truth_95_percent_of_the_time(flanges: list[Pose]) -> None:
    rng = np.random.default_rng(11)
    truth = truth_vector()
    inside = []
    for _ in range(120):
        est = estimate_mount(plane_views(flanges, rng), NOMINAL_MOUNT, TABLE)
        sigma = np.sqrt(np.diag(est.covariance))
        inside.append(np.abs(est.parameters - truth) <= est.z * sigma)
    rate = float(np.mean(inside))  # 1080 intervals: 95 % +- 0.7 % (1 s.e.)
    assert 0.925 <= rate <= 0.975, rate


def test_a_given_parameter_stays_at_its_configured_value(flanges: list[Pose]) -> None:
    views = plane_views(flanges, np.random.default_rng(5))
    est = estimate_mount(views, NOMINAL_MOUNT, TABLE, given=("plane_offset", "mount_z"), max_interval_scale=1e3)
    assert est.plane.offset_m == TABLE.offset_m and est.mount.translation[2] == NOMINAL_MOUNT.translation[2]
    assert est.covariance[8, 8] == 0.0 and est.covariance[5, 5] == 0.0
    assert est.observability.n_parameters == 7 and est.dof == 3 * len(flanges) - 7
    # the truth differs from the given values (1.2 mm, 3 mm), so the fit absorbs it: chi2 far above its dof,
    # and the intervals are scaled by sqrt(chi2/dof) and say that they rest on the given values
    assert est.chi2 > 10 * est.dof and est.noise.verdict == "scaled"
    assert est.interval_scale == pytest.approx(math.sqrt(est.chi2 / est.dof))
    assert any("plane_offset, mount_z held exact" in note for note in est.notes)
    # by default residuals 74x the stated noise are refused, naming the gate and the scale the fit above found
    assert 70 < est.interval_scale < 80
    refusal = rf"'noise_model' failed: {est.interval_scale:.6g} vs threshold 10;"
    with pytest.raises(CalibrationQualityError, match=refusal):
        estimate_mount(views, NOMINAL_MOUNT, TABLE, given=("plane_offset", "mount_z"))


def test_agrees_with_opencv_calibrate_hand_eye_on_the_same_poses(flanges: list[Pose]) -> None:
    rng = np.random.default_rng(2)
    plane = estimate_mount(plane_views(flanges, rng), NOMINAL_MOUNT, TABLE).mount
    board = Pose.from_xyz_rpy([0.2, -0.1, 0.0], np.radians([180.0, 0.0, 10.0]))
    views = board_views(flanges, board, rng, rotation_sigma_rad=1e-4, translation_sigma_m=1e-4)
    r, t = cv2.calibrateHandEye([f.rotation.as_matrix() for f in flanges], [f.translation for f in flanges],
                                [v.rotation.as_matrix() for v in views], [v.translation for v in views],
                                method=cv2.CALIB_HAND_EYE_PARK)
    opencv = Pose.from_matrix(np.vstack([np.hstack([r, t.reshape(3, 1)]), [0, 0, 0, 1]]))
    assert np.linalg.norm(plane.translation - opencv.translation) < 1e-3
    assert math.degrees(np.linalg.norm((plane.inv() @ opencv).rotation.as_rotvec())) < 0.05
    # and both are near the truth (OpenCV's with 0.006 deg / 0.1 mm board noise)
    assert math.degrees(np.linalg.norm((TRUE_MOUNT.inv() @ opencv).rotation.as_rotvec())) < 0.05


def test_bad_calls_are_one_line_errors(flanges: list[Pose]) -> None:
    views = plane_views(flanges, None)
    with pytest.raises(CalibrationError, match="at least 2 poses"):
        estimate_mount(views[:1], NOMINAL_MOUNT, TABLE)
    with pytest.raises(CalibrationError, match="unknown given"):
        estimate_mount(views, NOMINAL_MOUNT, TABLE, given=("mount_w",))
    assert len(PARAMETERS) == 9
