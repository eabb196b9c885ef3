"""A fixed camera's pose from a plate the arm shows it (issue #40): recovery, intervals, observability, plan."""

from __future__ import annotations

import json
import math
from collections.abc import Sequence

import numpy as np
import pytest
from look_at import look_at
from scipy.spatial.transform import Rotation

from cellcal.core.geometry.planes import Plane, tangent_basis
from cellcal.core.handeye import (
    FIXED_PARAMETERS,
    MeasuringPlaneView,
    PlaneObservation,
    estimate_fixed_camera,
    plate_poses,
)
from cellcal.core.handeye.estimator import ArmAccuracy
from cellcal.devices.errors import CalibrationError, CalibrationQualityError
from cellcal.devices.pose import Pose

#: Per view: 1-sigma of the normal across itself per axis (rad) and of the offset (m).
NORMAL_SIGMA, OFFSET_SIGMA = math.radians(0.035), 1e-4
#: The arm errs at random per pose by 0.5 mm / 0.05 deg RMS (the estimator told so: varying share 1).
ARM = ArmAccuracy(5e-4, math.radians(0.05), "test", varying=1.0, trend=0.0)
#: The measuring plane (the table, z = 0 in the base frame) and its base-frame covariance (tilts, rad; offset, m).
TABLE = Plane([0.0, 0.0, 1.0], 0.0)
TABLE_COV = np.diag([1e-4**2, 1e-4**2, 1e-4**2])


#: The camera: 1.3 m up and out, looking down at the arm's workspace; configured 0.9 deg and 20 mm off.
TRUE_CAMERA = look_at([1.0, 0.3, 0.9], [0.4, 0.0, 0.3])
NOMINAL_CAMERA = Pose(Rotation.from_rotvec([0.01, -0.008, 0.012]) * TRUE_CAMERA.rotation,
                      TRUE_CAMERA.translation + np.array([0.012, -0.015, 0.008]))
#: The plate 50 mm ahead of the flange along its z as configured, 0.4 deg tilted and 2 mm thicker in truth.
NOMINAL_PLATE = Plane([0.0, 0.0, 1.0], -0.05)
TRUE_PLATE = Plane([0.005, -0.004, 1.0], -0.052)


def plate_views(flanges: Sequence[Pose], rng: np.random.Generator | None, *, arm: ArmAccuracy | None = None,
                plate: Plane = TRUE_PLATE) -> list[PlaneObservation]:
    """The plate as the true camera sees it from each flange pose (``rng=None``: no noise).

    The noise is drawn from each view's covariance (its Cholesky factor across the normal); with
    ``arm`` each flange is off at random by its accuracy while the observation reports the pose asked.
    """
    out = []
    for flange in flanges:
        true_flange = flange
        if rng is not None and arm is not None:
            turn = Rotation.from_rotvec(rng.normal(0.0, arm.rotation_rad / math.sqrt(3), 3))  # about base axes
            shift = rng.normal(0.0, arm.position_m / math.sqrt(3), 3)  # base frame, m
            true_flange = Pose(turn * flange.rotation, flange.translation + shift)
        seen = plate.transformed(TRUE_CAMERA.inv() @ true_flange).oriented_toward_origin()
        out.append(_observed(flange, seen, rng))
    return out


def _observed(flange: Pose, seen: Plane, rng: np.random.Generator | None) -> PlaneObservation:
    """A view of the camera-frame plane ``seen`` with its covariance and (with ``rng``) noise drawn from it."""
    basis = tangent_basis(seen.normal)
    m = np.zeros((4, 3))
    m[:3, :2] = basis
    m[3, 2] = 1.0
    c3 = np.diag([NORMAL_SIGMA**2, NORMAL_SIGMA**2, OFFSET_SIGMA**2])
    c3[0, 2] = c3[2, 0] = 0.2 * NORMAL_SIGMA * OFFSET_SIGMA  # a little normal-offset correlation
    normal, offset = np.array(seen.normal), seen.offset_m
    if rng is not None:
        step = np.linalg.cholesky(c3) @ rng.standard_normal(3)
        normal = normal + basis @ step[:2]
        normal /= np.linalg.norm(normal)
        offset += step[2]
    return PlaneObservation(flange, normal, offset, m @ c3 @ m.T)


