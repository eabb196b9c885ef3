"""Poses with covariance (first order against seeded Monte Carlo) and the cameras' plane-agreement check (#40)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from cellcal.core.geometry import PoseWithCovariance, plane_agreement, relative_pose
from cellcal.core.geometry.planes import Plane
from cellcal.core.geometry.relative import inverse_jacobian, perturb
from cellcal.core.handeye.model import PlaneModel
from cellcal.devices.errors import CalibrationError
from cellcal.devices.pose import Pose

FloatArray = NDArray[np.float64]

#: Monte Carlo draws per check; a covariance entry's sampling error is then <= 1 % of the diagonal scale.
DRAWS = 20000
#: Tolerance of a Monte Carlo covariance entry, relative to sqrt(C_ii C_jj) of the propagated one.
MC_TOLERANCE = 0.05

FLANGE = Pose.from_xyz_rpy([0.42, -0.18, 0.55], np.radians([172.0, 8.0, 35.0]))  # T_base_flange
MOUNT = Pose.from_xyz_rpy([0.04, -0.01, 0.09], np.radians([2.0, -1.0, 90.0]))  # T_flange_camera
FIXED = Pose.from_xyz_rpy([1.2, 0.35, 0.95], np.radians([-140.0, 5.0, 160.0]))  # T_base_camera


def random_covariance(rng: np.random.Generator, sigma_rad: float, sigma_m: float) -> FloatArray:
    """A 6x6 covariance with correlations, 1-sigma about ``sigma_rad`` (turns) and ``sigma_m`` (shifts)."""
    a = rng.normal(size=(6, 6))
    corr = a @ a.T + 2.0 * np.eye(6)
    d = np.sqrt(np.diag(corr))
    scale = np.array([sigma_rad] * 3 + [sigma_m] * 3) * rng.uniform(0.5, 1.5, 6)
    out: FloatArray = corr / np.outer(d, d) * np.outer(scale, scale)
    return out


def draws(rng: np.random.Generator, cov: FloatArray, n: int = DRAWS) -> FloatArray:
    """``n`` steps (n, k) of covariance ``cov``."""
    out: FloatArray = rng.normal(size=(n, cov.shape[0])) @ np.linalg.cholesky(cov).T
    return out


def moved(pose: Pose, steps: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Rotation matrices (n, 3, 3) and translations (n, 3) of ``pose`` moved by each step (left turn, shift)."""
    rot = (Rotation.from_rotvec(steps[:, :3]) * pose.rotation).as_matrix()
    return rot, pose.translation + steps[:, 3:]


def steps_of(rot: FloatArray, t: FloatArray, nominal: Pose) -> FloatArray:
    """The steps (n, 6) that move ``nominal`` to the poses (rot, t)."""
    phi = Rotation.from_matrix(rot @ nominal.rotation_matrix.T).as_rotvec()
    return np.column_stack([phi, t - nominal.translation])


def assert_matches_mc(propagated: FloatArray, sample_steps: FloatArray) -> None:
    """Every entry of the sample covariance within MC_TOLERANCE of sqrt(C_ii C_jj) of the propagated one."""
    empirical = np.cov(sample_steps, rowvar=False)
    scale = np.sqrt(np.outer(np.diag(propagated), np.diag(propagated)))
    worst = float(np.max(np.abs(empirical - propagated) / scale))
    assert worst < MC_TOLERANCE, worst


def one_line(err: pytest.ExceptionInfo[CalibrationError]) -> str:
    text = str(err.value)
    assert "\n" not in text and text
    return text


# ---------------------------------------------------------------------------------------------------- poses
def test_the_parameterisation_is_the_hand_eye_mounts() -> None:
    # PlaneModel.mount turns about the flange axes (left) and shifts in the flange frame: perturb does the same
    step = np.array([0.01, -0.02, 0.015, 0.003, -0.002, 0.004])
    model = PlaneModel(MOUNT, Plane(np.array([0.0, 0.0, 1.0]), 0.1))
    assert perturb(MOUNT, step).is_close(model.mount(np.concatenate([step, np.zeros(3)])), atol_m=1e-15,
                                         atol_rad=1e-14)


