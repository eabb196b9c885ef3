"""The check that the camera's view follows the arm: predicted against measured plane changes, in sigmas."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cellcal.core.cli.text import MAX_LINE
from cellcal.core.geometry.view_follows import (
    GATE,
    KEEP,
    MAX_STATIC_FRACTION,
    MIN_PREDICTED_SIGMAS,
    MOUNT_TOLERANCE_M,
    MOUNT_TOLERANCE_RAD,
    ViewFollowsArm,
    ViewSample,
    not_on_arm_error,
    view_change,
)
from cellcal.devices.errors import CalibrationQualityError
from cellcal.devices.pose import Pose

#: The packaged sim's configured mount, and the flange 0.5 m above the table (z = 0), tool down.
MOUNT = Pose.from_xyz_rpy([0.0, 0.04, 0.06], np.radians([0.0, 0.0, 90.0]))
START = Pose.from_xyz_rpy([0.3, 0.0, 0.5], np.radians([180.0, 0.0, 0.0]))
#: The table's normal in the base frame (toward the camera above it).
UP = np.array([0.0, 0.0, 1.0])
#: 1-sigma of a ToF full-frame fit's normal (rad) and offset (m), as the sim gives them.
SIGMA_N, SIGMA_C = 1e-4, 2e-5


def rise(dz_m: float, pose: Pose = START) -> Pose:
    """``pose`` moved up by ``dz_m`` along the base z axis."""
    return Pose.from_xyz_rpy([0.0, 0.0, dz_m], [0.0, 0.0, 0.0]) @ pose


def turn_tool(deg: float, pose: Pose = START) -> Pose:
    """``pose`` turned by ``deg`` about its own x axis (across the tool axis)."""
    return pose @ Pose.from_xyz_rpy([0.0, 0.0, 0.0], [math.radians(deg), 0.0, 0.0])


def seen_plane(flange: Pose, mount: Pose = MOUNT) -> tuple[np.ndarray, float]:
    """The table z = 0 as a camera at ``flange @ mount`` sees it: normal toward the camera, offset (distance)."""
    camera = flange @ mount
    return camera.rotation_matrix.T @ UP, float(UP @ camera.translation)


def sample(label: str, flange: Pose, plane: tuple[np.ndarray, float], rng: np.random.Generator | None,
           sigma_n: float = SIGMA_N, sigma_c: float = SIGMA_C) -> ViewSample:
    """A measured plane: ``plane`` with noise of the stated sigmas (none without ``rng``), and that covariance."""
    n, c = np.array(plane[0], dtype=float), float(plane[1])
    tangent = np.eye(3) - np.outer(n, n)
    if rng is not None:
        n = n + tangent @ rng.normal(0.0, sigma_n, 3)
        n /= np.linalg.norm(n)
        c += rng.normal(0.0, sigma_c)
    cov = np.zeros((4, 4))
    cov[:3, :3] = sigma_n**2 * tangent
    cov[3, 3] = sigma_c**2
    return ViewSample(label, flange, n, c, cov)


def on_arm(label: str, flange: Pose, rng: np.random.Generator | None, **kw: float) -> ViewSample:
    return sample(label, flange, seen_plane(flange), rng, **kw)


def fixed(label: str, flange: Pose, rng: np.random.Generator | None, **kw: float) -> ViewSample:
    """A camera that stayed where START put it while the arm went to ``flange``."""
    return sample(label, flange, seen_plane(START), rng, **kw)


def test_a_camera_on_the_arm_sees_the_predicted_turn_and_shift() -> None:
    rng = np.random.default_rng(1)
    end = rise(0.13, turn_tool(15.0))
    change = view_change(on_arm("1", START, rng), on_arm("2", end, rng), MOUNT)
    c0 = seen_plane(START)[1]
    c1 = seen_plane(end)[1]
    assert math.degrees(change.arm_turn_rad) == pytest.approx(15.0, abs=1e-9)
    assert change.arm_travel_m == pytest.approx(math.dist(START.translation, end.translation), abs=1e-12)
    # the normal turns by the flange's turn (about an axis across it), the offset by the camera's rise
    assert math.degrees(change.predicted_turn_rad) == pytest.approx(15.0, abs=0.01)
    assert change.predicted_shift_m == pytest.approx(c1 - c0, abs=1e-4)
    assert math.degrees(change.measured_turn_rad) == pytest.approx(15.0, abs=0.05)
    assert change.measured_shift_m == pytest.approx(c1 - c0, abs=1e-4)
    assert change.measured_sigmas == pytest.approx(change.predicted_sigmas, rel=0.02)
    # the least change any mount within the tolerances predicts: the turn about an axis 90 deg from the
    # normal seen 10 deg closer to it; the rise less its share across a tilted normal and the lever's swing
    half = math.sin(math.radians(7.5))
    least_turn = 2 * math.asin(half * math.sin(math.pi / 2 - MOUNT_TOLERANCE_RAD))
    lever = math.hypot(0.04, 0.06) + MOUNT_TOLERANCE_M
    least_shift = 0.13 - 2 * math.sin(MOUNT_TOLERANCE_RAD / 2) * 0.13 - 2 * half * lever
    assert change.least_turn_rad == pytest.approx(least_turn, abs=1e-4)  # 14.77 deg
    assert change.least_shift_m == pytest.approx(least_shift, abs=1e-4)   # 75.5 mm
    assert change.least_sigmas > 10 * MIN_PREDICTED_SIGMAS           # 14.8 deg over a 1.4e-4 rad noise: ~1800
    assert 1.0 < change.fraction < 2.0                               # > 10x MAX_STATIC_FRACTION (1.45 here)
    assert change.decisive and not change.static


def test_a_camera_that_stays_put_is_static_and_named_in_one_line() -> None:
    rng = np.random.default_rng(2)
    end = rise(0.13, turn_tool(15.0))
    change = view_change(fixed("1", START, rng), fixed("2", end, rng), MOUNT)
    assert change.decisive and change.static
    assert change.fraction < 0.01                                    # noise only: ~2 of ~1800 sigmas
    assert abs(change.measured_shift_m) < 1e-4 and math.degrees(change.measured_turn_rad) < 0.05
    exc = not_on_arm_error(change)
    assert exc.gate == GATE and exc.threshold == MAX_STATIC_FRACTION and exc.value < 0.01
    text = str(exc)
    assert "the camera's view did not change while the arm moved 0.130 m and turned 15.0 deg between poses 1 and 2" \
        in text
    assert "on the arm: " in text and "15.00 deg" in text
    assert text.endswith("the camera is not on the arm that moves (check the rig, [camera]/[arm], or that the "
                         "emulator's scene follows the arm)")
    assert len(f"cellcal: error: {text}") <= MAX_LINE                # printed whole, not elided


def test_the_prediction_holds_with_a_mount_configured_1_deg_and_5_mm_off() -> None:
    """The turn seen does not depend on the mount; its lever moves the shift only by turn x error."""
    rng = np.random.default_rng(3)
    true_mount = Pose.from_xyz_rpy([0.003, 0.036, 0.064], np.radians([0.6, -0.5, 90.6]))
    for end in (turn_tool(15.0), rise(0.05, turn_tool(-25.0)), rise(0.1)):
        a = sample("1", START, seen_plane(START, true_mount), rng)
        b = sample("2", end, seen_plane(end, true_mount), rng)
        change = view_change(a, b, MOUNT)
        assert change.decisive
        assert change.measured_sigmas == pytest.approx(change.predicted_sigmas, rel=0.1)
        assert change.fraction > 1.0                                 # the truth is at least the least change


def test_a_half_turn_about_the_plane_normal_with_a_mount_1_deg_off_is_no_evidence() -> None:
    """The configured mount alone would predict a 2 deg turn; any mount within 10 deg allows none."""
    rng = np.random.default_rng(8)
    true_mount = Pose.from_xyz_rpy([0.0, 0.04, 0.06], np.radians([1.0, 0.0, 90.0]))
    tilted = Pose.from_xyz_rpy([0.3, 0.0, 0.5], np.radians([170.0, 0.0, 0.0]))
    vertical = np.array([0.3, 0.0, 0.0])
    half_turn = Pose.from_xyz_rpy(vertical, [0.0, 0.0, math.pi]) @ Pose.from_xyz_rpy(-vertical, [0.0, 0.0, 0.0])
    end = half_turn @ tilted                                          # about the vertical through the flange
    a = sample("1", tilted, seen_plane(tilted, true_mount), rng)
    b = sample("2", end, seen_plane(end, true_mount), rng)           # the same view: a camera on the arm
    change = view_change(a, b, MOUNT)
    assert math.degrees(change.predicted_turn_rad) == pytest.approx(2.0, abs=0.1)
    # judged by the configured mount alone, this camera on the arm would have been called static
    assert change.predicted_sigmas > 2 * MIN_PREDICTED_SIGMAS
    assert change.measured_sigmas / change.predicted_sigmas < MAX_STATIC_FRACTION
    assert change.least_turn_rad == 0.0 and change.least_shift_m == 0.0
    assert not change.decisive and not change.static


def test_a_turn_about_the_plane_normal_changes_nothing_and_decides_nothing() -> None:
    rng = np.random.default_rng(4)
    end = Pose.from_xyz_rpy([0.0, 0.0, 0.0], np.radians([0.0, 0.0, 30.0])) @ START  # about the base z axis
    for make in (on_arm, fixed):
        change = view_change(make("1", START, rng), make("2", end, rng), MOUNT)
        # what is left is the first sample's normal noise (1e-4 rad) times the 0.155 m travel: ~1 sigma
        assert change.predicted_sigmas < 10.0 and not change.decisive and not change.static
        assert abs(change.predicted_shift_m) < 1e-4 and math.degrees(change.predicted_turn_rad) < 0.01
    check = ViewFollowsArm(MOUNT)
    assert check.add(fixed("1", START, rng)) is None
    assert check.add(fixed("2", end, rng)) is None                   # the arm moved, but not so the camera could tell
    assert check.decided is None


@pytest.mark.parametrize(("sigma_c", "arm_sigma_m", "sigmas", "decisive"), [
    (2.5e-5, 0.0, 0.01 / math.sqrt(2 * 2.5e-5**2), True),            # 283 sigmas
    (1e-4, 0.0, 0.01 / math.sqrt(2 * 1e-4**2), False),               # 70.7 sigmas
    (2.5e-5, 1e-4, 0.01 / math.sqrt(2 * (2.5e-5**2 + 1e-4**2)), False),  # the arm's read-back noise counts: 68.6
])
def test_whether_a_rise_decides_comes_from_the_noise(sigma_c: float, arm_sigma_m: float, sigmas: float,
                                                     decisive: bool) -> None:
    """A 10 mm rise, tool still: only the offset changes, by 10 mm over the two samples' offset noise."""
    change = view_change(on_arm("1", START, None, sigma_c=sigma_c), on_arm("2", rise(0.01), None, sigma_c=sigma_c),
                         MOUNT, arm_translation_sigma_m=arm_sigma_m)
    assert change.predicted_shift_m == pytest.approx(0.01, abs=1e-12)
    assert change.predicted_sigmas == pytest.approx(sigmas, rel=1e-9)
    assert change.measured_sigmas == pytest.approx(sigmas, rel=1e-9)
    assert change.decisive is decisive and not change.static