def table_view(rng: np.random.Generator | None) -> MeasuringPlaneView:
    """The table as the true camera sees it, with its base-frame covariance."""
    obs = _observed(Pose.identity(), TABLE.transformed(TRUE_CAMERA.inv()).oriented_toward_origin(), rng)
    return MeasuringPlaneView(obs.normal, obs.offset_m, obs.covariance, TABLE, TABLE_COV)


def default_plan() -> list[Pose]:
    """The default plate plan at 0.6 m (17 poses)."""
    flanges: list[Pose] = plate_poses(TRUE_CAMERA, distance_m=0.6, plate_flange=NOMINAL_PLATE)
    return flanges


def truth_steps() -> np.ndarray:
    """The truth as the estimator's parameters: camera turn and shift from the nominal (base frame)."""
    turn = (TRUE_CAMERA.rotation * NOMINAL_CAMERA.rotation.inv()).as_rotvec()
    return np.concatenate([turn, TRUE_CAMERA.translation - NOMINAL_CAMERA.translation])


def assert_same_plane(a: Plane, b: Plane, atol: float) -> None:
    np.testing.assert_allclose(a.normal, b.normal, atol=atol)
    assert a.offset_m == pytest.approx(b.offset_m, abs=atol)


def test_noise_free_views_give_the_truth_with_the_plate_estimated() -> None:
    flanges = default_plan()
    est = estimate_fixed_camera(plate_views(flanges, None), NOMINAL_CAMERA, NOMINAL_PLATE)
    assert est.camera_base.distance_to(TRUE_CAMERA) < 1e-9 and est.camera_base.angle_to(TRUE_CAMERA) < 1e-9
    assert_same_plane(est.plate_flange, TRUE_PLATE, 1e-9)
    assert est.chi2 < 1e-12 and est.dof == 3 * len(flanges) - 9 and est.plate == "estimated"
    assert est.covariance.shape == (6, 6) and est.plate_covariance is not None and est.plate_covariance.shape == (3, 3)
    assert set(est.half_widths) == set(FIXED_PARAMETERS)
    assert all(r.normal_rad < 1e-9 and abs(r.offset_m) < 1e-9 and r.chi2 < 1e-12 for r in est.residuals)
    assert est.measuring_residual is None and est.observability.rank == 9
    document = json.loads(json.dumps(est.to_dict()))  # JSON form, SI units
    assert document["parameters"] == list(FIXED_PARAMETERS) and document["plate"] == "estimated"
    rpy, rpy_sigma = est.rpy_and_sigma_deg()
    np.testing.assert_allclose(rpy, np.degrees(TRUE_CAMERA.as_xyz_rpy()[3:]), atol=1e-7)
    assert np.all(rpy_sigma > 0)


def test_noise_free_views_give_the_truth_with_the_plate_given() -> None:
    flanges = default_plan()
    est = estimate_fixed_camera(plate_views(flanges, None), NOMINAL_CAMERA, TRUE_PLATE, estimate_plate=False)
    assert est.camera_base.distance_to(TRUE_CAMERA) < 1e-9 and est.camera_base.angle_to(TRUE_CAMERA) < 1e-9
    assert est.plate == "exact" and est.plate_covariance is None and est.dof == 3 * len(flanges) - 6
    assert set(est.half_widths) == set(FIXED_PARAMETERS[:6])
    assert any("held exact" in note for note in est.notes)


def test_noisy_views_with_arm_errors_are_within_four_sigma() -> None:
    flanges = default_plan()
    for seed in (1, 2, 3):
        rng = np.random.default_rng([40, seed])
        est = estimate_fixed_camera(plate_views(flanges, rng, arm=ARM), NOMINAL_CAMERA, NOMINAL_PLATE,
                                    arm_accuracy=ARM)
        error = est.parameters[:6] - truth_steps()
        assert np.all(np.abs(error) < 4 * est.sigma), (seed, error / est.sigma)
        # the targets: 0.05 deg and 0.5 mm are the size of a 1.5-sigma error of this plan, so 4 sigma here
        assert math.degrees(est.camera_base.angle_to(TRUE_CAMERA)) < 0.1
        assert est.noise.verdict in ("consistent", "scaled") and 0.2 < est.chi2_per_dof < 3.0
        # the per-pose arm error widens every camera interval against the views' noise alone
        plain = estimate_fixed_camera(plate_views(flanges, np.random.default_rng([40, seed])), NOMINAL_CAMERA,
                                      NOMINAL_PLATE)
        assert np.all(est.sigma > plain.sigma)
    assert est.arm_common_covariance is not None and est.arm_common_covariance.shape == (6, 6)
    assert np.all(np.sqrt(np.diag(est.arm_common_covariance))[3:] >= ARM.position_m / math.sqrt(3))
    assert any("arm's accuracy (0.5 mm" in note for note in est.notes)