def test_algebra_inverse_identity_associativity() -> None:
    rng = np.random.default_rng(1)
    a, b, c = (PoseWithCovariance(p, random_covariance(rng, 2e-3, 1e-3)) for p in (FLANGE, MOUNT, FIXED))
    # a^-1^-1 = a, covariance included (the inverse's Jacobian is its own inverse)
    back = a.inverse().inverse()
    assert back.pose.is_close(a.pose, atol_m=1e-15, atol_rad=1e-15)
    np.testing.assert_allclose(back.covariance, a.covariance, rtol=0, atol=1e-12 * np.max(a.covariance))
    # the exact identity on either side changes nothing
    ident = PoseWithCovariance.exact(Pose.identity())
    for composed in (ident.compose(a), a.compose(ident)):
        assert composed.pose.is_close(a.pose, atol_m=1e-15, atol_rad=1e-15)
        np.testing.assert_allclose(composed.covariance, a.covariance, rtol=0, atol=1e-18)
    # (a b) c = a (b c) for independent poses, to rounding
    left, right = a.compose(b).compose(c), a.compose(b.compose(c))
    assert left.pose.is_close(right.pose, atol_m=1e-14, atol_rad=1e-14)
    np.testing.assert_allclose(left.covariance, right.covariance, rtol=0, atol=1e-12 * np.max(left.covariance))


def test_a_with_its_own_inverse_is_the_exact_identity() -> None:
    rng = np.random.default_rng(2)
    a = PoseWithCovariance(FIXED, random_covariance(rng, 2e-3, 1e-3))
    # a @ a^-1 with the inverse's errors those of a (cross-covariance Cov(da, J da) = C J^T): no error at all
    same = a.compose(a.inverse(), cross_covariance=a.covariance @ inverse_jacobian(a.pose).T)
    assert same.pose.is_close(Pose.identity(), atol_m=1e-12, atol_rad=1e-12)
    assert np.max(np.abs(same.covariance)) < 1e-12
    # a camera relative to itself: a^-1 @ a, the cross-covariance its own covariance
    rel = relative_pose(a, a, cross_covariance=a.covariance)
    assert rel.pose.is_close(Pose.identity(), atol_m=1e-12, atol_rad=1e-12)
    assert np.max(np.abs(rel.covariance)) < 1e-12
    # independent copies: the variances add (a^-1 a's covariance is twice a's seen in a's own frame)
    indep = relative_pose(a, a)
    assert np.all(np.diag(indep.covariance) > 0.5 * np.min(np.diag(a.covariance)))


def test_inverse_and_compose_match_monte_carlo() -> None:
    rng = np.random.default_rng(3)
    a = PoseWithCovariance(FLANGE, random_covariance(rng, 3e-3, 2e-3))
    b = PoseWithCovariance(MOUNT, random_covariance(rng, 5e-3, 1e-3))
    da, db = draws(rng, a.covariance), draws(rng, b.covariance)
    rot_a, t_a = moved(a.pose, da)
    rot_b, t_b = moved(b.pose, db)
    # inverse: R^T, -R^T t
    inv = a.inverse()
    rot_i = np.transpose(rot_a, (0, 2, 1))
    assert_matches_mc(inv.covariance, steps_of(rot_i, -np.einsum("nij,nj->ni", rot_i, t_a), inv.pose))
    # composition of independent poses: R_a R_b, R_a t_b + t_a
    ab = a.compose(b)
    assert_matches_mc(ab.covariance, steps_of(rot_a @ rot_b, np.einsum("nij,nj->ni", rot_a, t_b) + t_a, ab.pose))


def test_relative_pose_with_correlated_cameras_matches_monte_carlo() -> None:
    rng = np.random.default_rng(4)
    joint = random_covariance(rng, 2e-3, 1e-3)
    joint = np.block([[joint, 0.6 * joint], [0.6 * joint, joint]])  # both cameras share part of their error
    joint[6:, 6:] += random_covariance(rng, 1e-3, 1e-3)
    a = PoseWithCovariance(FIXED, joint[:6, :6])
    b = PoseWithCovariance(FLANGE @ MOUNT, joint[6:, 6:])
    rel = relative_pose(a, b, cross_covariance=joint[:6, 6:])
    assert rel.pose.is_close(FIXED.inv() @ FLANGE @ MOUNT, atol_m=1e-14, atol_rad=1e-14)
    d = draws(rng, joint)
    rot_a, t_a = moved(a.pose, d[:, :6])
    rot_b, t_b = moved(b.pose, d[:, 6:])
    rot_at = np.transpose(rot_a, (0, 2, 1))  # a^-1 b: R_a^T R_b, R_a^T (t_b - t_a)
    assert_matches_mc(rel.covariance, steps_of(rot_at @ rot_b, np.einsum("nij,nj->ni", rot_at, t_b - t_a), rel.pose))
    # ignoring the shared part overstates the relative pose's variances here
    assert np.all(np.diag(relative_pose(a, b).covariance) > np.diag(rel.covariance))