def test_noise_free_samples_still_give_finite_sigmas() -> None:
    zero = np.zeros((4, 4))
    n0, c0 = seen_plane(START)
    a = ViewSample("1", START, n0, c0, zero)
    b_arm = ViewSample("2", rise(0.1), *seen_plane(rise(0.1)), zero)
    b_fixed = ViewSample("2", rise(0.1), n0, c0, zero)
    following, static = view_change(a, b_arm, MOUNT), view_change(a, b_fixed, MOUNT)
    assert math.isfinite(following.predicted_sigmas)
    assert following.measured_sigmas == pytest.approx(following.predicted_sigmas, rel=1e-9)
    assert following.fraction > 1.0
    assert static.measured_sigmas == 0.0 and static.static


def test_the_run_check_stops_at_the_first_deciding_pose_and_names_the_largest_change() -> None:
    rng = np.random.default_rng(5)
    check = ViewFollowsArm(MOUNT)
    assert check.add(fixed("1", START, rng)) is None
    assert check.add(fixed("2", rise(-0.001), rng)) is None        # 1 mm down: 35 sigmas, not enough to decide
    with pytest.raises(CalibrationQualityError) as info:
        check.add(fixed("3", rise(0.13), rng))                      # 4600 sigmas from pose 1, 4630 from pose 2
    assert info.value.gate == GATE
    assert "moved 0.131 m and turned 0.0 deg between poses 2 and 3" in str(info.value)


def test_once_the_view_is_seen_to_follow_later_samples_are_not_judged() -> None:
    rng = np.random.default_rng(6)
    check = ViewFollowsArm(MOUNT, what="frames at")
    check.add(on_arm("0.0 s", START, rng))
    decided = check.add(on_arm("2.0 s", turn_tool(10.0), rng))
    assert decided is not None and decided.fraction > 1.0
    assert check.decided is decided and check.kept == []
    assert check.add(fixed("9.0 s", rise(0.2), rng)) is decided    # a later static view is the tracker's business


def test_only_the_first_samples_are_kept_while_the_arm_has_not_moved_enough() -> None:
    rng = np.random.default_rng(7)
    check = ViewFollowsArm(MOUNT)
    for i in range(3 * KEEP):
        assert check.add(on_arm(str(i + 1), rise(5e-5 * i), rng)) is None  # 0.05 mm steps: at most 41 sigmas apart
    assert [s.label for s in check.kept] == [str(i + 1) for i in range(KEEP)]
