"""Synthetic plane views of a known mount and plane, and how often the intervals hold the truth.

A camera pose per view (inclination x roll about the optical axis, looking at a target)
gives the flange pose through the true mount; the model (:class:`PlaneModel`) gives the
camera-frame plane at the truth; Gaussian noise of the stated covariance is added to
it, and the flange pose the arm "reads back" gets read-back noise that may differ from
what the estimator is told (unmodelled noise). ``benchmarks/handeye_coverage.py`` and
the tests count how often the 95 % mount intervals contain the truth (ADR 0030).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cellcal.core.geometry.planes import Plane
from cellcal.core.handeye.estimator import estimate_mount, rpy_with_sigma_deg
from cellcal.core.handeye.model import PlaneModel, PlaneObservation, tangent_basis
from cellcal.core.handeye.noise import MAX_INTERVAL_SCALE, normal_z
from cellcal.devices.pose import Pose

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
#: The six ``[mount]`` values whose intervals are counted.
MOUNT_VALUES = ("x", "y", "z", "roll", "pitch", "yaw")


@dataclass(frozen=True)
class Scenario:
    """A true mount and plane, the configured ones, the views and the noise of the observations.

    Attributes:
        true_mount, nominal_mount: ``T_flange_camera`` as it is and as configured.
        true_plane, nominal_plane: The base-frame plane as it is and as configured.
        flanges: The true flange poses of the views.
        normal_sigma_rad: 1-sigma of the measured normal across itself, per axis, rad.
        offset_sigma_m: 1-sigma of the measured offset, m.
        correlation: Correlation of the first normal component with the offset.
        arm_translation_sigma_m: True 1-sigma of the arm's position read-back per axis, m.
        arm_rotation_sigma_rad: True 1-sigma of its orientation read-back per axis, rad.
        depth_scale_error: The camera's true depth scale error, common to every view (0.01: every
            measured offset 1 % long), relative.
        scale_allowance: The camera's stated 1-sigma scale allowance: each observation carries it as its
            ``scale`` systematic shift (and in its total covariance, as a full-frame fit would), relative.
    """

    true_mount: Pose
    nominal_mount: Pose
    true_plane: Plane
    nominal_plane: Plane
    flanges: tuple[Pose, ...]
    normal_sigma_rad: float = 5e-5
    offset_sigma_m: float = 2e-5
    correlation: float = 0.3
    arm_translation_sigma_m: float = 2.5e-5
    arm_rotation_sigma_rad: float = 0.0
    depth_scale_error: float = 0.0
    scale_allowance: float = 0.0

    def with_arm_noise(self, translation_sigma_m: float, rotation_sigma_rad: float) -> Scenario:
        """The same views with other (true) arm read-back noise."""
        return dataclasses.replace(self, arm_translation_sigma_m=translation_sigma_m,
                                   arm_rotation_sigma_rad=rotation_sigma_rad)


def camera_views(mount: Pose, target_m: Sequence[float], height_m: float, inclinations_deg: Sequence[float],
                 rolls_deg: Sequence[float], azimuths_deg: Sequence[float] = (0.0,)) -> tuple[Pose, ...]:
    """Flange poses whose camera looks down at ``target_m`` from ``height_m``, every inclination x roll x azimuth.

    The camera starts looking straight down (its x along the base x), is tilted about the base
    y axis so its optical axis makes the inclination with a horizontal plane, rolled about its
    optical axis, and turned about the vertical through the target by the azimuth (which leaves
    the plane as the camera sees it unchanged); the flange is the camera times the inverse mount.
    """
    from scipy.spatial.transform import Rotation

    down = Rotation.from_euler("x", math.pi)  # optical axis (camera z) along -z of the base
    target = np.asarray(target_m, dtype=np.float64)
    flanges = []
    for incl in inclinations_deg:
        tilt = Rotation.from_euler("y", math.radians(90.0 - incl))  # optical axis off the vertical
        for roll in rolls_deg:
            for azimuth in azimuths_deg:
                turn = Rotation.from_euler("z", math.radians(azimuth))  # about the vertical through the target
                rot = turn * tilt * down * Rotation.from_euler("z", math.radians(roll))  # roll about the optical axis
                camera = Pose(rot, target - height_m * rot.apply([0.0, 0.0, 1.0]))
                flanges.append(camera @ mount.inv())
    return tuple(flanges)


def sim_scenario(*, true_mount: Pose | None = None, nominal_mount: Pose | None = None) -> Scenario:
    """The hand-eye sim cell's geometry: mount 5.8 mm / 0.98 deg off the configured one, table tilted and 1.2 mm high.

    Eight views (inclinations 80 and 65 deg, rolls 0/90/180/270 deg) of the target 0.3 m in
    front of the base from 0.45 m, as ``configs/sim_handeye.toml`` plans them.
    """
    from scipy.spatial.transform import Rotation

    nominal = nominal_mount or Pose.from_xyz_rpy([0.0, 0.04, 0.06], np.radians([0.0, 0.0, 90.0]))
    truth = true_mount or Pose.from_xyz_rpy([0.003, 0.036, 0.063], np.radians([0.6, -0.5, 90.6]))
    table = Plane.from_point_normal([0.0, 0.0, 0.0], [0.0, 0.0, 1.0])
    true_table = Plane.from_point_normal([0.0, 0.0, 0.0012], Rotation.from_rotvec([3e-4, -2e-4, 0.0]).apply([0, 0, 1]))
    flanges = camera_views(truth, [0.3, 0.0, 0.0], 0.45, (80.0, 65.0), (0.0, 90.0, 180.0, 270.0))
    return Scenario(truth, nominal, true_table, table, flanges)


def observations(scenario: Scenario, rng: np.random.Generator | None) -> list[PlaneObservation]:
    """One noisy observation per view, carrying the plane's stated covariance (``rng=None``: no noise)."""
    from scipy.spatial.transform import Rotation

    s = scenario
    true = PlaneModel(s.true_mount, s.true_plane)
    normals, offsets = true.predict(np.zeros(9), list(s.flanges))  # the exact planes in the camera frames
    out = []
    for flange, n, offset in zip(s.flanges, normals, offsets, strict=True):
        if offset < 0:
            n, offset = -n, -offset  # normal toward the camera
        # two axes across the normal, built without a LAPACK call: an SVD's basis (and so the noise drawn along
        # it) differs with the BLAS kernel, and every figure drawn from these frames with it
        across = tangent_basis(n)
        c3 = np.diag([s.normal_sigma_rad**2, s.normal_sigma_rad**2, s.offset_sigma_m**2])
        c3[0, 2] = c3[2, 0] = s.correlation * s.normal_sigma_rad * s.offset_sigma_m
        m = np.zeros((4, 3))
        m[:3, :2] = across
        m[3, 2] = 1.0
        cov = m @ c3 @ m.T  # (normal, offset) covariance of the plane fit
        offset = offset * (1.0 + s.depth_scale_error)  # the camera's common scale error
        read = flange
        if rng is not None:
            # the plane fit's error; the Cholesky factor, unlike the default SVD, is unique: the same draws on any BLAS
            step = rng.multivariate_normal(np.zeros(3), c3, method="cholesky")
            n = n + across @ step[:2]
            n = n / np.linalg.norm(n)
            offset = offset + step[2]
            turn = Rotation.from_rotvec(rng.normal(0.0, s.arm_rotation_sigma_rad, 3))  # read-back error, base frame
            read = Pose(turn * flange.rotation, flange.translation + rng.normal(0.0, s.arm_translation_sigma_m, 3))
        if s.scale_allowance > 0:  # the allowance as a full-frame fit states it: total, noise, shift
            shift = s.scale_allowance * float(offset)
            total = cov.copy()
            total[3, 3] += shift * shift
            out.append(PlaneObservation(read, n, float(offset), total, cov, {"scale": (np.zeros(3), shift)}))
        else:
            out.append(PlaneObservation(read, n, float(offset), cov))
    return out