def test_camera_on_the_flange_at_a_flange_pose_matches_monte_carlo() -> None:
    rng = np.random.default_rng(5)
    mount = PoseWithCovariance(MOUNT, random_covariance(rng, 4e-3, 1.5e-3))
    flange_cov = random_covariance(rng, 1e-3, 5e-4)
    cam = mount.at_flange(FLANGE, flange_cov)
    assert cam.pose.is_close(FLANGE @ MOUNT, atol_m=1e-15, atol_rad=1e-15)
    rot_f, t_f = moved(FLANGE, draws(rng, flange_cov))
    rot_m, t_m = moved(MOUNT, draws(rng, mount.covariance))
    assert_matches_mc(cam.covariance, steps_of(rot_f @ rot_m, np.einsum("nij,nj->ni", rot_f, t_m) + t_f, cam.pose))
    # an exact flange: the mount's turn seen about the base axes, its lever swung by it
    exact = mount.at_flange(FLANGE)
    r = FLANGE.rotation_matrix
    np.testing.assert_allclose(exact.covariance[:3, :3], r @ mount.covariance[:3, :3] @ r.T, rtol=1e-12, atol=0)


def test_half_widths() -> None:
    cov = np.diag([1e-6, 4e-6, 9e-6, 1e-8, 4e-8, 2.5e-7])
    rot, shift = PoseWithCovariance(MOUNT, cov).half_widths(0.95)
    np.testing.assert_allclose(rot, 1.959963984540054 * np.array([1e-3, 2e-3, 3e-3]), rtol=1e-12)
    np.testing.assert_allclose(shift, 1.959963984540054 * np.array([1e-4, 2e-4, 5e-4]), rtol=1e-12)
    rot99, _ = PoseWithCovariance(MOUNT, cov).half_widths(0.99)
    np.testing.assert_allclose(rot99[0], 2.5758293035489 * 1e-3, rtol=1e-12)
    with pytest.raises(CalibrationError, match="confidence"):
        PoseWithCovariance(MOUNT, cov).half_widths(1.0)


@pytest.mark.parametrize(("cov", "words"), [
    (np.eye(5), "must be 6x6"),
    (np.full((6, 6), np.nan), "must be finite"),
    (np.eye(6) + np.triu(np.full((6, 6), 1e-3), 1), "must be symmetric"),
    (np.diag([1e-6, 1e-6, 1e-6, 1e-6, 1e-6, -1e-7]), "positive semi-definite"),
    ("x", "matrix of numbers"),
])
def test_bad_pose_covariance_is_one_clear_error(cov: object, words: str) -> None:
    with pytest.raises(CalibrationError) as err:
        PoseWithCovariance(MOUNT, cov)  # type: ignore[arg-type]
    assert words in one_line(err) and "pose covariance" in str(err.value)


def test_bad_cross_covariance_is_one_clear_error() -> None:
    a = PoseWithCovariance(FIXED, np.eye(6) * 1e-6)
    with pytest.raises(CalibrationError) as err:
        relative_pose(a, a, cross_covariance=np.eye(6) * 2e-6)  # a correlation of 2: impossible
    assert "positive semi-definite" in one_line(err)
    assert PoseWithCovariance(FIXED, np.zeros((6, 6))).half_widths()[0].tolist() == [0.0, 0.0, 0.0]


# ---------------------------------------------------------------------------------------------------- planes
#: The measuring plane in the base frame: slightly tilted, 4 cm below the base origin.
TRUE_PLANE = Plane(np.array([0.015, -0.01, 1.0]), 0.04)
#: Per camera: 1-sigma of its tilts (rad) and offset (m), and the tilt-offset correlation (its lever).
CAMERAS = {"flange": (2e-4, 1.5e-4, 0.3), "fixed_45": (6e-4, 8e-4, -0.5),
           "fixed_top": (3e-4, 4e-4, 0.6), "fixed_side": (1e-3, 6e-4, 0.2)}
