"""Pinned numbers of the tracker's estimate and its intervals (issue #32): intervals against an independent
least-squares fit of the same frames (tests/support/track_batch_fit.py), the noise test and its scaling, the
observability threshold on constructed informations at its exact boundary, the plane's orientation, the weak
prior, the windows, the arm's turn noise, and the batch step every 30 accepted frames.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy.stats import chi2 as chi2_dist
from scipy.stats import norm
from scipy.stats import t as student_t
from track_batch_fit import ARM_SIGMA_M, SC, WEAK, batch, feed, residuals_of, rpy_sigma_deg

from cellcal.core.geometry.planes import Plane
from cellcal.core.handeye.model import PARAMETERS, PlaneModel, PlaneObservation
from cellcal.core.handeye.observability import UNOBSERVABLE_SIGMA
from cellcal.core.handeye.synthetic import Scenario, camera_views
from cellcal.core.track import Tracker, TrackSettings
from cellcal.core.track.synthetic import work
from cellcal.devices.pose import Pose


# -------------------------------------------------------------------- intervals against a batch fit
def test_estimate_and_intervals_equal_an_independent_batch_fit_of_the_same_frames() -> None:
    tracker = Tracker(SC.nominal_mount, SC.nominal_plane)
    run = feed(tracker, SC, 31, 240)
    obs = [o for o, _ in run]
    x_ref, jac = batch(obs)
    info = np.einsum("nki,nkj->ij", jac, jac)
    cov = np.linalg.inv(info)  # no prior in the intervals: the data's information only
    sigma = np.sqrt(np.diag(cov))
    state = tracker.state
    assert state.frames_used == 240 and all(step.accepted for _, step in run)
    assert np.all(np.abs(state.parameters - x_ref) < 0.01 * sigma)  # the same estimate, to 1 % of a sigma
    np.testing.assert_allclose(state.covariance, cov, rtol=2e-3, atol=2e-3 * np.outer(sigma, sigma).max() * 1e-3)
    np.testing.assert_allclose(np.sqrt(np.diag(state.covariance)), sigma, rtol=1e-3)
    np.testing.assert_allclose(state.mount_translation_sigma_m, sigma[3:6], rtol=1e-3)
    np.testing.assert_allclose(state.plane_tilt_sigma_deg, np.degrees(sigma[6:8]), rtol=1e-3)
    assert state.plane_offset_sigma_m == pytest.approx(sigma[8], rel=1e-3)
    np.testing.assert_allclose(state.mount_rpy_sigma_deg, rpy_sigma_deg(state.mount, cov[:3, :3]), rtol=1e-3)
    # the noise is as stated: the test over every accepted frame's normalised innovation is consistent
    assert state.noise is not None and state.noise.verdict == "consistent" and state.noise.dof == 240
    assert state.interval_scale == 1.0 and state.interval_z == pytest.approx(norm.ppf(0.975), rel=1e-12)
    assert state.confidence == 0.95 and state.intervals_withheld == ""
    model = PlaneModel(SC.nominal_mount, SC.nominal_plane)
    assert state.mount.distance_to(model.mount(x_ref)) < 0.01 * sigma[3:6].min()
    assert state.plane.offset_m == pytest.approx(model.plane(x_ref).offset_m, abs=0.01 * sigma[8])  # as the parameters
    rpy_ref = np.degrees(model.mount(x_ref).as_xyz_rpy()[3:])
    assert np.all(np.abs(state.mount_rpy_deg - rpy_ref) < 0.02 * state.mount_rpy_sigma_deg)


def test_understated_noise_scales_each_component_share_as_the_innovations_show() -> None:
    noisy = SC.with_arm_noise(1e-4, 0.0)  # the arm reads back 0.1 mm per axis, the tracker is told 25 um
    tracker = Tracker(SC.nominal_mount, SC.nominal_plane)
    run = feed(tracker, noisy, 5, 300)
    accepted = [(o, s) for o, s in run if s.accepted]
    nis = np.array([np.asarray(s.residual) ** 2 for _, s in accepted]).sum(axis=0)  # per component
    n = len(accepted)
    # the test per component, independently: a component beyond the upper 1 % tail is scaled by chi2/dof
    scaled = chi2_dist.sf(nis, n) < 0.01
    factors = np.where(scaled, nis / n, 1.0)
    assert scaled.tolist() == [False, False, True]  # the offset carries the arm's translation noise
    state = tracker.state
    assert state.noise is not None and state.noise.verdict == "scaled" and state.noise.dof == n
    assert state.noise.chi2 == pytest.approx(nis.max(), rel=1e-9)  # the worst component's test
    assert state.interval_scale == pytest.approx(math.sqrt(factors.max()), rel=1e-9)
    assert state.interval_z == pytest.approx(student_t.ppf(0.975, n), rel=1e-9)
    # the sandwich: the information split by residual component, each share scaled by its own factor
    _, jac = batch([o for o, _ in accepted])
    parts = np.einsum("nki,nkj->kij", jac, jac)
    inv = np.linalg.inv(parts.sum(axis=0))
    cov = inv @ np.einsum("k,kij->ij", factors, parts) @ inv
    np.testing.assert_allclose(np.sqrt(np.diag(state.covariance)), np.sqrt(np.diag(cov)), rtol=3e-3)
    assert not state.events and state.intervals_withheld == ""


def test_intervals_are_withheld_above_the_largest_scale_with_one_sentence() -> None:
    noisy = SC.with_arm_noise(1e-4, 0.0)
    low = Tracker(SC.nominal_mount, SC.nominal_plane, TrackSettings(max_interval_scale=2.0))
    feed(low, noisy, 5, 300)
    state = low.state
    assert state.interval_scale > 2.0 and not state.events
    assert state.intervals_withheld == (f"the residuals are {state.interval_scale:.1f}x the stated noise: the noise "
                                        "model or the configured values are wrong, intervals withheld")
    assert np.all(np.isnan(state.covariance)) and np.all(np.isnan(state.mount_translation_sigma_m))
    assert np.all(np.isnan(state.mount_rpy_sigma_deg)) and np.all(np.isnan(state.plane_tilt_sigma_deg))
    assert math.isnan(state.plane_offset_sigma_m)
    # at the scale itself the intervals are given (withheld strictly above it)
    at = Tracker(SC.nominal_mount, SC.nominal_plane, TrackSettings(max_interval_scale=state.interval_scale))
    feed(at, noisy, 5, 300)
    given = at.state
    assert given.interval_scale == state.interval_scale and given.intervals_withheld == ""
    assert np.all(np.isfinite(given.covariance)) and np.all(np.isfinite(given.mount_rpy_sigma_deg))


def test_the_state_before_any_frame_and_after_one() -> None:
    tracker = Tracker(SC.nominal_mount, SC.nominal_plane)
    state = tracker.state
    assert state.noise is None and state.interval_scale == 1.0
    assert state.interval_z == pytest.approx(norm.ppf(0.975), rel=1e-12) and state.events == []
    assert not state.change_unresolved and state.frames_used == 0
    np.testing.assert_array_equal(state.parameters, np.zeros(9))
    assert np.all(np.isnan(state.covariance))
    feed(tracker, SC, 48, 1)
    state = tracker.state
    assert state.frames_used == 1 and state.noise is not None and state.noise.dof == 1
    assert len(state.unseen) >= 1 and all(": not shown by the work so far (would need " in u for u in state.unseen)


# ------------------------------------------------------------- observability on constructed informations
def constructed(lam: np.ndarray, basis: np.ndarray | None = None) -> Tracker:
    """A tracker whose data information is ``Q diag(lam) Qᵀ`` (one component's share), with one normal kept."""
    tracker = Tracker(SC.nominal_mount, SC.nominal_plane)
    q = np.eye(9) if basis is None else basis
    info = (q * lam) @ q.T
    tracker._info = info
    tracker._parts = np.zeros((4, 9, 9))
    tracker._parts[0] = info
    tracker._normals.append(np.array([0.0, 0.0, 1.0]))
    return tracker


def test_a_direction_is_seen_from_information_0_1_to_the_minus_2_its_sigma_0_1() -> None:
    lam = np.full(9, 1e6)
    lam[8] = UNOBSERVABLE_SIGMA ** -2  # sigma 0.1 m: exactly the hand-eye threshold
    state = constructed(lam).state
    assert all(state.observable.values())
    assert state.plane_offset_sigma_m == pytest.approx(0.1, rel=1e-12)
    np.testing.assert_allclose(state.mount_translation_sigma_m, 1e-3, rtol=1e-12)
    lam[8] = math.nextafter(UNOBSERVABLE_SIGMA ** -2, 0.0)  # just below: unseen, no sigma, the configured value kept
    tracker = constructed(lam)
    tracker._x = np.full(9, 1e-3)
    state = tracker.state
    assert [k for k, v in state.observable.items() if not v] == ["plane_offset"]
    assert math.isnan(state.plane_offset_sigma_m) and np.all(np.isnan(state.covariance[8]))
    assert np.all(np.isnan(state.covariance[:, 8])) and np.all(np.isfinite(state.covariance[:8, :8]))
    np.testing.assert_allclose(state.parameters, np.r_[np.full(8, 1e-3), 0.0], rtol=0, atol=1e-18)
    assert state.plane.offset_m == SC.nominal_plane.offset_m


def test_the_threshold_rises_with_the_largest_information_1e_20_of_it() -> None:
    lam = np.full(9, 1e12)
    lam[0] = 1e30
    lam[5] = lam[0] * 1e-20  # 1e10: at the relative threshold, seen
    assert all(constructed(lam).state.observable.values())
    lam[5] = math.nextafter(lam[0] * 1e-20, 0.0)  # below it: unseen although far above 100
    state = constructed(lam).state
    assert [k for k, v in state.observable.items() if not v] == [PARAMETERS[5]]
    assert math.isnan(state.mount_translation_sigma_m[2]) and np.isfinite(state.mount_translation_sigma_m[:2]).all()


def rotation_into(i: int, j: int, share: float) -> np.ndarray:
    """An orthonormal basis whose last column has ``share`` of parameter ``i`` and the rest in ``j``."""
    q = np.eye(9)
    c, s = share, math.sqrt(1.0 - share**2)
    q[:, [i, j]] = np.column_stack([np.eye(9)[i] * s - np.eye(9)[j] * c, np.eye(9)[i] * c + np.eye(9)[j] * s])
    return q[:, [k for k in range(9) if k != j] + [j]]


@pytest.mark.parametrize(("share", "seen"), [(0.049, True), (0.051, False)])
def test_a_parameter_is_seen_when_under_5_percent_of_it_lies_in_the_unseen_direction(share: float, seen: bool
                                                                                     ) -> None:
    lam = np.r_[np.full(8, 1e6), 1.0]  # the last basis direction is unseen
    state = constructed(lam, rotation_into(3, 8, share)).state  # mount_x with a share of it, plane_offset the rest
    assert state.observable["plane_offset"] is False
    assert state.observable["mount_x"] is seen
    assert bool(np.isfinite(state.mount_translation_sigma_m[0])) is seen
    assert sum(not v for v in state.observable.values()) == (1 if seen else 2)


def test_rpy_sigma_is_withheld_for_an_angle_that_moves_with_an_unseen_turn() -> None:
    lam = np.r_[np.full(8, 1e6), 1.0]
    q = np.eye(9)[:, [1, 2, 3, 4, 5, 6, 7, 8, 0]]  # the turn about flange x unseen
    state = constructed(lam, q).state
    assert not state.observable["mount_rot_x"] and state.observable["mount_rot_y"]
    mount = state.mount
    share = rpy_sigma_deg(mount, np.diag([1.0, 0.0, 0.0]))  # how much of each angle a turn about x moves
    expected_nan = share > math.degrees(0.05)
    assert expected_nan.any() and not expected_nan.all()
    assert np.isnan(state.mount_rpy_sigma_deg).tolist() == expected_nan.tolist()
    cov = np.diag(np.r_[0.0, np.full(2, 1e-6)])
    finite = ~expected_nan
    np.testing.assert_allclose(state.mount_rpy_sigma_deg[finite], rpy_sigma_deg(mount, cov)[finite], rtol=1e-4)


def test_unseen_directions_are_named_in_the_users_words() -> None:
    views = camera_views(SC.true_mount, [0.3, 0.0, 0.0], 0.45, (70.0,), (0.0, 90.0, 180.0, 270.0))
    tracker = Tracker(SC.nominal_mount, SC.nominal_plane)
    feed(tracker, dataclasses.replace(SC, flanges=views), 4, 240)
    assert tracker.state.unseen == [
        "mount translation along flange z vs the plane's height: not shown by the work so far (would need poses at "
        "a second inclination (one cone of normals is not enough), or given = [\"plane_offset\"])"]


# -------------------------------------------------------------------------- the plane's orientation
def test_a_plane_configured_with_its_normal_away_from_the_cameras_is_turned_toward_them() -> None:
    """The table configured at z = 1 mm, once with its normal up (toward the cameras), once down: the same."""
    toward = Tracker(SC.nominal_mount, Plane(np.array([0.0, 0.0, 1.0]), -0.001))
    away = Tracker(SC.nominal_mount, Plane(np.array([0.0, 0.0, -1.0]), 0.001))
    a = feed(toward, SC, 12, 120)
    b = feed(away, SC, 12, 120)
    assert [s.chi2 for _, s in a] == pytest.approx([s.chi2 for _, s in b], rel=1e-9)
    s1, s2 = toward.state, away.state
    np.testing.assert_allclose(np.asarray(s2.plane.normal), np.asarray(s1.plane.normal), atol=1e-12)
    assert s2.plane.normal[2] > 0.99 and s2.plane.offset_m == pytest.approx(s1.plane.offset_m, abs=1e-12)
    np.testing.assert_allclose(s2.parameters, s1.parameters, atol=1e-12)
    assert not s2.events and s2.frames_used == 120
    assert np.asarray(away.nominal_plane.normal).tolist() == [0.0, 0.0, 1.0] and away.nominal_plane.offset_m == -0.001


@pytest.mark.parametrize("off_m", [0.46, 0.6])
def test_a_plane_configured_beyond_the_camera_keeps_its_normal_toward_the_measured_one(off_m: float) -> None:
    """The table configured 0.46 / 0.6 m too high: the cameras (0.45 m above it) are below the configured plane.

    Turning the normal toward the cameras' configured positions would point it down: the normal's error across
    itself cannot tell a normal from its opposite, and the estimate converged to the mirrored mount 0.9 m off
    (found by this test). The measured normal, seen in the base frame, says up.
    """
    high = Plane(np.array(SC.nominal_plane.normal), SC.nominal_plane.offset_m - off_m)
    tracker = Tracker(SC.nominal_mount, high)
    run = feed(tracker, SC, 90, 240)
    first = run[0][0]
    measured_up = (first.flange @ SC.nominal_mount).rotation_matrix @ first.normal
    assert measured_up[2] > 0.99 and tracker.nominal_plane.normal[2] == 1.0
    assert tracker.nominal_plane.offset_m == high.offset_m
    state = tracker.state
    error_m = float(np.linalg.norm(state.mount.translation - SC.true_mount.translation))
    if off_m == 0.6:  # far enough out for the frames to be told apart: re-estimated from the data
        assert not state.change_unresolved and error_m < 1e-4 and state.plane.normal[2] > 0.99
        assert abs(state.plane.offset_m - SC.true_plane.offset_m) < 5e-5
    else:  # every frame just beyond the clip: kept, the change still open, no interval and nothing moved
        assert state.change_unresolved and state.frames_used == 0 and error_m < 0.01
        assert np.all(np.isnan(state.mount_translation_sigma_m))


def flip_plane(plane: Plane) -> Plane:
    """The plane turned upside down about base x (a point p goes to diag(1, -1, -1) p)."""
    return Plane(np.asarray(plane.normal) * np.array([1.0, -1.0, -1.0]), plane.offset_m)


def test_a_ceiling_seen_from_below_gets_its_normal_turned_down() -> None:
    """Cameras below the plane, the plane configured with its normal up: turned toward them at the first frame."""
    from scipy.spatial.transform import Rotation

    flip = Pose(Rotation.from_euler("x", math.pi), np.zeros(3))  # the whole cell upside down about base x
    scenario = dataclasses.replace(SC, flanges=tuple(flip @ f for f in SC.flanges),
                                   true_plane=flip_plane(SC.true_plane), nominal_plane=flip_plane(SC.nominal_plane))
    ceiling = Plane(np.array([0.0, 0.0, 1.0]), 0.0)  # normal up, away from the cameras below
    tracker = Tracker(SC.nominal_mount, ceiling)
    run = feed(tracker, scenario, 13, 240)
    assert all(s.accepted for _, s in run)
    state = tracker.state
    assert state.plane.normal[2] < -0.99  # toward the cameras below
    assert abs(state.plane.offset_m - scenario.true_plane.offset_m) < 5e-5
    assert math.degrees(state.mount.angle_to(SC.true_mount)) < 0.01


def alternating(turn_deg: float) -> Scenario:
    """View 0 and view 0 turned about base x by ``turn_deg`` (the plane normal seen from the flange turns as much)."""
    from scipy.spatial.transform import Rotation

    turn = Pose(Rotation.from_euler("x", math.radians(turn_deg)), np.zeros(3))
    return dataclasses.replace(SC, flanges=(SC.flanges[0], turn @ SC.flanges[0]))


@pytest.mark.parametrize(("turn_deg", "kept"), [(0.9, 1), (1.1, 6)])
def test_a_plane_normal_is_kept_when_it_differs_by_more_than_1_degree(turn_deg: float, kept: int) -> None:
    tracker = Tracker(SC.nominal_mount, SC.nominal_plane)
    feed(tracker, alternating(turn_deg), 57, 30, dwell=5)  # 6 dwells, alternating
    assert len(tracker._normals) == kept


# ------------------------------------------------------------------ the prior, the windows, the arm's turn noise
def test_the_first_frame_is_judged_against_the_weak_prior_and_stepped_to_its_fit() -> None:
    tracker = Tracker(SC.nominal_mount, SC.nominal_plane)
    (obs, step), = feed(tracker, SC, 50, 1)
    fun = residuals_of([obs])
    h = 1e-6
    jac = np.column_stack([(fun(h * e) - fun(-h * e)).ravel() / (2 * h) for e in np.eye(9)])  # (3, 9)
    r = fun(np.zeros(9)).ravel()
    innov = np.eye(3) + jac @ jac.T / WEAK  # the residual's covariance with the prior's (0.05 rad / m) spread
    assert step.chi2 == pytest.approx(float(r @ np.linalg.solve(innov, r)), rel=1e-6)
    assert step.accepted and step.note == ""
    x_ref, _ = batch([obs])  # one frame and the weak prior, minimised
    np.testing.assert_allclose(tracker._x, x_ref, rtol=0, atol=1e-7)  # two Gauss-Newton steps: converged to 2e-6 sigma
    # one frame shows three directions (the rows of its Jacobian): the others keep the configured values
    at = np.column_stack([(fun(x_ref + h * e) - fun(x_ref - h * e)).ravel() / (2 * h) for e in np.eye(9)])
    seen = np.linalg.pinv(at) @ at  # projector on the row space of the Jacobian at the estimate
    np.testing.assert_allclose(tracker.state.parameters, seen @ x_ref, rtol=0, atol=1e-7)
    assert not any(tracker.state.observable.values())  # no single parameter lies in three directions


def test_a_window_shorter_than_the_work_gives_the_batch_fit_of_every_frame() -> None:
    tracker = Tracker(SC.nominal_mount, SC.nominal_plane, TrackSettings(window=60, relinearise_every=20))
    run = feed(tracker, SC, 52, 300)
    x_ref, jac = batch([o for o, _ in run])
    sigma = np.sqrt(np.diag(np.linalg.inv(np.einsum("nki,nkj->ij", jac, jac))))
    state = tracker.state
    assert state.frames_used == 300 and len(tracker._window) == 60
    assert np.all(np.abs(state.parameters - x_ref) < 0.02 * sigma)  # frames left the window as a quadratic prior
    np.testing.assert_allclose(np.sqrt(np.diag(state.covariance)), sigma, rtol=2e-3)


def test_the_arm_turn_noise_acts_through_the_mount_lever() -> None:
    turn_sigma = 2e-5  # rad: 9 um at the 72 mm lever, comparable to the offset noise
    noisy = SC.with_arm_noise(ARM_SIGMA_M, turn_sigma)
    tracker = Tracker(SC.nominal_mount, SC.nominal_plane, TrackSettings(arm_rotation_sigma_rad=turn_sigma))
    run = feed(tracker, noisy, 51, 240)
    obs = [o for o, _ in run]
    _, jac = batch(obs, rotation_sigma_rad=turn_sigma)
    sigma = np.sqrt(np.diag(np.linalg.inv(np.einsum("nki,nkj->ij", jac, jac))))
    state = tracker.state
    # the turn noise modelled: chi2/dof 1.01, 1.01, 0.95 per component, far inside the 1 % tails (0.80-1.22 at
    # 240 dof; over seeds 50-61 the means are 0.99, 1.03, 0.96)
    assert state.noise is not None and state.noise.verdict == "consistent"
    assert 0.9 < state.noise.chi2 / state.noise.dof < 1.1
    np.testing.assert_allclose(np.sqrt(np.diag(state.covariance)), sigma, rtol=2e-3)
    _, plain = batch(obs)  # the same frames without the turn noise: narrower, so the lever matters
    plain_sigma = np.sqrt(np.diag(np.linalg.inv(np.einsum("nki,nkj->ij", plain, plain))))
    assert np.all(sigma[:3] > 1.05 * plain_sigma[:3])


def test_the_noise_test_reads_the_last_noise_window_frames() -> None:
    tracker = Tracker(SC.nominal_mount, SC.nominal_plane, TrackSettings(noise_window=40))
    run = feed(tracker, SC, 54, 100)
    nis = np.array([np.asarray(s.residual) ** 2 for _, s in run[-40:]]).sum(axis=0)
    state = tracker.state
    assert state.noise is not None and state.noise.dof == 40
    assert state.noise.chi2 == pytest.approx(nis.max(), rel=1e-9)


def test_the_change_test_divides_by_the_measured_noise_after_30_frames_capped_at_the_largest_scale() -> None:
    noisy = SC.with_arm_noise(1e-4, 0.0)
    for cap, seed in ((1.5, 55), (10.0, 56)):
        tracker = Tracker(SC.nominal_mount, SC.nominal_plane, TrackSettings(max_interval_scale=cap))
        used: list[np.ndarray] = []
        for t_s, obs in work(noisy, np.random.default_rng(seed), 60, dwell=10):
            step = tracker.update(t_s, obs)
            # no change detected (a detection would empty the noise window): the CUSUM stays below 86 of its 120
            assert step.event is None and tracker._cusum.statistic < 100.0
            if step.accepted:
                used.append(np.asarray(step.residual) ** 2)
            if len(used) < 30:
                assert tracker._noise_scale2() == 1.0  # fewer than 30 frames: the stated noise
            else:
                worst = float(np.mean(used[-900:], axis=0).max())  # the worst component's mean chi2
                assert tracker._noise_scale2() == pytest.approx(min(max(1.0, worst), cap**2), rel=1e-12)
        assert len(used) >= 40 and float(np.mean(used, axis=0).max()) > 2.25  # the cap of 1.5 was reached


# -------------------------------------------------------------------- the batch step
def test_every_30_accepted_frames_the_estimate_is_the_batch_fit() -> None:
    """Between batch steps the estimate is sequential (here up to 0.8 sigma off at 29 frames); at 30 and 60 it
    is the batch fit of every frame. A reference of 1000 keeps surprising frames from adding batch steps: the
    innovations' chi2 stay below 100 (3 dof: below 30 here), ten times below it."""
    tracker = Tracker(SC.nominal_mount, SC.nominal_plane,
                      TrackSettings(detector_reference=1000.0, detector_clip=2000.0, detector_threshold=1e4))
    obs: list[PlaneObservation] = []
    for k, (t_s, o) in enumerate(work(SC, np.random.default_rng(91), 60, dwell=10), start=1):
        step = tracker.update(t_s, o)
        assert step.accepted and step.chi2 < 100.0
        assert tracker._since_batch == k % 30  # accepted frames since the last batch step
        obs.append(o)
        if k in (30, 60):
            x_ref, jac = batch(obs)
            sigma = np.sqrt(np.diag(np.linalg.inv(np.einsum("nki,nkj->ij", jac, jac) + WEAK * np.eye(9))))
            assert np.all(np.abs(tracker._x - x_ref) < 1e-4 * sigma), k  # the estimate, unseen directions too


def test_without_iterations_nothing_is_estimated_and_nothing_fails() -> None:
    """``iterations = 0``: no Gauss-Newton step, so the frames are judged and counted but add no information."""
    tracker = Tracker(SC.nominal_mount, SC.nominal_plane, TrackSettings(iterations=0, relinearise_every=5))
    run = feed(tracker, SC, 92, 12)
    assert all(s.accepted for _, s in run) and tracker.frames_used == 12
    state = tracker.state
    assert not any(state.observable.values()) and np.all(state.parameters == 0.0)
    assert np.all(tracker._info == 0.0) and state.mount.is_close(SC.nominal_mount)