@dataclass(frozen=True)
class Trial:
    """One estimate against the truth.

    Attributes:
        error: Estimate minus truth of the six ``[mount]`` values (m, m, m, deg, deg, deg).
        sigma: Their 1-sigma as the intervals use it; sigma_absolute: with the stated noise as it is.
        z: Half-width of the intervals in sigmas; z_absolute: the normal quantile.
        interval_scale: Factor the residuals put on the sigmas.
        verdict: The noise test's verdict; refused: the gate that refused the fit, or None.
    """

    error: FloatArray
    sigma: FloatArray
    sigma_absolute: FloatArray
    z: float
    z_absolute: float
    interval_scale: float
    verdict: str
    refused: str | None

    @property
    def inside(self) -> BoolArray:
        """Whether each interval holds the truth (False for a refused fit)."""
        if self.refused:
            return np.zeros(len(MOUNT_VALUES), dtype=np.bool_)
        inside: BoolArray = np.abs(self.error) <= self.z * self.sigma
        return inside

    @property
    def inside_absolute(self) -> BoolArray:
        """Whether each interval of the stated noise, unscaled and never refused, holds the truth."""
        inside: BoolArray = np.abs(self.error) <= self.z_absolute * self.sigma_absolute
        return inside


def trial(scenario: Scenario, rng: np.random.Generator, *, max_interval_scale: float = MAX_INTERVAL_SCALE,
          **options: Any) -> Trial:
    """Estimate from one draw of observations and compare with the truth.

    ``options`` go to :func:`estimate_mount` (``given``, ``given_sigma``, the stated arm noise,
    ``noise_test_level``). The fit runs without the ``noise_model`` refusal so that the absolute
    intervals are known in every run; a run is counted as refused exactly when
    :func:`~cellcal.core.handeye.noise.check_noise` would refuse it at ``max_interval_scale``.
    """
    est = estimate_mount(observations(scenario, rng), scenario.nominal_mount, scenario.nominal_plane,
                         max_interval_scale=math.inf, **options)
    truth = scenario.true_mount
    rpy, rpy_sigma = est.rpy_and_sigma_deg()
    _, rpy_sigma_abs = rpy_with_sigma_deg(est.mount, est.absolute_covariance[:3, :3])  # type: ignore[index]
    rpy_err = np.remainder(rpy - np.degrees(truth.as_xyz_rpy()[3:]) + 180.0, 360.0) - 180.0  # wrapped, deg
    error = np.concatenate([est.mount.translation - truth.translation, rpy_err])
    t_sigma_abs = np.sqrt(np.diag(est.absolute_covariance)[3:6])  # type: ignore[arg-type]
    refused = ("noise_model" if est.noise.verdict == "scaled" and est.interval_scale > max_interval_scale
               else None)
    return Trial(error, np.concatenate([est.translation_sigma_m, rpy_sigma]),
                 np.concatenate([t_sigma_abs, rpy_sigma_abs]), est.z, normal_z(est.confidence), est.interval_scale,
                 est.noise.verdict, refused)