FLIP = np.diag([1.0, -1.0, -1.0])  # the step's coordinates of the same plane given with -n, -c


def plane_covariance(sigma_rad: float, sigma_m: float, rho: float) -> FloatArray:
    """3x3 of (tilt a, tilt b, rad; offset, m) with the first tilt correlated with the offset."""
    s = np.array([sigma_rad, 1.3 * sigma_rad, sigma_m])
    corr = np.array([[1.0, 0.1, rho], [0.1, 1.0, 0.0], [rho, 0.0, 1.0]])
    out: FloatArray = corr * np.outer(s, s)
    return out


def camera_planes(rng: np.random.Generator, names: tuple[str, ...] = tuple(CAMERAS), *,
                  shifted: dict[str, float] | None = None, flipped: tuple[str, ...] = ("fixed_side",)
                  ) -> dict[str, tuple[Plane, FloatArray]]:
    """Each camera's estimate, drawn from its covariance as the hand-eye model moves the plane.

    ``shifted``: the camera's offset moved by that many of its sigmas; ``flipped``: reported with -n, -c.
    """
    out = {}
    model = PlaneModel(MOUNT, TRUE_PLANE)
    for name in names:
        cov = plane_covariance(*CAMERAS[name])
        step = rng.normal(size=3) @ np.linalg.cholesky(cov).T
        step[2] += (shifted or {}).get(name, 0.0) * math.sqrt(cov[2, 2])
        plane = model.plane(np.concatenate([np.zeros(6), step]))
        if name in flipped:
            plane, cov = Plane(-plane.normal, -plane.offset_m), FLIP @ cov @ FLIP
        out[name] = (plane, cov)
    return out


def test_agreeing_planes_pass() -> None:
    result = plane_agreement(camera_planes(np.random.default_rng(11)))
    assert result.agree and result.outlier is None and result.dof == 9
    assert result.p_value > 0.3  # far from the 0.05 threshold
    assert len(result.pairs) == 6 and max(p.chi2 for p in result.pairs) < 7.8  # chi2(3) at 0.95: 7.81
    assert max(p.angle_rad for p in result.pairs) < math.radians(0.2)
    assert result.message().startswith("the 4 cameras' planes agree")


def test_false_alarms_at_the_stated_level_and_chi2_mean() -> None:
    # 400 seeded trials of agreeing cameras (one given from the other side): the joint test fails ~5 % of them
    rng = np.random.default_rng(12)
    results = [plane_agreement(camera_planes(rng)) for _ in range(400)]
    rate = float(np.mean([not r.agree for r in results]))
    assert 0.02 < rate < 0.09, rate
    pair_mean = float(np.mean([p.chi2 for r in results for p in r.pairs]))
    assert 2.7 < pair_mean < 3.3, pair_mean  # chi2 with 3 dof: mean 3
    assert abs(float(np.mean([r.chi2 for r in results])) - 9.0) < 0.6


def test_the_orientation_of_a_plane_does_not_matter() -> None:
    plain = plane_agreement(camera_planes(np.random.default_rng(13), flipped=()))
    flipped = plane_agreement(camera_planes(np.random.default_rng(13), flipped=("fixed_45", "fixed_top")))
    assert flipped.chi2 == pytest.approx(plain.chi2, rel=1e-9)
    for a, b in zip(plain.pairs, flipped.pairs, strict=True):
        assert (a.chi2, a.angle_rad, a.offset_m) == pytest.approx((b.chi2, b.angle_rad, b.offset_m), rel=1e-9)
    # the first camera's orientation is the common one: flipping it flips the offsets' signs only
    first = plane_agreement(camera_planes(np.random.default_rng(13), flipped=("flange",)))
    assert first.chi2 == pytest.approx(plain.chi2, rel=1e-9)
    for a, b in zip(plain.pairs, first.pairs, strict=True):
        assert (a.chi2, a.angle_rad, a.offset_m) == pytest.approx((b.chi2, b.angle_rad, -b.offset_m), rel=1e-9)


