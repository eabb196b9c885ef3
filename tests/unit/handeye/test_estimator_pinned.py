"""The hand-eye estimator pinned against computations of the test's own: covariance, chi2, rpy sigmas, the document.

Every expected figure is computed here from the documented model, never read back from the
estimator: the whitened plane residual of each pose (the tangent components of the normal's
error and the offset error, weighted by the plane fit's stated covariance plus the arm's
read-back noise) is written out again with scipy rotations (:class:`ByHand`); its
finite-difference Jacobian gives the covariance ``(JᵀJ)⁻¹`` (with the given values' priors,
and scaled by chi2/dof when the residuals exceed the stated noise). The rpy sigmas come from
finite differences of scipy's Euler angles, wrapped (never unwrapped), and from a Monte Carlo
of turns drawn from the covariance. Mounts rolled 180 deg (a camera looking down: the ordinary
case) and yawed near ±180 deg are where roll/pitch/yaw wrap.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np
import pytest
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation
from scipy.stats import chi2 as chi2_dist
from scipy.stats import norm
from scipy.stats import t as student_t

from cellcal.core.geometry.planes import Plane
from cellcal.core.handeye.estimator import HandEyeEstimate, estimate_mount, jacobian, observability, rpy_with_sigma_deg
from cellcal.core.handeye.model import PlaneObservation
from cellcal.core.handeye.synthetic import Scenario, camera_views, observations, sim_scenario
from cellcal.devices.errors import CalibrationError, CalibrationQualityError
from cellcal.devices.pose import Pose
from tests.support.numerics import assert_covariance_close

FloatArray = NDArray[np.float64]

#: The arm's read-back noise the estimator assumes by default (m, rad).
ARM_T, ARM_R = 2.5e-5, 0.0
#: The issue's unmodelled read-back noise: 0.1 mm, 0.01 deg.
TRUE_ARM_T, TRUE_ARM_R = 1e-4, math.radians(0.01)
#: ``[handeye] given`` names, in the order of the parameter vector (ADR 0018), typed out.
NAMES = ["mount_rot_x", "mount_rot_y", "mount_rot_z", "mount_x", "mount_y", "mount_z",
         "plane_tilt_a", "plane_tilt_b", "plane_offset"]
#: The tilts of a table whose normal is +z: about the axis across it closest to base x (x itself), then z × x = y.
TILT_AXES = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
#: A correlated covariance of the mount's turn about the flange axes (rad²), about 0.01 deg 1-sigma.
A = np.array([[1.0, 0.2, -0.1], [0.0, 0.8, 0.3], [0.0, 0.0, 1.5]]) * 1.5e-4
TURN_COVARIANCE = A @ A.T
#: Every key of the fit's JSON form (handeye.json's ``fit``).
FIT_KEYS = {"chi2", "dof", "chi2_per_dof", "p_value", "given", "given_sigma", "parameters", "covariance",
            "covariance_absolute", "interval_scale", "interval_z", "noise_model", "notes"}


# ---------------------------------------------------------------------- the test's own computations
def euler_deg(rotation: Rotation) -> FloatArray:
    """Roll, pitch, yaw (deg) of a rotation by scipy: extrinsic x-y-z, ``Rz(yaw) Ry(pitch) Rx(roll)``."""
    angles: FloatArray = rotation.as_euler("xyz", degrees=True)
    return angles


def wrap_deg(angle: FloatArray) -> FloatArray:
    """Angles (deg) wrapped into [-180, 180)."""
    wrapped: FloatArray = np.remainder(np.asarray(angle) + 180.0, 360.0) - 180.0
    return wrapped


def rpy_gradient(rotation: Rotation, step: float = 1e-5) -> FloatArray:
    """d(roll, pitch, yaw)/d(turn about the flange x, y, z) (rad/rad), central differences of wrapped angles."""
    cols = []
    for e in np.eye(3):
        plus = euler_deg(Rotation.from_rotvec(step * e) * rotation)
        minus = euler_deg(Rotation.from_rotvec(-step * e) * rotation)
        cols.append(np.radians(wrap_deg(plus - minus)) / (2.0 * step))
    return np.column_stack(cols)


def rpy_sigma_deg(rotation: Rotation, turn_covariance: FloatArray) -> FloatArray:
    """1-sigma (deg) of roll, pitch, yaw propagated linearly from the covariance of the turn (rad²)."""
    g = rpy_gradient(rotation)
    return np.degrees(np.sqrt(np.diag(g @ turn_covariance @ g.T)))


def monte_carlo_rpy_sigma_deg(rotation: Rotation, turn_covariance: FloatArray, runs: int, seed: int) -> FloatArray:
    """Sample 1-sigma (deg) of roll, pitch, yaw of turns drawn from the covariance, each wrapped around the centre."""
    turns = np.random.default_rng(seed).multivariate_normal(np.zeros(3), turn_covariance, runs, method="cholesky")
    angles = (Rotation.from_rotvec(turns) * rotation).as_euler("xyz", degrees=True)
    spread: FloatArray = np.std(wrap_deg(angles - euler_deg(rotation)), axis=0, ddof=1)
    return spread


def jacobian_by_hand(fun: Callable[[FloatArray], FloatArray], x: FloatArray, step: float = 2e-6) -> FloatArray:
    """Central-difference Jacobian (a step other than the estimator's)."""
    return np.column_stack([(fun(x + step * e) - fun(x - step * e)) / (2.0 * step) for e in np.eye(len(x))])


@dataclass(frozen=True)
class ByHand:
    """The plane constraints of a set of observations, written out from the model's documentation.

    Parameters ``p`` (9,): the mount's turn about the flange axes (applied on the left), its
    translation step (flange frame), the table normal's tilts about :data:`TILT_AXES`, the
    offset step. Pose ``i``'s camera is ``flange_i @ mount``; it sees the base-frame plane
    ``(n_B, c_B)`` as ``n_C = R_C^T n_B`` and ``c_C = c_B + n_B·t_C``.

    Attributes:
        observations: The plane observations.
        nominal_mount: The configured mount (``p = 0``).
        nominal_plane: The configured plane, normal +z.
        arm_t: The arm's read-back 1-sigma per axis the residuals are weighed with, m.
        arm_r: Likewise for its orientation, rad.
    """

    observations: Sequence[PlaneObservation]
    nominal_mount: Pose
    nominal_plane: Plane
    arm_t: float = ARM_T
    arm_r: float = ARM_R

    def __post_init__(self) -> None:
        assert np.allclose(self.nominal_plane.normal, [0.0, 0.0, 1.0], atol=0.0)  # the TILT_AXES are its

    def mount(self, p: FloatArray) -> Pose:
        """The mount of the parameters."""
        return Pose(Rotation.from_rotvec(p[:3]) * self.nominal_mount.rotation, self.nominal_mount.translation + p[3:6])

    def plane(self, p: FloatArray) -> tuple[FloatArray, float]:
        """The base-frame plane's normal and offset of the parameters."""
        turn = Rotation.from_rotvec(p[6] * TILT_AXES[0] + p[7] * TILT_AXES[1])
        return turn.apply(np.array(self.nominal_plane.normal)), self.nominal_plane.offset_m + p[8]

    def parameters_of(self, mount: Pose, plane: Plane) -> FloatArray:
        """The parameters of a mount and a plane (the plane's tilt: the turn taking the configured normal to it)."""
        n0, n = np.array(self.nominal_plane.normal), np.array(plane.normal)
        across = np.cross(n0, n)
        angle = math.atan2(float(np.linalg.norm(across)), float(n0 @ n))
        tilt = across / np.linalg.norm(across) * angle if angle > 0 else np.zeros(3)
        return np.concatenate([(mount.rotation * self.nominal_mount.rotation.inv()).as_rotvec(),
                               mount.translation - self.nominal_mount.translation, TILT_AXES @ tilt,
                               [plane.offset_m - self.nominal_plane.offset_m]])

    def predicted(self, p: FloatArray) -> list[tuple[FloatArray, float]]:
        """The camera-frame normal and offset each pose would see."""
        mount, (n_b, c_b) = self.mount(p), self.plane(p)
        out = []
        for o in self.observations:
            camera = o.flange @ mount
            out.append((camera.rotation.inv().apply(n_b), c_b + float(n_b @ camera.translation)))
        return out

    def pose_residuals(self, p: FloatArray) -> FloatArray:
        """Whitened residuals (N, 3): the normal's error across the measured normal and the offset's, whitened."""
        lever = float(np.linalg.norm(self.nominal_mount.translation))
        rows = []
        for o, (n_c, c_c) in zip(self.observations, self.predicted(p), strict=True):
            across = np.linalg.svd(np.eye(3) - np.outer(o.normal, o.normal))[0][:, :2]  # any basis across it
            m = np.zeros((3, 4))
            m[:2, :3] = across.T
            m[2, 3] = 1.0
            cov = m @ o.covariance @ m.T + np.diag([self.arm_r**2, self.arm_r**2,
                                                     self.arm_t**2 + (self.arm_r * lever) ** 2])
            values, vectors = np.linalg.eigh(cov)
            whiten = vectors @ np.diag(values**-0.5) @ vectors.T  # cov^(-1/2)
            rows.append(whiten @ np.concatenate([across.T @ (n_c - o.normal), [c_c - o.offset_m]]))
        return np.array(rows)

    def whitened(self, p: FloatArray) -> FloatArray:
        """All whitened residuals, flattened (3N,)."""
        return self.pose_residuals(p).ravel()

    def jacobian(self, p: FloatArray) -> FloatArray:
        """Whitened residuals by the nine parameters (3N, 9)."""
        return jacobian_by_hand(self.whitened, p)


def covariance(jac: FloatArray, fitted: Sequence[int], prior_info: Sequence[float] = (), scale: float = 1.0
               ) -> FloatArray:
    """The 9x9 covariance of the fitted parameters: data information over scale², plus the priors' 1/sigma²."""
    info = jac[:, fitted].T @ jac[:, fitted] / scale**2 + np.diag(prior_info or [0.0] * len(fitted))
    out = np.zeros((9, 9))
    out[np.ix_(fitted, fitted)] = np.linalg.inv(info)
    return out


def check_pinned(est: HandEyeEstimate, by: ByHand) -> tuple[FloatArray, FloatArray]:
    """Check the estimate's parameters against its mount and plane and that it is the least-squares minimum.

    Returns:
        The parameters (computed from the mount and plane) and the whitened Jacobian there.
    """
    p = by.parameters_of(est.mount, est.plane)
    np.testing.assert_allclose(est.parameters, p, rtol=0.0, atol=1e-12)
    jac = by.jacobian(p)
    return p, jac


# ---------------------------------------------------------------------- rpy_with_sigma_deg at the seam
@pytest.mark.parametrize("rpy", [(180.0, 0.0, 90.0), (-180.0, 0.3, 179.9), (180.0, -0.2, -179.95),
                                 (180.0, 0.5, 180.0), (-180.0, -0.4, -180.0), (179.99, 0.1, 180.0),
                                 (0.6, -0.5, 90.6)])
def test_rpy_sigma_of_a_mount_looking_down_equals_finite_differences_of_scipy_angles(
        rpy: tuple[float, float, float]) -> None:
    """At roll ±180 deg and yaw near ±180 deg the sigmas are those of the wrapped angles, not of a 360 deg jump."""
    mount = Pose.from_xyz_rpy([0.0, 0.04, -0.06], np.radians(rpy))
    angles, sigma = rpy_with_sigma_deg(mount, TURN_COVARIANCE)
    np.testing.assert_array_equal(angles, np.degrees(mount.as_xyz_rpy()[3:]))  # as in [mount]
    np.testing.assert_allclose(wrap_deg(angles - euler_deg(mount.rotation)), 0.0, atol=1e-9)
    np.testing.assert_allclose(sigma, rpy_sigma_deg(mount.rotation, TURN_COVARIANCE), rtol=1e-6)
    assert np.all(sigma < 0.05)  # about 0.01 deg each: one 360 deg jump in a difference would make it ~1e4 deg


@pytest.mark.parametrize("rpy", [(180.0, 0.0, 90.0), (-180.0, 0.3, 179.9), (180.0, -0.2, -180.0)])
def test_rpy_sigma_of_a_mount_looking_down_equals_a_monte_carlo_of_turns(rpy: tuple[float, float, float]) -> None:
    """20 000 turns drawn from the covariance, converted by scipy and wrapped: the same sigmas within 3 %."""
    mount = Pose.from_xyz_rpy([0.0, 0.04, -0.06], np.radians(rpy))
    _, sigma = rpy_with_sigma_deg(mount, TURN_COVARIANCE)
    sampled = monte_carlo_rpy_sigma_deg(mount.rotation, TURN_COVARIANCE, 20_000, seed=180)
    np.testing.assert_allclose(sigma, sampled, rtol=0.03)  # sampling error 0.5 % (1 s.e.); both ways


def test_rpy_sigma_scales_with_the_turn_and_is_zero_for_a_turn_known_exactly() -> None:
    """Sigma follows the covariance's square root exactly; no turn uncertainty gives 0 for every angle."""
    mount = Pose.from_xyz_rpy([0.0, 0.04, -0.06], np.radians([180.0, 0.0, 90.0]))
    _, sigma = rpy_with_sigma_deg(mount, TURN_COVARIANCE)
    _, wide = rpy_with_sigma_deg(mount, 9.0 * TURN_COVARIANCE)
    np.testing.assert_allclose(wide, 3.0 * sigma, rtol=1e-12)
    # at yaw 90 deg (pitch 0) a turn about flange z moves yaw alone by as much, about flange -x pitch, about y roll
    one = math.radians(0.01) ** 2
    for axis, moved in ((2, 2), (0, 1), (1, 0)):
        cov = np.zeros((3, 3))
        cov[axis, axis] = one
        _, sigma = rpy_with_sigma_deg(mount, cov)
        expected = np.zeros(3)
        expected[moved] = 0.01
        np.testing.assert_allclose(sigma, expected, rtol=1e-6, atol=1e-9)
    _, none = rpy_with_sigma_deg(mount, np.zeros((3, 3)))
    np.testing.assert_array_equal(none, np.zeros(3))


# ---------------------------------------------------------------------- a camera looking down, whole fit
def test_a_fit_of_a_mount_rolled_180_deg_gives_the_rpy_sigmas_of_its_own_covariance() -> None:
    """The roll of the fitted mount sits on the ±180 deg seam; its sigmas are those of the test's covariance."""
    nominal = Pose.from_xyz_rpy([0.0, 0.04, -0.06], np.radians([180.0, 0.0, 180.0]))
    truth = Pose.from_xyz_rpy([0.002, 0.037, -0.063], np.radians([180.0, 0.4, 179.7]))
    scenario = sim_scenario(true_mount=truth, nominal_mount=nominal)
    views = observations(scenario, None)
    est = estimate_mount(views, nominal, scenario.nominal_plane)
    by = ByHand(views, nominal, scenario.nominal_plane)
    _, jac = check_pinned(est, by)
    assert est.noise.verdict == "too_good"  # noise-free: chi2 ~0, the intervals keep the stated noise
    cov = covariance(jac, range(9))
    assert_covariance_close(est.covariance, cov, rtol=1e-5)
    rpy, sigma = est.rpy_and_sigma_deg()
    assert abs(abs(rpy[0]) - 180.0) < 1e-7 and rpy[2] == pytest.approx(179.7, abs=1e-7)  # on the seam
    np.testing.assert_allclose(sigma, rpy_sigma_deg(est.mount.rotation, cov[:3, :3]), rtol=1e-5)
    assert np.all(sigma < 0.01)  # a few thousandths of a degree
    np.testing.assert_allclose(est.rotation_sigma_rad, np.sqrt(np.diag(cov)[:3]), rtol=1e-5)
    np.testing.assert_allclose(est.translation_sigma_m, np.sqrt(np.diag(cov)[3:6]), rtol=1e-5)


# ---------------------------------------------------------------------- the fit's figures and document
def test_a_consistent_fit_carries_the_chi2_covariance_and_document_of_the_model() -> None:
    """Right stated noise: every figure of the fit and every key of its JSON form, computed by the test."""
    scenario = sim_scenario()
    views = observations(scenario, np.random.default_rng(2))
    est = estimate_mount(views, scenario.nominal_mount, scenario.nominal_plane)
    by = ByHand(views, scenario.nominal_mount, scenario.nominal_plane)
    p, jac = check_pinned(est, by)
    white = by.pose_residuals(p)
    chi2 = float(np.sum(white**2))
    cov = covariance(jac, range(9))
    # the fit is the least-squares minimum: the Gauss-Newton step from it is below 1e-6 of each sigma
    step = cov @ jac.T @ white.ravel()
    assert np.all(np.abs(step) < 1e-6 * np.sqrt(np.diag(cov)))
    assert est.chi2 == pytest.approx(chi2, rel=1e-9) and est.dof == 15  # 8 poses x 3 residuals - 9 parameters
    assert_covariance_close(est.covariance, cov, rtol=1e-5)
    assert_covariance_close(est.absolute_covariance, cov, rtol=1e-5)
    # per pose: the angle between predicted and measured normals, measured minus predicted offset, chi2
    for r, o, (n_c, c_c), w in zip(est.residuals, views, by.predicted(p), white, strict=True):
        angle = math.degrees(math.atan2(float(np.linalg.norm(np.cross(n_c, o.normal))), float(n_c @ o.normal)))
        assert r.normal_deg == pytest.approx(angle, rel=1e-6)
        assert r.offset_m == pytest.approx(o.offset_m - c_c, rel=1e-6, abs=1e-12)
        assert r.chi2 == pytest.approx(float(w @ w), rel=1e-6)
    # the observability at the solution: the singular values of the test's Jacobian
    singular = np.linalg.svd(jac, compute_uv=False)
    np.testing.assert_allclose(est.observability.singular_values, singular, rtol=1e-5)
    assert est.observability.rank == 9 and est.observability.condition == pytest.approx(singular[0] / singular[-1],
                                                                                         rel=1e-5)
    assert est.p_value == pytest.approx(float(chi2_dist.sf(chi2, 15)), rel=1e-8)
    np.testing.assert_allclose(est.rpy_and_sigma_deg()[1], rpy_sigma_deg(est.mount.rotation, cov[:3, :3]), rtol=1e-5)
    z95 = float(norm.ppf(0.975))
    assert est.z == z95 and est.interval_scale == 1.0 and est.notes == ()
    doc = est.to_dict()
    assert set(doc) == FIT_KEYS
    assert doc["chi2"] == pytest.approx(chi2, rel=1e-9) and doc["dof"] == 15
    assert doc["chi2_per_dof"] == pytest.approx(chi2 / 15, rel=1e-9)
    assert doc["p_value"] == pytest.approx(float(chi2_dist.sf(chi2, 15)), rel=1e-8)
    assert doc["given"] == [] and doc["given_sigma"] == {} and doc["parameters"] == NAMES
    assert_covariance_close(doc["covariance"], cov, rtol=1e-5)
    assert_covariance_close(doc["covariance_absolute"], cov, rtol=1e-5)
    assert doc["interval_scale"] == 1.0 and doc["interval_z"] == z95
    assert doc["noise_model"] == {"verdict": "consistent", "chi2_per_dof": pytest.approx(chi2 / 15, rel=1e-9),
                                  "p_above": pytest.approx(float(chi2_dist.sf(chi2, 15)), rel=1e-8),
                                  "p_below": pytest.approx(float(chi2_dist.cdf(chi2, 15)), rel=1e-8),
                                  "test_level": 0.01, "interval_scale": 1.0, "interval_z": z95, "note": None}
    assert doc["notes"] == []
    assert json.loads(json.dumps(doc))["covariance"] == doc["covariance"]  # what handeye.json carries
    # an estimate without an absolute covariance reports its covariance as the absolute one
    bare = replace(est, absolute_covariance=None).to_dict()
    assert bare["covariance_absolute"] == doc["covariance"]


def test_a_scaled_fit_with_a_held_and_a_prior_given_value_carries_both_in_its_document() -> None:
    """Unmodelled arm noise, tilt a held exact, the table height with a 2 mm prior, 90 % intervals, 5 % test."""
    scenario = sim_scenario().with_arm_noise(TRUE_ARM_T, TRUE_ARM_R)
    views = observations(scenario, np.random.default_rng(1))
    est = estimate_mount(views, scenario.nominal_mount, scenario.nominal_plane, given=("plane_tilt_a", "plane_offset"),
                         given_sigma={"plane_offset": 0.002}, confidence=0.9, noise_test_level=0.05)
    by = ByHand(views, scenario.nominal_mount, scenario.nominal_plane)
    p, jac = check_pinned(est, by)
    assert p[6] == 0.0 == est.parameters[6]  # held exact
    fitted, prior = [0, 1, 2, 3, 4, 5, 7, 8], [0.0] * 7 + [0.002**-2]
    chi2 = float(np.sum(by.whitened(p) ** 2)) + (p[8] / 0.002) ** 2  # the data and the prior's term
    dof = 8 * 3 + 1 - 8  # 24 residuals and the prior's, 8 fitted parameters
    scale = math.sqrt(chi2 / dof)
    assert est.dof == dof and est.chi2 == pytest.approx(chi2, rel=1e-9)
    assert est.noise.verdict == "scaled" and est.interval_scale == pytest.approx(scale, rel=1e-9) and scale > 2.0
    absolute = covariance(jac, fitted, prior)
    scaled = covariance(jac, fitted, prior, scale)
    assert_covariance_close(est.absolute_covariance, absolute, rtol=1e-5)
    assert_covariance_close(est.covariance, scaled, rtol=1e-5)
    np.testing.assert_allclose(est.rpy_and_sigma_deg()[1], rpy_sigma_deg(est.mount.rotation, scaled[:3, :3]),
                               rtol=1e-5)
    # the observability at the solution is that of the 7 free parameters' columns
    free = [0, 1, 2, 3, 4, 5, 7]
    assert est.observability.n_parameters == 7 and est.observability.rank == 7
    np.testing.assert_allclose(est.observability.singular_values, np.linalg.svd(jac[:, free], compute_uv=False),
                               rtol=1e-5)
    t90 = float(student_t.ppf(0.95, dof))
    p_above = float(chi2_dist.sf(chi2, dof))
    noise_note = (f"chi2/dof {chi2 / dof:.2f} is more than {dof} dof allow (p = {p_above:.2g} < 0.05): the residuals "
                  f"exceed the stated noise, so the intervals are scaled by {scale:.2f} (sqrt of chi2/dof) with "
                  f"Student-t quantiles ({dof} dof)")
    notes = [noise_note,
             "given plane_tilt_a held exact: the intervals are conditional on this value being right (set [handeye] "
             "given_sigma to include its uncertainty)",
             "given plane_offset ± 2 mm (1 sigma): fitted with that prior, its uncertainty is in the intervals"]
    doc = est.to_dict()
    assert set(doc) == FIT_KEYS
    assert doc["chi2"] == pytest.approx(chi2, rel=1e-9) and doc["dof"] == dof
    assert doc["chi2_per_dof"] == pytest.approx(chi2 / dof, rel=1e-9)
    assert doc["p_value"] == pytest.approx(p_above, rel=1e-6)
    assert doc["given"] == ["plane_tilt_a", "plane_offset"] and doc["given_sigma"] == {"plane_offset": 0.002}
    assert doc["parameters"] == NAMES
    assert_covariance_close(doc["covariance"], scaled, rtol=1e-5)
    assert_covariance_close(doc["covariance_absolute"], absolute, rtol=1e-5)
    assert doc["interval_scale"] == pytest.approx(scale, rel=1e-9)
    assert doc["interval_z"] == pytest.approx(t90, rel=1e-12) and est.z == doc["interval_z"]
    assert doc["noise_model"] == {"verdict": "scaled", "chi2_per_dof": pytest.approx(chi2 / dof, rel=1e-9),
                                  "p_above": pytest.approx(p_above, rel=1e-6),
                                  "p_below": pytest.approx(float(chi2_dist.cdf(chi2, dof)), rel=1e-9),
                                  "test_level": 0.05, "interval_scale": pytest.approx(scale, rel=1e-9),
                                  "interval_z": pytest.approx(t90, rel=1e-12), "note": noise_note}
    assert doc["notes"] == notes and list(est.notes) == notes and est.confidence == 0.9


def test_a_prior_sigma_of_exactly_1_is_a_prior_like_any_other() -> None:
    """Given 1 m on the table height (prior information 1/sigma² exactly 1): one more residual, its information."""
    scenario = sim_scenario()
    views = observations(scenario, np.random.default_rng(2))
    est = estimate_mount(views, scenario.nominal_mount, scenario.nominal_plane, given=("plane_offset",),
                         given_sigma={"plane_offset": 1.0})
    by = ByHand(views, scenario.nominal_mount, scenario.nominal_plane)
    p, jac = check_pinned(est, by)
    chi2 = float(np.sum(by.whitened(p) ** 2)) + p[8] ** 2
    assert est.dof == 16 and est.chi2 == pytest.approx(chi2, rel=1e-9)  # 24 + 1 residuals, 9 parameters
    assert_covariance_close(est.covariance, covariance(jac, range(9), [0.0] * 8 + [1.0]), rtol=1e-5)
    assert est.to_dict()["given_sigma"] == {"plane_offset": 1.0}


@pytest.mark.parametrize(("given", "dof"), [(("mount_rot_z", "mount_z", "plane_offset"), 0),
                                            (("mount_rot_x", "mount_rot_y", "mount_x", "mount_y"), 1)])
def test_two_poses_leave_zero_or_one_degree_of_freedom(given: tuple[str, ...], dof: int) -> None:
    """Two poses are enough with given values (here the true ones): no dof (untested, no chi2/dof, p NaN) or one."""
    scenario = sim_scenario(nominal_mount=sim_scenario().true_mount)
    views = [observations(scenario, np.random.default_rng(2))[i] for i in (0, 5)]
    assert observability(views, scenario.nominal_mount, scenario.nominal_plane, given=given).observable
    est = estimate_mount(views, scenario.nominal_mount, scenario.nominal_plane, given=given)
    by = ByHand(views, scenario.nominal_mount, scenario.nominal_plane)
    p, jac = check_pinned(est, by)
    chi2 = float(np.sum(by.whitened(p) ** 2))
    fitted = [i for i, name in enumerate(NAMES) if name not in given]
    assert est.dof == dof == 6 - len(fitted)
    doc = est.to_dict()
    assert set(doc) == FIT_KEYS and doc["given"] == list(given) and doc["given_sigma"] == {}
    held = (f"given {', '.join(given)} held exact: the intervals are conditional on these values being right "
            "(set [handeye] given_sigma to include its uncertainty)")
    if dof == 0:
        assert est.chi2 < 1e-12 and doc["chi2_per_dof"] is None and math.isnan(doc["p_value"])
        assert doc["noise_model"]["verdict"] == "untested" and doc["noise_model"]["chi2_per_dof"] is None
        assert doc["notes"] == ["no degrees of freedom left: the noise model cannot be checked, the intervals assume "
                                "it", held]
        assert_covariance_close(est.covariance, covariance(jac, fitted), rtol=1e-5)
    else:
        assert doc["chi2"] == pytest.approx(chi2, rel=1e-6) and doc["chi2_per_dof"] == pytest.approx(chi2, rel=1e-6)
        assert doc["p_value"] == pytest.approx(float(chi2_dist.sf(chi2, 1)), rel=1e-6)
        assert doc["noise_model"]["verdict"] == "consistent" and doc["notes"] == [held]


# ---------------------------------------------------------------------- the plane normal, toward the cameras
def table_below_the_base() -> Scenario:
    """The sim cell with the table 0.3 m below the arm's base (the plane's offset is then not 0)."""
    base = sim_scenario()
    true_table = Plane.from_point_normal([0.0, 0.0, -0.2988], Rotation.from_rotvec([3e-4, -2e-4, 0.0]).apply([0, 0, 1]))
    flanges = camera_views(base.true_mount, [0.3, 0.0, -0.3], 0.45, (80.0, 65.0), (0.0, 90.0, 180.0, 270.0))
    return replace(base, true_plane=true_table, nominal_plane=Plane(np.array([0.0, 0.0, 1.0]), 0.3), flanges=flanges)


def test_a_configured_normal_pointing_away_from_the_cameras_is_turned_toward_them() -> None:
    """``[reference]`` with the table's normal down gives the very fit of the normal up."""
    scenario = table_below_the_base()
    views = observations(scenario, np.random.default_rng(2))
    up = scenario.nominal_plane
    down = Plane(np.array([0.0, 0.0, -1.0]), -0.3)  # the same table, normal away from the cameras
    cameras = np.array([(o.flange @ scenario.nominal_mount).translation for o in views])
    assert np.all(down.signed_distance(cameras) < -0.3)
    right = estimate_mount(views, scenario.nominal_mount, up)
    turned = estimate_mount(views, scenario.nominal_mount, down)
    np.testing.assert_array_equal(turned.parameters, right.parameters)
    np.testing.assert_array_equal(turned.covariance, right.covariance)
    np.testing.assert_array_equal(turned.mount.as_matrix(), right.mount.as_matrix())
    np.testing.assert_array_equal(turned.plane.normal, right.plane.normal)
    assert turned.plane.offset_m == right.plane.offset_m and turned.chi2 == right.chi2
    # ... which is the true table, its normal toward the cameras
    assert np.all(turned.plane.signed_distance(cameras) > 0.3)
    assert np.degrees(np.arccos(turned.plane.normal @ scenario.true_plane.normal)) < 0.005
    assert turned.plane.offset_m == pytest.approx(scenario.true_plane.offset_m, abs=1e-3)  # 0.27 mm 1-sigma
    assert turned.noise.verdict == "consistent"
    by_down = observability(views, scenario.nominal_mount, down)
    assert by_down.singular_values == observability(views, scenario.nominal_mount, up).singular_values


@pytest.mark.parametrize("too_high_m", [0.46, 0.6])
@pytest.mark.parametrize("normal_z", [1.0, -1.0])
def test_the_side_is_the_measured_normals_even_for_a_table_configured_above_the_cameras(
        too_high_m: float, normal_z: float) -> None:
    """A table configured 0.46 m / 0.6 m too high (above every camera, ~0.44 m above the real one), either normal.

    The side is decided by the first measured normal (toward its camera) in the base frame, so the fit
    converges to the true table and mount; turned by the cameras' configured positions instead, the
    configured normal would point away from them and the fit would reach the mirrored mount, 0.9 m off.
    """
    scenario = sim_scenario()
    views = observations(scenario, None)
    nominal = scenario.nominal_mount
    height = -scenario.true_plane.offset_m * scenario.true_plane.normal[2]     # the true table's z, base frame
    configured = Plane.from_point_normal([0.0, 0.0, height + too_high_m], [0.0, 0.0, normal_z])
    cameras = np.array([(o.flange @ nominal).translation for o in views])
    assert np.all(cameras[:, 2] < height + too_high_m)                         # every camera below the configured table
    est = estimate_mount(views, nominal, configured)
    np.testing.assert_allclose(est.mount.translation, scenario.true_mount.translation, rtol=0, atol=1e-7)
    assert np.linalg.norm((scenario.true_mount.inv() @ est.mount).rotation.as_rotvec()) < 1e-7
    np.testing.assert_allclose(est.plane.normal, scenario.true_plane.normal, rtol=0, atol=1e-7)
    assert est.plane.offset_m == pytest.approx(scenario.true_plane.offset_m, abs=1e-7)


def test_the_report_of_an_estimate_is_at_its_solution_where_a_turn_can_cross_the_limit() -> None:
    """Stated noise such that the weakest direction's singular value is 10.004 (limit 10) at the configured mount.

    The plan is accepted (observable before the fit); at the solution the same direction, a turn
    about the flange z axis (the tool axis, about which the plane normal's cone lies) traded with
    the table's tilt, has 0.26 % less: the estimate's report says the data cannot determine it. The normal's
    first axis across (nearest the camera's x) correlated -0.5 with the offset sets how much less: +0.3 would give
    0.13 % more.
    """
    scenario = replace(sim_scenario(), correlation=-0.5)
    views = observations(scenario, None)
    free = list(range(8))  # the table height given
    by = ByHand(views, scenario.nominal_mount, scenario.nominal_plane, arm_t=0.0)
    weakest = np.linalg.svd(by.jacobian(np.zeros(9))[:, free], compute_uv=False)[-1]
    views = [replace(o, covariance=o.covariance * (weakest / 10.004) ** 2) for o in views]  # about 680x the noise
    by = ByHand(views, scenario.nominal_mount, scenario.nominal_plane, arm_t=0.0)
    before = observability(views, scenario.nominal_mount, scenario.nominal_plane, given=("plane_offset",),
                           arm_translation_sigma_m=0.0)
    assert before.observable and before.singular_values[-1] == pytest.approx(10.004, rel=1e-6)
    est = estimate_mount(views, scenario.nominal_mount, scenario.nominal_plane, given=("plane_offset",),
                         arm_translation_sigma_m=0.0)
    _, s, vt = np.linalg.svd(by.jacobian(est.parameters)[:, free])
    assert s[-1] < 9.99  # 9.978: below the limit by 0.1 % of it at least, far beyond any rounding
    np.testing.assert_allclose(est.observability.singular_values, s, rtol=1e-6)
    # the unseen direction by the naming rules: its turn is along flange z and along the mean normal, with tilt in it
    turn = vt[-1][:3] / np.linalg.norm(vt[-1][:3])
    mean_normal = np.mean([o.flange.rotation.inv().apply([0.0, 0.0, 1.0]) for o in views], axis=0)
    assert abs(turn[2]) > 0.999 and abs(turn @ mean_normal) / np.linalg.norm(mean_normal) > 0.98
    assert np.abs(vt[-1][6:8]).max() > 0.2
    report = est.observability
    assert (report.rank, report.n_parameters, report.observable) == (7, 8, False)
    assert re.fullmatch(r"cannot see 1 of 8 parameters: mount rotation about flange z \(= the plane normal\) "
                        r"\(traded with the plane's tilt\); "
                        r"fix: add a second inclination and rolls about the tool axis", report.message())


# ---------------------------------------------------------------------- refusals and their words
def one_orientation_plan() -> tuple[list[PlaneObservation], Pose, Plane]:
    """Four views straight down from one flange orientation (only the position changes), camera z along flange z."""
    mount = Pose.from_xyz_rpy([0.0, 0.04, 0.06], np.radians([0.0, 0.0, 90.0]))
    table = Plane(np.array([0.0, 0.0, 1.0]), 0.0)
    down = Rotation.from_euler("x", math.pi)
    flanges = tuple(Pose(down, [x, y, 0.45]) @ mount.inv() for x, y in [(0.2, 0.0), (0.3, 0.1), (0.4, -0.1),
                                                                         (0.3, -0.2)])
    return observations(Scenario(mount, mount, table, table, flanges), None), mount, table


def test_a_plan_of_one_orientation_is_refused_naming_what_it_cannot_see() -> None:
    """One orientation sees neither the turn about the normal nor the translation but its height (traded with c_B).

    The normal is flange ∓z at every pose: the offsets see ``c_B + n_B·t_A + u·t_X``, so the
    mount translation across z is unseen and along z it trades with the table height; the
    normals see the mount's turn but about the normal. Rank 9 - 4 = 5.
    """
    views, mount, table = one_orientation_plan()
    words = (r"cannot see 4 of 9 parameters: mount rotation about flange z \(= the plane normal\); "
             r"mount translation along flange -?z vs the plane's height; "
             r"mount translation across flange z \(parallel to the plane\); "
             r"fix: add a second inclination and rolls about the tool axis")
    report = observability(views, mount, table)
    assert report.rank == 5 and report.n_parameters == 9
    assert re.fullmatch(words, report.message())
    with pytest.raises(CalibrationQualityError) as err:
        estimate_mount(views, mount, table)
    assert (err.value.gate, err.value.value, err.value.threshold) == ("observability", 5, 9)
    assert re.fullmatch(r"quality gate 'observability' failed: 5 vs threshold 9; " + words, str(err.value))


def test_residuals_beyond_ten_times_the_noise_are_refused_naming_the_worst_pose() -> None:
    """A 3 mm error in pose 6's offset: refused, the message says chi2, dof and the worst pose with its chi2."""
    scenario = sim_scenario()
    views = observations(scenario, np.random.default_rng(2))
    views[5] = replace(views[5], offset_m=views[5].offset_m + 0.003)
    accepted = estimate_mount(views, scenario.nominal_mount, scenario.nominal_plane, max_interval_scale=math.inf)
    by = ByHand(views, scenario.nominal_mount, scenario.nominal_plane)
    p, _ = check_pinned(accepted, by)
    per_pose = np.sum(by.pose_residuals(p) ** 2, axis=1)
    chi2 = float(per_pose.sum())
    worst = int(np.argmax(per_pose))
    assert worst == 5 and per_pose[5] > 1.5 * np.sort(per_pose)[-2]  # clearly the largest
    scale = math.sqrt(chi2 / 15)
    assert 10.0 < scale < 20.0
    with pytest.raises(CalibrationQualityError) as err:
        estimate_mount(views, scenario.nominal_mount, scenario.nominal_plane)
    assert str(err.value) == (
        f"quality gate 'noise_model' failed: {scale:.6g} vs threshold 10; the residuals are {scale:.1f}x the stated "
        f"noise (chi2 {chi2:.4g} over 15 dof): the noise model ([handeye] arm_translation_sigma_m / "
        "arm_rotation_sigma_deg) or a given value is wrong, or the plane moved; largest residual at pose 6 "
        f"(chi2 {per_pose[5]:.4g})")


def test_bad_calls_are_one_line_errors_said_whole() -> None:
    """One pose, or an unknown given name: the whole message."""
    scenario = sim_scenario()
    views = observations(scenario, None)
    with pytest.raises(CalibrationError) as err:
        estimate_mount(views[:1], scenario.nominal_mount, scenario.nominal_plane)
    assert str(err.value) == "hand-eye estimation needs at least 2 poses, got 1"
    with pytest.raises(CalibrationError) as err:
        observability(views[:1], scenario.nominal_mount, scenario.nominal_plane)
    assert str(err.value) == "hand-eye estimation needs at least 2 poses, got 1"
    with pytest.raises(CalibrationError) as err:
        estimate_mount(views, scenario.nominal_mount, scenario.nominal_plane, given=("mount_w", "plane_offset", "a"))
    assert str(err.value) == ("unknown given parameter(s) ['a', 'mount_w']; expected some of mount_rot_x, mount_rot_y, "
                              "mount_rot_z, mount_x, mount_y, mount_z, plane_tilt_a, plane_tilt_b, plane_offset")
    # two poses are not refused as too few: the plan is, by the observability gate (6 residuals, 9 parameters)
    report = observability(views[:2], scenario.nominal_mount, scenario.nominal_plane)
    assert report.n_parameters == 9 and report.rank <= 6


# ---------------------------------------------------------------------- the Jacobian
def test_the_jacobian_of_a_known_function_and_of_no_parameters() -> None:
    """Central differences match the derivatives by hand; no parameters give an (m, 0) matrix."""

    def fun(x: FloatArray) -> FloatArray:
        return np.array([x[0] ** 2 * x[1], math.sin(x[1]), math.exp(x[0]) + 3.0 * x[1], 2.0])

    x = np.array([0.3, -1.2])
    expected = np.array([[2 * 0.3 * -1.2, 0.3**2], [0.0, math.cos(-1.2)], [math.exp(0.3), 3.0], [0.0, 0.0]])
    np.testing.assert_allclose(jacobian(fun, x), expected, rtol=0, atol=1e-8)
    empty = jacobian(lambda _: np.ones(4), np.zeros(0))
    assert empty.shape == (4, 0)
    scenario = sim_scenario()
    report = observability(observations(scenario, None), scenario.nominal_mount, scenario.nominal_plane,
                           given=tuple(NAMES))
    assert (report.rank, report.n_parameters, report.singular_values, report.unseen) == (0, 0, (), ())
    assert report.message() == "all 0 parameters observable (condition inf)"