@dataclass(frozen=True)
class Coverage:
    """How often the intervals of many trials held the truth.

    Attributes:
        runs: Trials run.
        refused: Trials refused by a gate.
        inside: Fraction of the runs whose interval held the truth, per ``[mount]`` value (refusals count as misses).
        inside_accepted: The same over the accepted runs only (NaN if none).
        inside_absolute: The fraction with the stated noise's intervals, unscaled and never refused (before).
        scaled: Fraction of the runs whose intervals were scaled; median_scale: their median scale.
    """

    runs: int
    refused: int
    inside: FloatArray
    inside_accepted: FloatArray
    inside_absolute: FloatArray
    scaled: float
    median_scale: float

    @property
    def refusal_rate(self) -> float:
        """Fraction of the runs refused."""
        return self.refused / self.runs

    @property
    def covered_or_refused(self) -> FloatArray:
        """Per ``[mount]`` value: the fraction of runs that held the truth or were refused."""
        return self.inside + self.refusal_rate


def coverage(scenario: Scenario, runs: int, seed: int, **options: Any) -> Coverage:
    """Run ``runs`` trials of ``scenario`` from one seed (``options`` as for :func:`trial`)."""
    if runs < 1:
        raise ValueError(f"coverage needs at least 1 run, got {runs}")
    rng = np.random.default_rng(seed)
    trials = [trial(scenario, rng, **options) for _ in range(runs)]
    refused = np.array([t.refused is not None for t in trials])
    inside = np.array([t.inside for t in trials])
    accepted = inside[~refused].mean(axis=0) if (~refused).any() else np.full(len(MOUNT_VALUES), math.nan)
    scales = np.array([t.interval_scale for t in trials])
    return Coverage(runs, int(refused.sum()), inside.mean(axis=0), accepted,
                    np.array([t.inside_absolute for t in trials]).mean(axis=0), float(np.mean(scales > 1.0)),
                    float(np.median(scales)))


__all__ = ["MOUNT_VALUES", "Coverage", "Scenario", "Trial", "camera_views", "coverage", "observations",
           "sim_scenario", "trial"]
