"""The plan within the arm's reach: its class, generated views it can take, and the check that names a pose.

A ``[plan]`` generated from heights, inclination and azimuths asks for exact camera
views; the flange pose of a view is the camera pose times the inverse ``[mount]``. A
camera mounted even 1 deg off the flange axes then asks a 5-axis arm for a tool axis
tilted sideways, which it cannot take (docs/adr/0034-handeye-loop-and-board.md). Such a
pose is replaced by the nearest one the arm can take: the flange pitch and roll as
asked, the tool back in the base's vertical plane, and the optical axis still meeting
the plane where the asked view meets it, at the same distance (its direction moves by
at most the sideways tilt). Explicit ``[[plan.poses]]`` are flange poses as the user
gave them: they are checked, never changed.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from cellcal.core.calibration.config import CellConfig, plan_flange_poses
from cellcal.devices.errors import SafetyError
from cellcal.devices.geometry.reach import orientation_violation, radial_flange_rotation, sideways_tilt_rad
from cellcal.devices.pose import Pose
from cellcal.devices.safety import format_pose

if TYPE_CHECKING:
    from scipy.spatial.transform import Rotation

#: Arm backends that are 5-axis xArms unless their section says otherwise. (``xarm-emulated`` moves
#: the simulated arm behind its emulator, which refuses what its own ``reach`` key says: "any" unless set.)
XARM_BACKENDS = ("xarm",)
#: A generated view is moved within reach only when its tool axis is tilted sideways by at most this
#: (rad): the small tilts of a mount a little off the flange axes. A larger one is a plan the arm
#: cannot follow (the paper's inclination about the wrong axis), refused by name, never silently
#: replaced by a view of another inclination.
MAX_MOVE_RAD = math.radians(2.0)
#: Iterations of the base-yaw root search, and its tolerance (rad).
MAX_ITERATIONS = 100
YAW_TOLERANCE_RAD = 1e-9


def arm_reach(config: CellConfig) -> str:
    """The arm class of the configuration: ``[handeye] reach``, else the arm's own (``[arm] reach`` / axes)."""
    if config.handeye.reach is not None:
        return config.handeye.reach
    arm: Mapping[str, Any] = config.arm_section
    if isinstance(arm.get("reach"), str):
        return str(arm["reach"])
    if arm.get("backend") in XARM_BACKENDS and int(arm.get("axes", 5)) == 5:
        return "xarm5"
    return "any"


def reach_problem(pose: Pose, reach: str) -> str | None:
    """Why an arm of class ``reach`` cannot take ``pose`` (None when it can)."""
    return orientation_violation(pose, reach)


def check_reach(config: CellConfig, poses: Sequence[Pose]) -> None:
    """Refuse the first pose the configuration's arm class cannot take (nothing moves).

    Raises:
        SafetyError: Naming the pose (1-based plan index), its target and why.
    """
    reach = arm_reach(config)
    for i, pose in enumerate(poses):
        why = reach_problem(pose, reach)
        if why is not None:
            raise SafetyError(f"plan pose {i + 1} ({format_pose(pose)}) is out of reach of a '{reach}' arm: {why}")


def nearest_radial_pose(pose: Pose, mount: Pose, plane_point_m: np.ndarray, plane_normal: np.ndarray) -> Pose:
    """The pose a 5-axis arm can take nearest ``pose``: same pitch and roll, the view's plane point kept.

    Args:
        pose: The asked flange pose, ``T_base_flange``.
        mount: ``T_flange_camera``.
        plane_point_m: A point of the plane the camera looks at, base frame, m.
        plane_normal: The plane's normal, base frame.

    Returns:
        ``pose`` itself when its optical axis misses the plane or the yaw does not converge.
    """
    camera = pose @ mount
    n = np.asarray(plane_normal, float) / np.linalg.norm(plane_normal)
    axis = camera.apply_vector([0.0, 0.0, 1.0])
    along = float(axis @ n)
    if abs(along) < 1e-9:
        return pose
    height = float((np.asarray(plane_point_m, float) - camera.translation) @ n) / along  # camera to plane, m
    if height <= 0:
        return pose
    target = camera.translation + height * axis
    mount_t = np.array(mount.translation, dtype=float)

    def place(yaw: float) -> Pose:  # the radial pose nearest the asked one at base yaw ``yaw``, viewing ``target``
        rot = radial_flange_rotation(yaw, *nearest_pitch_roll(pose.rotation, yaw)).rotation
        optical = (rot * mount.rotation).apply([0.0, 0.0, 1.0])
        return Pose(rot, target - height * optical - rot.apply(mount_t))

    def yaw_error(yaw: float) -> float:  # the placed flange's own base yaw minus the yaw it was placed at, rad
        flange = place(yaw).translation
        return math.remainder(math.atan2(flange[1], flange[0]) - yaw, 2 * math.pi)

    from scipy.optimize import root_scalar

    start = math.atan2(pose.translation[1], pose.translation[0])
    found = root_scalar(yaw_error, x0=start, x1=start + 1e-4, method="secant", xtol=1e-14, maxiter=MAX_ITERATIONS)
    if not found.converged or abs(yaw_error(found.root)) > YAW_TOLERANCE_RAD:
        return pose
    return place(found.root)


def nearest_pitch_roll(rotation: Rotation, yaw_rad: float) -> tuple[float, float]:
    """(pitch, roll) of :func:`radial_flange_rotation` at ``yaw_rad`` nearest ``rotation`` (rad)."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    # T = Rz(j1) Ry(pitch) Rz(-roll) Rx(pi): a start read off the ZYZ angles of Rz(-j1) T Rx(pi)
    a, b, c = (Rotation.from_euler("z", -yaw_rad) * rotation * Rotation.from_euler("x", math.pi)).as_euler("ZYZ")
    start = [b, -(a + c)] if abs(math.remainder(a, 2 * math.pi)) < math.pi / 2 else [-b, -(a + c + math.pi)]
    fit = least_squares(lambda v: (radial_flange_rotation(yaw_rad, v[0], v[1]).rotation.inv() * rotation).as_rotvec(),
                        start, xtol=1e-15, ftol=1e-15, gtol=1e-15)
    return float(fit.x[0]), float(fit.x[1])


def within_reach(config: CellConfig, poses: Sequence[Pose]) -> list[Pose]:
    """``poses`` with each one the arm class cannot take, by a small sideways tilt, replaced by the nearest one it can.

    A pose tilted sideways by more than :data:`MAX_MOVE_RAD` is left as asked, for
    :func:`check_reach` to refuse by name.
    """
    reach = arm_reach(config)
    if config.reference is None:
        return list(poses)
    mount = config.mount.pose()
    point = np.asarray(config.reference.plane_point_m, float)
    normal = np.asarray(config.reference.plane_normal, float)
    return [nearest_radial_pose(p, mount, point, normal)
            if reach_problem(p, reach) is not None and sideways_tilt_rad(p) <= MAX_MOVE_RAD else p for p in poses]


def reachable_plan_poses(config: CellConfig) -> list[Pose]:
    """The flange poses of ``[plan]``: generated views moved within the arm's reach, explicit poses as given."""
    poses = plan_flange_poses(config)
    return poses if config.plan.poses else within_reach(config, poses)


__all__ = ["MAX_MOVE_RAD", "XARM_BACKENDS", "arm_reach", "check_reach", "nearest_radial_pose", "reach_problem",
           "reachable_plan_poses", "within_reach"]
