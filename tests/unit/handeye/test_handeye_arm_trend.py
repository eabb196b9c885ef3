"""The arm's error in step with the pose: trend coefficients in the hand-eye intervals (ADR 0055)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from cellcal.core.handeye.arm_trend import TREND_PREFIX, arm_trend_terms, pose_coordinates
from cellcal.core.handeye.estimator import ArmAccuracy, estimate_mount
from cellcal.core.handeye.synthetic import observations, sim_scenario
from cellcal.devices.pose import Pose

#: An arm stated at 0.6 mm and 0.05 deg RMS (about the sim arm's, ADR 0055).
ACCURACY_M, ACCURACY_RAD = 0.6e-3, math.radians(0.05)


def test_pose_coordinates_are_centred_unit_rms_and_skip_what_the_plan_does_not_move() -> None:
    views = observations(sim_scenario(), None)
    coords, names = pose_coordinates([v.flange for v in views])
    assert names[-3:] == ["px", "py", "pz"] and all(n.startswith("r") for n in names[:-3])
    assert coords.shape == (8, len(names)) and len(names) >= 9
    np.testing.assert_allclose(coords.mean(axis=0), 0.0, atol=1e-12)
    np.testing.assert_allclose(np.sqrt(np.mean(coords**2, axis=0)), 1.0, rtol=1e-12)
    # a plan that only slides the flange along x and y: no turn, no height change, no trend there
    start = views[0].flange
    slid = [Pose(start.rotation, start.translation + np.array([dx, dy, 0.0]))
            for dx, dy in ((0.0, 0.0), (0.05, 0.0), (0.0, 0.05), (0.05, 0.05))]
    assert pose_coordinates(slid)[1] == ["px", "py"]


def test_trend_terms_share_the_stated_accuracy_among_the_coordinates() -> None:
    scenario = sim_scenario()
    views = observations(scenario, None)
    terms = arm_trend_terms(views, scenario.nominal_mount, 0.3e-3, 0.0)   # position only
    coords, names = pose_coordinates([v.flange for v in views])
    assert len(terms) == 3 * len(names) and {k.split("_")[2] for k in terms} == {"x", "y", "z"}
    # a shift along the base z moves each measured offset by its share times the coordinate, along the normal
    # (here the base z seen from the camera), and turns no normal
    sigma = 0.3e-3 / math.sqrt(3 * len(names))
    shifts = terms[f"{TREND_PREFIX}z_r33"]
    for k, (dn, dc) in enumerate(shifts):
        n_base = (views[k].flange @ scenario.nominal_mount).rotation_matrix @ views[k].normal
        assert np.linalg.norm(dn) == pytest.approx(0.0, abs=1e-15)
        assert dc == pytest.approx(sigma * coords[k, names.index("r33")] * n_base[2], rel=1e-9)
    assert arm_trend_terms(views, scenario.nominal_mount, 0.0, 0.0) == {}


def _estimate(views: list, trend: float, varying: float) -> tuple[np.ndarray, float]:
    scenario = sim_scenario()
    est = estimate_mount(views, scenario.nominal_mount, scenario.nominal_plane,
                         arm_accuracy=ArmAccuracy(ACCURACY_M, ACCURACY_RAD, "config", varying=varying, trend=trend))
    err = est.mount.translation - scenario.true_mount.translation
    return err / (est.z * est.translation_sigma_m), float(err[2])


def test_a_flange_error_in_step_with_the_tilt_is_inside_the_intervals_only_with_the_trend() -> None:
    scenario = sim_scenario()
    views = observations(scenario, np.random.default_rng(1))
    coords, names = pose_coordinates([v.flange for v in views])
    tilt = coords[:, names.index("r33")]   # the tool axis' z component: the cosine of its tilt
    # the reported flange 0.15 mm RMS too high, in step with the tilt (as a wrist joint's zero error puts it)
    bad = [dataclasses.replace(v, flange=Pose(v.flange.rotation, v.flange.translation - [0.0, 0.0, 1.5e-4 * t]))
           for v, t in zip(views, tilt, strict=True)]
    random_only, tz_error = _estimate(bad, trend=0.0, varying=0.5)
    assert tz_error == pytest.approx(3.94e-3, abs=0.3e-3)  # 0.15 mm of flange, 3.9 mm of mount along the axis
    assert abs(random_only[2]) > 1.15             # 1.23 half-widths: the random per-pose model misses it
    with_trend, _ = _estimate(bad, trend=0.5, varying=0.25)   # the defaults
    assert np.all(np.abs(with_trend) < 0.85)      # tz at 0.77 half-widths
    assert ArmAccuracy(ACCURACY_M, ACCURACY_RAD) == ArmAccuracy(ACCURACY_M, ACCURACY_RAD, varying=0.25, trend=0.5)