def test_a_camera_ten_sigma_off_is_named() -> None:
    result = plane_agreement(camera_planes(np.random.default_rng(14), shifted={"fixed_45": 10.0}))
    assert not result.agree and result.p_value < 1e-10
    assert result.outlier == "fixed_45"
    d = result.outlier_difference
    assert d is not None and d.camera_a == "fixed_45" and d.p_value < 1e-10
    assert d.offset_m == pytest.approx(-8e-3, abs=3.5e-3)  # the others' plane is 8 mm (10 sigma) the other way
    assert result.message().startswith("camera 'fixed_45' disagrees: its plane is ")
    assert "from the others' (p = " in result.message()


def test_two_cameras_that_disagree_name_neither() -> None:
    result = plane_agreement(camera_planes(np.random.default_rng(15), ("flange", "fixed_45"),
                                           shifted={"fixed_45": 10.0}))
    assert not result.agree and result.outlier is None and result.p_value < 1e-10
    assert result.chi2 == pytest.approx(result.pairs[0].chi2, rel=1e-9)  # two cameras: the pair is the test
    message = result.message()
    assert "'flange'" in message and "'fixed_45'" in message and "neither can be named" in message


def test_no_single_camera_to_blame() -> None:
    # three cameras, two of them off in opposite directions: no one removal leaves the rest agreeing
    result = plane_agreement(camera_planes(np.random.default_rng(16), ("flange", "fixed_45", "fixed_top"),
                                           shifted={"fixed_45": 12.0, "fixed_top": -12.0}))
    assert not result.agree and result.outlier is None
    assert "no single camera explains it" in result.message()


@pytest.mark.parametrize(("cov", "words"), [
    (np.eye(2) * 1e-8, "must be 3x3"),
    (np.diag([1e-8, 1e-8, np.inf]), "must be finite"),
    (np.array([[1e-8, 5e-9, 0.0], [0.0, 1e-8, 0.0], [0.0, 0.0, 1e-8]]), "must be symmetric"),
    (np.diag([1e-8, 0.0, 1e-8]), "positive definite"),
    (np.diag([1e-8, 1e-8, -1e-8]), "positive definite"),
])
def test_bad_plane_covariance_is_one_clear_error(cov: FloatArray, words: str) -> None:
    planes = camera_planes(np.random.default_rng(17), ("flange", "fixed_45"))
    planes["fixed_45"] = (planes["fixed_45"][0], cov)
    with pytest.raises(CalibrationError) as err:
        plane_agreement(planes)
    text = one_line(err)
    assert text.startswith("camera 'fixed_45': the plane covariance") and words in text


def test_too_few_cameras_or_a_bad_level() -> None:
    planes = camera_planes(np.random.default_rng(18), ("flange", "fixed_45"))
    with pytest.raises(CalibrationError, match="at least two cameras"):
        plane_agreement({"flange": planes["flange"]})
    with pytest.raises(CalibrationError, match="confidence"):
        plane_agreement(planes, confidence=0.0)


def test_transform_plane_propagates_both_covariances_as_a_monte_carlo_does() -> None:
    from cellcal.core.geometry.relative import _plane_coordinates, _plane_step, perturb, transform_plane

    rng = np.random.default_rng(11)
    plane = Plane(np.array([0.1, -0.2, -1.0]) / np.linalg.norm([0.1, -0.2, -1.0]), 1.19)   # a table seen from above
    cov_plane = np.diag([2e-4, 3e-4, 1e-3]) ** 2
    a = rng.normal(size=(6, 6)) * np.array([1e-3] * 3 + [2e-3] * 3)
    pose = PoseWithCovariance(Pose.from_xyz_rpy([0.3, 0.0, 1.2], np.radians([180.0, 0.5, -0.3])), a @ a.T)
    out, cov = transform_plane(plane, cov_plane, pose)
    assert np.allclose(out.normal, plane.transformed(pose.pose).normal, atol=1e-15)
    draws = []
    for _ in range(20000):
        moved = _plane_step(plane, rng.multivariate_normal(np.zeros(3), cov_plane))
        draws.append(_plane_coordinates(moved.transformed(perturb(pose.pose, rng.multivariate_normal(
            np.zeros(6), pose.covariance))), out))
    mc = np.cov(np.array(draws).T)
    scale = np.sqrt(np.outer(np.diag(cov), np.diag(cov)))
    # first order against 20000 draws: within 5 % of each entry's diagonal scale (sampling error ~1-2 %)
    assert np.max(np.abs(mc - cov) / scale) < 0.05