def test_a_given_plate_with_a_prior_widens_the_intervals() -> None:
    flanges = default_plan()
    views = plate_views(flanges, np.random.default_rng(7))
    exact = estimate_fixed_camera(views, NOMINAL_CAMERA, TRUE_PLATE, estimate_plate=False)
    prior = estimate_fixed_camera(views, NOMINAL_CAMERA, TRUE_PLATE, estimate_plate=False,
                                  plate_sigma=(math.radians(0.5), math.radians(0.5), 2e-3))
    free = estimate_fixed_camera(views, NOMINAL_CAMERA, TRUE_PLATE)
    assert prior.plate == "prior" and prior.plate_covariance is not None and prior.dof == exact.dof
    assert np.all(prior.sigma >= exact.sigma * (1 - 1e-9)) and np.all(prior.sigma <= free.sigma * (1 + 1e-9))
    assert prior.sigma[5] > 1.5 * exact.sigma[5]  # tz trades with the plate's offset
    assert any("prior plate_sigma" in note for note in prior.notes)


def test_a_wrong_given_plate_is_refused_by_the_noise_test() -> None:
    views = plate_views(default_plan(), np.random.default_rng(8))
    with pytest.raises(CalibrationQualityError, match="'noise_model' failed"):  # 3 mm, 1 deg off: ~30x the noise
        estimate_fixed_camera(views, NOMINAL_CAMERA, Plane([0.0, 0.017, 1.0], -0.055), estimate_plate=False)


def test_the_noise_test_scales_understated_noise_and_flags_overstated_noise() -> None:
    flanges = default_plan()
    rng = np.random.default_rng(9)
    views = plate_views(flanges, rng)
    under = [PlaneObservation(v.flange, v.normal, v.offset_m, v.covariance / 9.0) for v in views]  # sigma / 3
    est = estimate_fixed_camera(under, NOMINAL_CAMERA, NOMINAL_PLATE)
    assert est.noise.verdict == "scaled" and 2.0 < est.noise.interval_scale < 4.5
    assert any("scaled by" in note for note in est.notes)
    over = [PlaneObservation(v.flange, v.normal, v.offset_m, v.covariance * 25.0) for v in views]  # sigma x 5
    est = estimate_fixed_camera(over, NOMINAL_CAMERA, NOMINAL_PLATE)
    assert est.noise.verdict == "too_good" and est.noise.interval_scale == 1.0
    assert any("suspect" in note for note in est.notes)
    with pytest.raises(CalibrationQualityError, match="'noise_model' failed"):  # sigma / 30: 30x the noise
        estimate_fixed_camera([PlaneObservation(v.flange, v.normal, v.offset_m, v.covariance / 900.0)
                               for v in views], NOMINAL_CAMERA, NOMINAL_PLATE)


def one_axis_plan() -> list[Pose]:
    """The plate tilted about the camera's y axis only: its normals lie in one plane of directions.

    The translation along the camera's y axis, which points down and away, is then unseen; the table sees it
    (tilted about the camera's x axis, the unseen axis would be horizontal: parallel to the table too).
    """
    flanges: list[Pose] = plate_poses(TRUE_CAMERA, distance_m=0.6, plate_flange=NOMINAL_PLATE,
                                      tilts_deg=(0.0, 20.0, 30.0), azimuths_deg=(90.0, 270.0))
    return flanges


def test_normals_in_one_plane_leave_a_translation_unseen() -> None:
    views = plate_views(one_axis_plan(), None)
    y = TRUE_CAMERA.rotation_matrix[:, 1]  # the camera's y axis in the base frame: (0.60, 0.30, -0.75)
    assert np.allclose(-y, [-0.60, -0.30, 0.75], atol=0.005)  # named as a line: largest component positive
    with pytest.raises(CalibrationQualityError, match=r"'observability' failed: 8 vs threshold 9; cannot see 1 "
                       r"of 9 parameters: camera translation along base \(-0\.60,-0\.30,0\.75\) \(parallel to "
                       r"the plate at every pose\): tilt the plate toward that axis .* measuring plane"):
        estimate_fixed_camera(views, NOMINAL_CAMERA, NOMINAL_PLATE)


