"""The automatic hand-eye plan (``--plan auto``): inclinations x rolls about the tool axis.

Every mount parameter is observable from plane views once the plane normal, seen from
the flange, takes directions off one cone (ADR 0018). The plan therefore views the
target at each ``[handeye] inclinations_deg`` and, at each, rolls the flange about the
tool axis by every ``rolls_deg``. The tool is pitched only within the vertical plane
through the base axis (toward the base), which every arm class can do, a 5-axis xArm
included; the flange yaw that puts it there is found by a fixed-point iteration, so the
optical axis meets the target exactly. Every pose is checked against ``[safety]`` and
the arm class before anything moves.
"""

from __future__ import annotations

import math

import numpy as np

from cellcal.core.calibration.config import CellConfig
from cellcal.core.calibration.reach import XARM_BACKENDS, arm_reach, check_reach, reachable_plan_poses
from cellcal.devices.errors import ConfigError
from cellcal.devices.geometry.reach import radial_flange_rotation
from cellcal.devices.pose import Pose

#: Iterations of the flange-yaw fixed point, and its tolerance (rad).
MAX_ITERATIONS = 100
YAW_TOLERANCE_RAD = 1e-13


def view_pose(target_m: np.ndarray, height_m: float, inclination_rad: float, roll_rad: float,
              mount: Pose) -> Pose:
    """The flange pose whose camera's optical axis meets ``target_m`` at ``height_m``.

    The tool is pitched by ``pi/2 - inclination_rad`` toward the base within the vertical
    plane through the base axis and the flange, then rolled by ``roll_rad`` about its axis.

    Raises:
        ConfigError: If the flange yaw does not converge (target on the base axis).
    """
    pitch = math.pi / 2 - inclination_rad
    yaw = math.atan2(target_m[1], target_m[0])
    for _ in range(MAX_ITERATIONS):
        rot = radial_flange_rotation(yaw, pitch, roll_rad).rotation
        axis = (rot * mount.rotation).apply([0.0, 0.0, 1.0])  # optical axis in the base frame
        flange = target_m - height_m * axis - rot.apply(np.array(mount.translation))  # camera at target - h * axis
        new_yaw = math.atan2(flange[1], flange[0])
        step = math.remainder(new_yaw - yaw, 2 * math.pi)
        yaw = new_yaw
        if abs(step) < YAW_TOLERANCE_RAD:
            return Pose(radial_flange_rotation(yaw, pitch, roll_rad).rotation, flange)
    raise ConfigError("no flange yaw puts the tool in the base's vertical plane for this view (target "
                      f"{np.round(target_m, 3).tolist()} m too close to the base axis?)", key="handeye.target_m")


def auto_plan(config: CellConfig) -> list[Pose]:
    """The flange poses (base frame) of the automatic plan, in order.

    Raises:
        ConfigError: Without a ``[reference]`` plane that is horizontal enough to pitch toward.
        SafetyError: If a pose or move leaves ``[safety]`` or the arm class cannot take a pose.
    """
    if config.reference is None:
        raise ConfigError("the automatic hand-eye plan needs a [reference] plane", source=config.source,
                          key="reference")
    he = config.handeye
    target = np.asarray(he.target_m if he.target_m is not None else config.plan.target_m, dtype=np.float64)
    # the view is built around the base's vertical: the reference normal must be (close to) vertical
    normal = np.asarray(config.reference.plane_normal, dtype=np.float64)
    if abs(normal[2]) / np.linalg.norm(normal) < math.cos(math.radians(5.0)):
        raise ConfigError("the automatic plan assumes a horizontal reference plane (normal within 5 deg of z); "
                          "use --plan config with explicit [[plan.poses]]", source=config.source,
                          key="reference.plane_normal")
    mount = config.mount.pose()
    poses = [view_pose(target, he.height_m, math.radians(incl), math.radians(roll), mount)
             for incl in he.inclinations_deg for roll in he.rolls_deg]
    check_plan(config, poses)
    return poses


def check_plan(config: CellConfig, poses: list[Pose]) -> None:
    """Check every pose against the arm class and every move against ``[safety]`` (nothing moves).

    Raises:
        SafetyError: Naming the first offending pose.
    """
    check_reach(config, poses)
    plan = config.plan
    config.safety_limits().check_plan(None, poses, plan.speed_m_s, plan.acceleration_m_s2)


def plan_poses(config: CellConfig, kind: str) -> list[Pose]:
    """The poses of ``--plan auto`` or ``--plan config`` (``[plan]`` as ``cellcal calibrate`` runs it), checked.

    Raises:
        ConfigError, SafetyError: As :func:`auto_plan` / :func:`check_plan`.
    """
    if kind == "auto":
        return auto_plan(config)
    poses = reachable_plan_poses(config)
    check_plan(config, poses)
    return poses


__all__ = ["XARM_BACKENDS", "arm_reach", "auto_plan", "check_plan", "plan_poses", "view_pose"]
