"""Change detection: the CUSUM, a knock on the camera, a moved table, and no alarm on a long run without change."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from cellcal.core.handeye.synthetic import Scenario, sim_scenario
from cellcal.core.track import ChangeEvent, Tracker
from cellcal.core.track.detector import Cusum
from cellcal.core.track.synthetic import knocked_mount, shifted_plane, work

SC = sim_scenario()


def test_cusum_adds_clipped_excess_and_remembers_the_run() -> None:
    cusum = Cusum(reference=8.0, clip=40.0, threshold=120.0)
    assert not cusum.update(3.0) and cusum.statistic == 0.0 and cusum.run_length == 0
    assert not cusum.update(1000.0) and cusum.statistic == 32.0 and cusum.run_length == 1  # clipped at 40
    assert not cusum.update(20.0) and cusum.statistic == 44.0
    assert not cusum.update(40.0) and not cusum.update(40.0) and cusum.statistic == 108.0
    assert cusum.update(21.0) and cusum.statistic == 121.0 and cusum.run_length == 5
    cusum.reset()
    assert cusum.statistic == 0.0 and cusum.run_length == 0
    with pytest.raises(ValueError):
        Cusum(reference=50.0, clip=40.0)


def settle(tracker: Tracker, scenario: Scenario, rng: np.random.Generator, frames: int) -> None:
    for t_s, obs in work(scenario, rng, frames):
        assert tracker.update(t_s, obs).event is None


def events_after(tracker: Tracker, scenario: Scenario, rng: np.random.Generator, start: int,
                 frames: int) -> list[tuple[int, ChangeEvent]]:
    """Frame number (after the change) and event of each step that reported one."""
    out = []
    for t_s, obs in work(scenario, rng, frames, start_frame=start):
        step = tracker.update(t_s, obs)
        if step.event is not None:
            out.append((round(t_s * 30) - start, step.event))
    return out


def test_a_half_degree_knock_is_detected_told_apart_and_re_estimated() -> None:
    rng = np.random.default_rng(21)
    tracker = Tracker(SC.nominal_mount, SC.nominal_plane)
    settle(tracker, SC, rng, 600)
    knocked = dataclasses.replace(SC, true_mount=knocked_mount(SC.true_mount, 0.5, (0.0, 1.0, 0.0)))
    seen = events_after(tracker, knocked, rng, 607, 300)
    first_frame, first = seen[0]
    assert first_frame <= 5 and first.kind == "mount or plane"  # detected at once, not told apart at one pose
    assert first.started_at_s == pytest.approx(607 / 30)  # the change point: the knock's first frame
    state = tracker.state
    assert len(state.events) == 1 and not state.change_unresolved
    event = state.events[0]
    assert event.kind == "mount" and event.size["rotation_deg"] == pytest.approx(0.5, abs=0.01)
    assert event.resolved_at_s is not None and event.resolved_at_s - event.detected_at_s < 2.0
    truth = knocked.true_mount
    assert math.degrees(state.mount.angle_to(truth)) < 0.01
    assert np.linalg.norm(state.mount.translation - truth.translation) < 1e-4
    error = state.mount_translation_sigma_m * state.interval_z
    assert np.all(np.abs(state.mount.translation - truth.translation) <= error)
    assert abs(state.plane.offset_m - SC.true_plane.offset_m) < 5e-5  # the plane kept


def test_a_5_mm_table_shift_is_told_apart_from_a_mount_change() -> None:
    rng = np.random.default_rng(22)
    tracker = Tracker(SC.nominal_mount, SC.nominal_plane)
    settle(tracker, SC, rng, 600)
    moved = dataclasses.replace(SC, true_plane=shifted_plane(SC.true_plane, 0.005))
    seen = events_after(tracker, moved, rng, 607, 300)
    assert seen[0][0] <= 5
    state = tracker.state
    event = state.events[0]
    assert event.kind == "plane" and event.size["plane_shift_m"] == pytest.approx(0.005, abs=1e-4)
    assert event.size["plane_offset_m"] == pytest.approx(-0.005, abs=1e-4) and event.size["plane_tilt_deg"] < 0.005
    assert not state.change_unresolved
    assert abs(state.plane.offset_m - moved.true_plane.offset_m) < 5e-5
    assert np.linalg.norm(state.mount.translation - SC.true_mount.translation) < 1e-4  # the mount kept


def test_at_one_pose_a_change_is_mount_or_plane_and_waits() -> None:
    rng = np.random.default_rng(23)
    tracker = Tracker(SC.nominal_mount, SC.nominal_plane)
    settle(tracker, SC, rng, 600)
    moved = dataclasses.replace(SC, true_plane=shifted_plane(SC.true_plane, 0.005))
    for t_s, obs in work(moved, rng, 100, start_frame=600, dwell=1000):  # the arm stays at view 0
        step = tracker.update(t_s, obs)
        assert not step.accepted
    state = tracker.state
    assert state.events[0].kind == "mount or plane" and state.change_unresolved
    assert np.all(np.isnan(state.mount_translation_sigma_m))  # no interval while it is open


@pytest.mark.statistical
def test_no_alarm_in_3000_frames_without_change() -> None:
    rng = np.random.default_rng(24)
    tracker = Tracker(SC.nominal_mount, SC.nominal_plane)
    accepted = sum(tracker.update(t_s, obs).accepted for t_s, obs in work(SC, rng, 3000))
    state = tracker.state
    assert not state.events and not state.change_unresolved
    assert accepted == 3000 and state.noise is not None and state.noise.verdict == "consistent"