def test_the_measuring_plane_makes_a_one_axis_plan_observable() -> None:
    views = plate_views(one_axis_plan(), None)
    est = estimate_fixed_camera(views, NOMINAL_CAMERA, NOMINAL_PLATE, measuring_plane=table_view(None))
    assert est.camera_base.distance_to(TRUE_CAMERA) < 1e-9 and est.camera_base.angle_to(TRUE_CAMERA) < 1e-9
    assert est.observability.observable and est.observability.n_views == len(views) + 1
    assert est.measuring_residual is not None and est.measuring_residual.chi2 < 1e-12
    assert est.dof == 3 * (len(views) + 1) - 9
    # with noise the unseen translation now rests on the table: 0.1 mm in its offset, a few mm of interval
    noisy = estimate_fixed_camera(plate_views(one_axis_plan(), np.random.default_rng(4)), NOMINAL_CAMERA,
                                  NOMINAL_PLATE, measuring_plane=table_view(np.random.default_rng(5)))
    error = noisy.parameters[:6] - truth_steps()
    assert np.all(np.abs(error) < 4 * noisy.sigma)
    assert any("measuring plane" in note for note in noisy.notes)


def test_the_same_normal_at_every_pose_sees_three_parameters() -> None:
    first = default_plan()[0]  # face-on; then shifted in the plate's plane and along the optical axis
    flanges = [first.with_translation(first.translation + step) for step in
               ([0.0, 0.0, 0.0], [0.05, 0.0, 0.0], [0.0, 0.05, 0.0], [0.0, 0.0, 0.05], [0.03, -0.04, 0.02])]
    views = plate_views(flanges, None)
    with pytest.raises(CalibrationQualityError, match=r"3 vs threshold 6; cannot see 3 of 6 parameters: camera "
                       r"rotation about base \(.*\) \(the plate normal\): tilt the plate about a second axis; camera "
                       r"translation across .* \(parallel to the plate at every pose\)"):
        estimate_fixed_camera(views, NOMINAL_CAMERA, TRUE_PLATE, estimate_plate=False)
    with pytest.raises(CalibrationQualityError, match=r"cannot see 4 of 9 parameters: camera rotation about base "
                       r"\(.*\) \(the plate normal\).* vs the plate's offset: show the plate at more flange"):
        estimate_fixed_camera(views, NOMINAL_CAMERA, NOMINAL_PLATE)


def test_fewer_than_three_views_are_refused() -> None:
    views = plate_views(default_plan()[1:3], None)
    with pytest.raises(CalibrationQualityError, match=r"2 plane view\(s\) cannot fix 6 parameters \(show the plate "
                       r"at 3 or more orientations"):
        estimate_fixed_camera(views, NOMINAL_CAMERA, TRUE_PLATE, estimate_plate=False)
    # two plate views and the table are three planes: enough for a given plate
    est = estimate_fixed_camera(views, NOMINAL_CAMERA, TRUE_PLATE, estimate_plate=False,
                                measuring_plane=table_view(None))
    assert est.camera_base.distance_to(TRUE_CAMERA) < 1e-9 and est.dof == 3


def test_bad_inputs_are_one_line_errors() -> None:
    views = plate_views(default_plan(), None)
    v = views[0]
    cases: list[tuple[dict[str, object], list[PlaneObservation], str]] = [
        ({}, [], "no plate views"),
        ({}, [PlaneObservation(v.flange, 2 * v.normal, v.offset_m, v.covariance), *views[1:]], "unit 3-vector"),
        ({}, [PlaneObservation(v.flange, v.normal, v.offset_m, np.eye(3)), *views[1:]], "4x4"),
        ({}, [PlaneObservation(v.flange, v.normal, v.offset_m, np.zeros((4, 4))), *views[1:]],
         "not positive definite"),
        ({}, [*views, PlaneObservation(v.flange, -v.normal, -v.offset_m, v.covariance)], "other face"),
        ({"plate_sigma": (1e-3, 1e-3, 1e-3)}, views, "estimate_plate=False"),
        ({"plate_sigma": (1e-3, -1e-3, 1e-3), "estimate_plate": False}, views, "3 finite numbers > 0"),
        ({"confidence": 1.5}, views, "confidence must be in"),
        ({"arm_accuracy": ArmAccuracy(-1e-3, 0.0)}, views, "finite and >= 0"),
        ({"measuring_plane": MeasuringPlaneView(v.normal, v.offset_m, v.covariance, TABLE, np.eye(2))}, views,
         "finite 3x3 positive"),
    ]
    for options, observations, message in cases:
        with pytest.raises(CalibrationError, match=message) as caught:
            estimate_fixed_camera(observations, NOMINAL_CAMERA, NOMINAL_PLATE, **options)  # type: ignore[arg-type]
        assert "\n" not in str(caught.value) and not isinstance(caught.value, CalibrationQualityError)


