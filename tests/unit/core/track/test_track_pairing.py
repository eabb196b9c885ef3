"""PoseHistory: the flange pose at a frame's time, and the frames it refuses, with exact figures."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cellcal.core.track.pairing import SKIP_FAST, SKIP_NO_POSE, SKIP_TURNING, PoseHistory, Skip
from cellcal.devices.pose import Pose


def pose(x_m: float, yaw_deg: float = 0.0) -> Pose:
    return Pose.from_xyz_rpy([x_m, 0.2, 0.3], [0.0, 0.0, math.radians(yaw_deg)])


def test_interpolates_translation_linearly_and_rotation_at_a_constant_rate() -> None:
    history = PoseHistory()
    history.add(0.0, pose(0.0, 0.0))
    history.add(0.01, pose(0.0004, 0.04))  # 40 mm/s and 4 deg/s
    got = history.at(0.0025)
    assert isinstance(got, Pose)
    np.testing.assert_allclose(got.translation, [0.0001, 0.2, 0.3], atol=1e-15)
    assert math.degrees(got.as_xyz_rpy()[5]) == pytest.approx(0.01, abs=1e-12)
    exact = history.at(0.01)  # a sample at the frame time is returned as it is
    assert isinstance(exact, Pose) and exact.is_close(pose(0.0004, 0.04))


def test_a_fast_arm_is_skipped_with_its_speed() -> None:
    history = PoseHistory()
    history.add(0.0, pose(0.0))
    history.add(0.01, pose(0.001))  # 100 mm/s, limit 50
    got = history.at(0.005)
    assert got == Skip(SKIP_FAST, "100 mm/s (limit 50 mm/s)")


def test_a_turning_arm_is_skipped_with_its_rate() -> None:
    history = PoseHistory(max_turn_rate_rad_s=math.radians(5.0))
    history.add(0.0, pose(0.0, 0.0))
    history.add(0.01, pose(0.0, 0.06))  # 6 deg/s, limit 5
    got = history.at(0.005)
    assert got == Skip(SKIP_TURNING, "6.0 deg/s (limit 5.0 deg/s)")


def test_an_exact_hit_is_judged_by_the_segments_around_it() -> None:
    history = PoseHistory()
    for k, x in enumerate([0.0, 0.0, 0.002]):  # still, then 200 mm/s
        history.add(0.01 * k, pose(x))
    assert isinstance(history.at(0.01), Skip)  # the arm leaves the sample at 200 mm/s over 20 ms: 100 mm/s
    assert history.at(0.01).reason == SKIP_FAST  # type: ignore[union-attr]


def test_frames_without_a_pose_on_both_sides_are_skipped() -> None:
    history = PoseHistory()
    assert history.at(0.0) == Skip(SKIP_NO_POSE, "no arm pose yet")
    assert history.pending(0.0)
    history.add(1.0, pose(0.0))
    history.add(1.2, pose(0.0))  # 200 ms apart, limit 100
    assert history.at(1.1) == Skip(SKIP_NO_POSE, "arm samples 200 ms apart around the frame (limit 100 ms)")
    assert history.at(0.5).reason == SKIP_NO_POSE  # type: ignore[union-attr]
    assert history.at(1.3) == Skip(SKIP_NO_POSE, "frame at 1.3000 s is after the newest arm pose")
    assert history.pending(1.3) and not history.pending(1.2)


def test_out_of_order_samples_are_dropped_and_the_buffer_is_bounded() -> None:
    history = PoseHistory(capacity=4)
    for k in range(10):
        history.add(0.01 * k, pose(0.0))
    history.add(0.05, pose(1.0))  # older than the newest: dropped
    history.add(0.09, pose(1.0))  # repeated time: dropped
    assert len(history) == 4 and history.dropped == 2
    assert history.newest_s == pytest.approx(0.09)
    assert isinstance(history.at(0.075), Pose)
    assert history.at(0.055).reason == SKIP_NO_POSE  # type: ignore[union-attr]  # fell out of the buffer
    with pytest.raises(ValueError):
        PoseHistory(capacity=1)
