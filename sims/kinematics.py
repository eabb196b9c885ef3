"""The simulated arm's xArm-5-like chain and its kinematic errors (``[sim.arm_errors]``; issue #39, ADR 0055).

The chain (:func:`inverse_kinematics`, :func:`forward_position`) is the one the sim arm's
controller believes. A real arm's joint zeros and link lengths differ from its controller's
model by a little: the flange stands where the chain *with those errors* puts it at the
joint angles the controller computed for the commanded pose, so the pose it reports errs
smoothly with the pose and the same way every time it returns there (ISO 9283 absolute
accuracy, against the random repeatability). :class:`ArmErrors` is that difference: the
true flange pose is ``D(q) @ reported`` with ``D(q) = F_err(q) @ F_nom(q)^-1`` at the
joint angles ``q`` of the reported (nominal, noise-free) pose. Poses in the base frame,
metres, radians.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from cellcal.devices.pose import Pose

# xArm-5-like geometry, metres.
SHOULDER_HEIGHT_M = 0.267
UPPER_ARM_M = 0.2895
FOREARM_M = 0.3512
WRIST_TO_FLANGE_M = math.hypot(0.076, 0.097)
#: The chain's links in the order of ``[sim.arm_errors] link_errors_mm``.
LINKS_M = (SHOULDER_HEIGHT_M, UPPER_ARM_M, FOREARM_M, WRIST_TO_FLANGE_M)
#: Joints of the chain (J1 base yaw, J2 shoulder, J3 elbow, J4 wrist pitch, J5 flange roll).
JOINTS = 5


def _wrap_near(angle: float, reference: float) -> float:
    return angle + 2.0 * math.pi * round((reference - angle) / (2.0 * math.pi))


def inverse_kinematics(pose: Pose, previous: NDArray[np.float64] | None = None) -> NDArray[np.float64]:
    """Joint angles (rad, 5) of the simplified xArm-5-like chain for a flange pose.

    The chain: base yaw J1 about z; shoulder J2 at height 0.267 m, upper arm 0.2895 m,
    forearm 0.3512 m (J3), wrist pitch J4, and a rigid wrist-to-flange link of 0.1232 m
    along the tool axis, flange roll J5 about the tool axis. ``J1 = atan2(y, x)``; the
    tool axis is projected into the arm's vertical plane (the 5-DoF constraint) to give
    the wrist point and the tool pitch; J2/J3 solve the planar two-link problem (elbow
    up, the reach clamped to the links' range), J4 makes up the tool pitch, J5 is the
    residual roll. Angles: J2 from vertical (forward positive), J3 and J4 relative to
    the previous link.

    Args:
        pose: Flange pose in the base frame.
        previous: Previous joint reading; J1 and J5 are unwrapped towards it.
    """
    p = pose.translation
    rmat = pose.rotation_matrix
    j1 = math.atan2(p[1], p[0]) if math.hypot(p[0], p[1]) > 1e-9 else 0.0
    e_r = np.array([math.cos(j1), math.sin(j1), 0.0])
    a = rmat[:, 2]  # tool (approach) axis
    a_r, a_z = float(a @ e_r), float(a[2])
    alpha4 = math.atan2(a_r, a_z) if math.hypot(a_r, a_z) > 1e-9 else math.pi  # tool direction from +z
    r = float(p @ e_r)
    w_r = r - WRIST_TO_FLANGE_M * math.sin(alpha4)
    w_z = float(p[2]) - WRIST_TO_FLANGE_M * math.cos(alpha4)
    dr, dz = w_r, w_z - SHOULDER_HEIGHT_M
    lo, hi = abs(UPPER_ARM_M - FOREARM_M) + 1e-6, UPPER_ARM_M + FOREARM_M - 1e-6
    dist = min(max(math.hypot(dr, dz), lo), hi)
    cos_elbow = (dist**2 - UPPER_ARM_M**2 - FOREARM_M**2) / (2.0 * UPPER_ARM_M * FOREARM_M)
    j3 = math.acos(max(-1.0, min(1.0, cos_elbow)))  # elbow bend (forearm pitched down relative)
    beta = math.atan2(dr, dz)  # direction shoulder->wrist from +z
    gamma = math.atan2(FOREARM_M * math.sin(j3), UPPER_ARM_M + FOREARM_M * math.cos(j3))
    j2 = beta - gamma
    j4 = alpha4 - j2 - j3
    # Rz(j1), then Ry(alpha4) about the fixed y axis: Ry(alpha4) @ Rz(j1) (scipy's extrinsic "zy")
    r04 = (Pose.from_xyz_rotvec(np.zeros(3), (0.0, alpha4, 0.0))
           @ Pose.from_xyz_rotvec(np.zeros(3), (0.0, 0.0, j1))).rotation_matrix
    resid = r04.T @ rmat
    j5 = math.atan2(resid[1, 0], resid[0, 0])
    j4 = math.remainder(j4, 2.0 * math.pi)
    if previous is not None and len(previous) >= 5:
        j1 = _wrap_near(j1, float(previous[0]))
        j5 = _wrap_near(j5, float(previous[4]))
    return np.array([j1, j2, j3, j4, j5], dtype=np.float64)


def forward_position(joints: NDArray[np.float64]) -> NDArray[np.float64]:
    """Flange position (m, base frame) of the simplified chain for joints J1..J4 (rad)."""
    return _chain_position(joints, LINKS_M)


def _chain_position(joints: NDArray[np.float64], links: tuple[float, ...]) -> NDArray[np.float64]:
    """Flange position of the chain with link lengths ``links`` (shoulder height, upper arm, forearm, wrist)."""
    j1, j2, j3, j4 = (float(v) for v in joints[:4])
    h, l2, l3, l4 = links
    r = l2 * math.sin(j2) + l3 * math.sin(j2 + j3) + l4 * math.sin(j2 + j3 + j4)
    z = h + l2 * math.cos(j2) + l3 * math.cos(j2 + j3) + l4 * math.cos(j2 + j3 + j4)
    return np.array([r * math.cos(j1), r * math.sin(j1), z])


def _rz(angle: float) -> NDArray[np.float64]:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _ry(angle: float) -> NDArray[np.float64]:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


@dataclass(frozen=True)
class ArmErrorsConfig:
    """The sim arm's kinematic errors, the ``[sim.arm_errors]`` table (on by default; issue #39, ADR 0055).

    The defaults are small, fixed, unlike-signed errors of an uncalibrated arm: across the
    hand-eye and calibrate plans of the shipped sim configs they move the flange by about
    0.5 mm and turn it by about 0.05 deg (RMS over :func:`workspace_sample`: 0.48 mm,
    0.049 deg; ADR 0055). ``enabled = false`` gives the
    ideal arm of before (bit-identical poses).
    """

    enabled: bool = field(default=True, metadata={"doc": "false: the ideal arm (the reported pose is the true one)"})
    joint_offsets_deg: tuple[float, float, float, float, float] = field(
        default=(0.025, 0.03, -0.02, 0.025, -0.01), metadata={
            "ge": -5.0, "le": 5.0, "doc": "joint zero offsets J1..J5 (true minus the controller's), degrees"})
    link_errors_mm: tuple[float, float, float, float] = field(
        default=(0.3, -0.35, 0.3, 0.2), metadata={
            "ge": -50.0, "le": 50.0,
            "doc": "link length errors (shoulder height, upper arm, forearm, wrist to flange; true minus nominal), mm"})

    def errors(self) -> ArmErrors | None:
        """The error model, or None when switched off or all zero."""
        if not self.enabled or not (any(self.joint_offsets_deg) or any(self.link_errors_mm)):
            return None
        return ArmErrors(np.radians(np.asarray(self.joint_offsets_deg, dtype=np.float64)),
                         np.asarray(self.link_errors_mm, dtype=np.float64) / 1000.0)


class ArmErrors:
    """Joint zero offsets and link length errors of the chain: maps a reported flange pose to the true one.

    Args:
        joint_offsets_rad: (5,) true minus believed joint zeros, rad.
        link_errors_m: (4,) true minus nominal link lengths (:data:`LINKS_M` order), m.
    """

    def __init__(self, joint_offsets_rad: NDArray[np.float64], link_errors_m: NDArray[np.float64]) -> None:
        self.joint_offsets_rad = np.asarray(joint_offsets_rad, dtype=np.float64).reshape(JOINTS)
        self.link_errors_m = np.asarray(link_errors_m, dtype=np.float64).reshape(len(LINKS_M))
        self._links = tuple(float(v) for v in np.asarray(LINKS_M) + self.link_errors_m)
        self._last: tuple[Pose, Pose] | None = None

    def delta(self, joints: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``D(q) = F_err(q) @ F_nom(q)^-1`` as (rotation matrix, translation) at the joints ``q`` (rad)."""
        q = np.asarray(joints, dtype=np.float64)
        d = self.joint_offsets_rad
        alpha = float(q[1] + q[2] + q[3])
        r_nom = _rz(float(q[0])) @ _ry(alpha)  # the J5 roll cancels: F_err F_nom^-1 holds Rz(d5) between
        r_err = _rz(float(q[0] + d[0])) @ _ry(alpha + float(d[1] + d[2] + d[3])) @ _rz(float(d[4]))
        rot = r_err @ r_nom.T
        p_nom = _chain_position(q, LINKS_M)
        p_err = _chain_position(q + d, self._links)
        return rot, p_err - rot @ p_nom

    def true_pose(self, reported: Pose) -> Pose:
        """The true flange pose where the controller believes (and, without noise, reports) ``reported``.

        The last answer is kept: a standing arm hands out the same pose object, which maps to the same truth.
        """
        last = self._last
        if last is not None and last[0] is reported:
            return last[1]
        rot, shift = self.delta(inverse_kinematics(reported))
        true = Pose.from_matrix(_compose(rot, shift, reported.as_matrix()))
        self._last = (reported, true)
        return true

    def error_of(self, reported: Pose) -> tuple[float, float]:
        """How far the true flange is from ``reported``: (distance, m; angle, rad)."""
        true = self.true_pose(reported)
        return (float(np.linalg.norm(true.translation - reported.translation)),
                float(np.linalg.norm(reported.rotvec_to(true))))


def workspace_sample() -> list[Pose]:
    """Flange poses across the sim arm's usual workspace, where :meth:`ArmErrors.rms_error` states its figures.

    Tool down and tilted up to 20 deg, radius 0.25-0.55 m, azimuth -60..60 deg, flange 0.25-0.55 m high:
    where the hand-eye and calibrate plans of the shipped sim configs stand.
    """
    poses = []
    for radius in (0.25, 0.4, 0.55):
        for azimuth in np.radians((-60.0, -20.0, 20.0, 60.0)):
            for height in (0.25, 0.4, 0.55):
                for tilt in ((0.0, 0.0), (20.0, 0.0), (0.0, 20.0), (-20.0, -20.0)):
                    xyz = (radius * math.cos(azimuth), radius * math.sin(azimuth), height)
                    poses.append(Pose.from_xyz_rpy(np.asarray(xyz), np.radians((180.0 + tilt[0], tilt[1], 0.0))))
    return poses


def rms_error(errors: ArmErrors | None, poses: list[Pose] | None = None) -> tuple[float, float]:
    """RMS (distance, m; angle, rad) of the true flange from the reported one over ``poses``
    (default :func:`workspace_sample`); zeros for the ideal arm."""
    if errors is None:
        return 0.0, 0.0
    found = np.array([errors.error_of(p) for p in (workspace_sample() if poses is None else poses)])
    return float(np.sqrt(np.mean(found[:, 0] ** 2))), float(np.sqrt(np.mean(found[:, 1] ** 2)))


def _compose(rot: NDArray[np.float64], shift: NDArray[np.float64], matrix: NDArray[np.float64]) -> NDArray[np.float64]:
    out = np.eye(4)
    out[:3, :3] = rot @ matrix[:3, :3]
    out[:3, 3] = rot @ matrix[:3, 3] + shift
    return out


def random_arm_errors(rng: np.random.Generator, *, joint_sigma_deg: float = 0.025,
                      link_sigma_mm: float = 0.3) -> ArmErrorsConfig:
    """A random ``[sim.arm_errors]`` table: each joint offset and link error drawn normal with these sigmas.

    The defaults are the magnitude of :class:`ArmErrorsConfig`'s defaults (benchmarks draw an arm per seed).
    """
    joints = tuple(float(v) for v in rng.normal(0.0, joint_sigma_deg, JOINTS))
    links = tuple(float(v) for v in rng.normal(0.0, link_sigma_mm, len(LINKS_M)))
    return ArmErrorsConfig(True, joints, links)  # type: ignore[arg-type]


__all__ = ["FOREARM_M", "JOINTS", "LINKS_M", "SHOULDER_HEIGHT_M", "UPPER_ARM_M", "WRIST_TO_FLANGE_M", "ArmErrors",
           "ArmErrorsConfig", "forward_position", "inverse_kinematics", "random_arm_errors", "rms_error",
           "workspace_sample"]
