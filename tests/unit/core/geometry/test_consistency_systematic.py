"""The poses' consistency and the consensus's interval with the camera's systematic error and the arm's accuracy.

Synthetic poses (no sim): the table is z = 0 in the base frame, eight camera poses look at it from
0.46 and 0.6 m and four azimuths, each pose's camera-frame plane is the true one seen through a
common 1 % depth-scale error (ranges 1 % long: the plane 1 % farther), and the arm's reported poses
err by a common part and a per-pose part. ADR 0055, "Poses combined".
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cellcal.core.calibration.config import look_at_pose
from cellcal.core.geometry.consistency import PosePlane, noise_shifts, plane_consistency
from cellcal.core.geometry.planes import Plane
from cellcal.devices.arm_model import ArmModel
from cellcal.devices.pose import Pose

TABLE = Plane(np.array([0.0, 0.0, 1.0]), 0.0)
#: 0.5 mm and 0.05 deg RMS: the sim's default [sim.arm_errors] (ADR 0055).
ARM = ArmModel(repeatability_m=1e-4, accuracy_m=5e-4, accuracy_rad=math.radians(0.05), source="test")
NOISE_RAD, NOISE_M = 2e-5, 2e-5


def cameras() -> list[Pose]:
    target = np.array([0.3, 0.0, 0.0])
    out = []
    for h in (0.46, 0.6):
        for yaw_deg in (-40.0, -15.0, 15.0, 40.0):
            about = (Pose(translation=target) @ Pose(Rotation.from_euler("z", yaw_deg, degrees=True))
                     @ Pose(translation=-target))
            out.append(about @ look_at_pose(target, np.array([0.0, 0.0, 1.0]), h, math.radians(75.0), "x"))
    return out


def arm_error(rng: np.random.Generator, position_m: float, rotation_rad: float) -> Pose:
    """An isotropic rigid error of RMS length ``position_m`` and angle ``rotation_rad`` (1-sigma per axis / sqrt 3)."""
    return Pose(Rotation.from_rotvec(rng.normal(0.0, rotation_rad / math.sqrt(3.0), 3)),
                rng.normal(0.0, position_m / math.sqrt(3.0), 3))


def poses(*, scale_error: float = 0.01, scale_allowance: float | None = 0.01, moved_m: float = 0.0,
          arm: ArmModel | None = ARM, seed: int = 3, total_sigmas: bool = False) -> list[PosePlane]:
    """The eight poses' planes as calibrate builds them.

    Args:
        scale_error: The camera's true depth-scale error (common to every pose).
        scale_allowance: Its stated 1-sigma allowance (the fit's "scale" shift; None: no shift stated).
        moved_m: The table raised by this for the poses at the two last azimuths of each height (a table
            moved in step with the heights would be a depth-scale error's pattern: ADR 0055).
        arm: The arm's true error: a common part of its accuracy and half of it per pose (None: exact).
        total_sigmas: Put the allowance into each pose's own sigmas as if independent (the total
            covariance of ADR 0059) and state no shifts.
    """
    rng = np.random.default_rng(seed)
    common = Pose() if arm is None else arm_error(rng, arm.accuracy_m, arm.accuracy_rad)
    out = []
    for i, true_cam in enumerate(cameras()):
        table = TABLE if i % 4 < 2 else Plane(TABLE.normal, TABLE.offset_m - moved_m)
        seen = table.transformed(true_cam.inv())  # the camera-frame plane, normal toward the camera
        d = float(seen.offset_m)
        measured = Plane(seen.normal, d * (1.0 + scale_error))  # ranges 1 % long: the plane 1 % farther
        vary = Pose() if arm is None else arm_error(rng, 0.5 * arm.accuracy_m, 0.5 * arm.accuracy_rad)
        reported = common @ vary @ true_cam  # where the arm says the camera was
        shifts = {} if scale_allowance is None else {"scale": (np.zeros(3), scale_allowance * d)}
        n_sigma, h_sigma = NOISE_RAD, NOISE_M
        if total_sigmas and scale_allowance is not None:
            h_sigma, shifts = math.hypot(NOISE_M, scale_allowance * d), {}
        out.append(PosePlane.from_camera(measured, reported, normal_sigma_rad=n_sigma, offset_sigma_m=h_sigma,
                                         shifts_cam=shifts))
    return out


def test_a_common_scale_error_is_consistent_and_a_moved_table_is_not() -> None:
    ok = plane_consistency(poses(), arm=ARM)
    assert ok.verdict == "consistent", ok.interpretation
    # the 1 % scale error moves the poses at 0.46 and 0.6 m apart by ~1.4 mm: a real spread, explained
    # by the differential part of the allowance (not by noise: 20 um)
    assert 1.0e-3 < ok.height_spread_m < 2.0e-3
    assert ok.expected_parts["systematic"][1] > 0.5e-3 and ok.expected_parts["noise"][1] < 3e-5
    assert ok.height_tolerance_m < 6e-3  # the differential part, not the full allowance (5.3 mm per pose)

    moved = plane_consistency(poses(moved_m=0.005), arm=ARM)
    assert moved.verdict == "inconsistent", moved.interpretation
    assert moved.height_spread_m > 5e-3 > moved.height_tolerance_m

    # without the allowance's shifts the same consistent cell is flagged (its spread is 'beyond the noise')
    bare = plane_consistency(poses(scale_allowance=None), arm=ARM)
    assert bare.verdict == "inconsistent"
    # with the allowance as if independent per pose (the total covariance) the moved table is not caught: blind
    blind = plane_consistency(poses(moved_m=0.005, total_sigmas=True), arm=ARM)
    assert blind.verdict == "consistent" and blind.height_tolerance_m > 20e-3


def test_the_arms_accuracy_does_not_flag_a_consistent_cell() -> None:
    exact_camera = dict(scale_error=0.0, scale_allowance=None)
    flagged = 0
    for seed in range(20):
        result = plane_consistency(poses(**exact_camera, seed=seed), arm=ARM)
        flagged += result.verdict == "inconsistent"
    assert flagged == 0
    # and a 5 mm moved table is caught through the arm's allowance
    assert plane_consistency(poses(**exact_camera, moved_m=0.005), arm=ARM).verdict == "inconsistent"


def test_the_consensus_interval_covers_a_common_error_within_the_allowance() -> None:
    covered = 0
    seeds = range(40)
    for seed in seeds:
        rng = np.random.default_rng(100 + seed)
        error = float(rng.normal(0.0, 0.01))  # a scale error drawn within the 1 % allowance
        r = plane_consistency(poses(scale_error=error, seed=seed), arm=ARM)
        assert r.consensus_height_sigma_m is not None and r.consensus_normal_sigma_rad is not None
        height = float(r.reference_point_m[2])  # the consensus's height above the true table where it is compared
        covered += abs(height) <= 1.96 * r.consensus_height_sigma_m
    assert covered >= 0.9 * len(seeds)
    r = plane_consistency(poses(), arm=ARM)
    # the parts: the allowance's mean shift (1 % of ~0.53 m), the arm's common accuracy (0.5 mm / sqrt 3)
    sys_h = r.consensus_parts["systematic"][1]
    assert sys_h == pytest.approx(0.01 * 0.53, rel=0.1)
    assert r.consensus_parts["arm"][1] == pytest.approx(math.hypot(5e-4 / math.sqrt(3.0), 0.0), rel=0.2)
    assert r.consensus_parts["noise"][1] < 2e-5
    d = r.to_dict()["consensus_interval"]
    assert d["height_halfwidth_m"] == pytest.approx(1.959964 * r.consensus_height_sigma_m)
    assert set(d["parts"]) == {"noise", "systematic", "arm"}


def test_noise_shifts_reads_both_forms() -> None:
    as_result = type("R", (), {"systematic_shifts": {"scale": (np.array([0.0, 1e-4, 0.0]), 2e-3)}})()
    as_json = {"systematic_shifts": {"scale": {"normal": [0.0, 1e-4, 0.0], "offset_m": 2e-3}}}
    for src in (as_result, as_json):
        got = noise_shifts(src)
        assert list(got) == ["scale"] and got["scale"][1] == 2e-3 and got["scale"][0][1] == 1e-4
    assert noise_shifts({}) == {} and noise_shifts(object()) == {}