def test_the_plate_normal_configured_the_other_way_is_turned_round() -> None:
    flipped = Plane(-NOMINAL_PLATE.normal, -NOMINAL_PLATE.offset_m)
    est = estimate_fixed_camera(plate_views(default_plan(), None), NOMINAL_CAMERA, flipped)
    assert est.camera_base.distance_to(TRUE_CAMERA) < 1e-9
    assert_same_plane(est.plate_flange, TRUE_PLATE, 1e-9)


@pytest.mark.parametrize("tilts", [(0.0, 20.0, 30.0), (10.0, 45.0)])
def test_plate_poses_put_the_plate_centre_on_the_axis_facing_the_camera(tilts: tuple[float, ...]) -> None:
    centre = np.array([0.02, -0.01, 0.05])  # on the plate z = 0.05 of the flange
    azimuths = (0.0, 90.0, 180.0, 270.0)
    flanges = plate_poses(TRUE_CAMERA, distance_m=0.7, plate_flange=NOMINAL_PLATE, tilts_deg=tilts,
                          azimuths_deg=azimuths, plate_centre_flange_m=centre)
    faces = [(t, a) for t in tilts for a in (azimuths if t > 0 else azimuths[:1])]
    assert len(flanges) == len(faces)
    target = TRUE_CAMERA.apply([0.0, 0.0, 0.7])  # on the optical axis at 0.7 m
    normals = []
    for flange, (tilt, _) in zip(flanges, faces, strict=True):
        np.testing.assert_allclose(flange.apply(centre), target, atol=1e-12)
        normal = flange.apply_vector(NOMINAL_PLATE.normal)
        to_camera = (TRUE_CAMERA.translation - target) / 0.7
        assert float(normal @ to_camera) == pytest.approx(math.cos(math.radians(tilt)), abs=1e-12)  # faces it
        assert NOMINAL_PLATE.transformed(TRUE_CAMERA.inv() @ flange).offset_m > 0  # the camera on its front
        normals.append(normal)
    assert np.linalg.matrix_rank(np.array(normals), tol=1e-3) == 3  # normals out of one plane of directions
    # the flange's roll about the plate normal is varied pose by pose (0, 90, -90, 180 deg in turn)
    turns = [flanges[0].rotation_matrix.T @ f.rotation_matrix for f in flanges[1:4]]
    assert max(math.degrees(math.acos(np.clip((np.trace(t) - 1) / 2, -1, 1))) for t in turns) > 80


def test_plate_poses_refuse_bad_arguments() -> None:
    with pytest.raises(CalibrationError, match="distance_m"):
        plate_poses(TRUE_CAMERA, distance_m=0.0, plate_flange=NOMINAL_PLATE)
    with pytest.raises(CalibrationError, match=r"tilts in \[0, 80\)"):
        plate_poses(TRUE_CAMERA, distance_m=0.6, plate_flange=NOMINAL_PLATE, tilts_deg=(85.0,))
    with pytest.raises(CalibrationError, match="10 mm off the plate"):
        plate_poses(TRUE_CAMERA, distance_m=0.6, plate_flange=NOMINAL_PLATE, plate_centre_flange_m=[0, 0, 0.06])


@pytest.mark.statistical
def test_intervals_hold_the_truth_95_percent_of_the_time() -> None:
    flanges = default_plan()
    truth = truth_steps()
    inside = []
    for seed in range(200):
        rng = np.random.default_rng([40, 1000 + seed])
        est = estimate_fixed_camera(plate_views(flanges, rng, arm=ARM), NOMINAL_CAMERA, NOMINAL_PLATE,
                                    arm_accuracy=ARM, max_interval_scale=math.inf)
        inside.append(np.abs(est.parameters[:6] - truth) <= est.z * est.sigma)
    rate = float(np.mean(inside))  # 1200 intervals: 95 % +- 0.6 % (1 s.e.)
    assert 0.90 <= rate <= 0.99, rate
