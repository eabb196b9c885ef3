"""``cellcal calibrate --dry-run``: every move the plan would make, with its safety and reach checks.

Nothing is connected, so nothing moves: the first move is checked at its target only,
every later one along its whole straight path as :class:`~cellcal.devices.safety.SafeArm`
checks it at run time (ADR 0008), and every target against the arm's class (``reach``),
as the run checks it before the first move (ADR 0034).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from cellcal.core.calibration.config import CellConfig
from cellcal.core.calibration.reach import arm_reach, check_reach, reach_problem, reachable_plan_poses
from cellcal.core.calibration.region import describe_region
from cellcal.devices.pose import Pose
from cellcal.devices.safety import SafetyLimits, format_pose


@dataclass(frozen=True)
class MoveCheck:
    """The safety checks of one planned move.

    Attributes:
        index: 0-based plan index.
        target: Target flange pose, base frame.
        path_length_m: Straight-line flange travel from the previous pose, metres (None
            for the first move: the start pose is not known without the arm).
        min_standoff_m: Smallest camera distance to the reference plane along the
            checked path, metres (None without a reference plane).
        problems: Violated rules (empty when the move is safe).
    """

    index: int
    target: Pose
    path_length_m: float | None
    min_standoff_m: float | None
    problems: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        """Whether every check passed."""
        return not self.problems


def check_moves(limits: SafetyLimits, poses: Sequence[Pose], speed_m_s: float, acceleration_m_s2: float,
                start: Pose | None = None, reach: str = "any") -> list[MoveCheck]:
    """Check every move of a plan (all of them, not stopping at the first violation).

    Args:
        limits: The safety envelope.
        poses: Target flange poses, base frame.
        speed_m_s: Planned tool speed, m/s.
        acceleration_m_s2: Planned tool acceleration, m/s^2.
        start: The arm's pose before the first move (None: unknown, the first move is checked at its target).
        reach: The arm class every target must suit (``any``, ``xarm5``).
    """
    out = []
    previous = start
    for i, target in enumerate(poses):
        _flange, camera = limits.path(previous, target)
        standoff = None
        if limits.plane_point_m is not None and limits.plane_normal is not None:
            n = np.asarray(limits.plane_normal, float)
            # smallest signed distance of the camera path to the plane, along its unit normal, m
            standoff = float(np.min((camera - np.asarray(limits.plane_point_m, float)) @ (n / np.linalg.norm(n))))
        # straight-line flange travel, m (unknown for the first move: no start pose without the arm)
        length = None if previous is None else float(np.linalg.norm(target.translation - previous.translation))
        why = reach_problem(target, reach)
        out.append(MoveCheck(i, target, length, standoff,
                             ([] if why is None else [f"out of reach of a '{reach}' arm: {why}"])
                             + limits.violations(previous, target, speed_m_s, acceleration_m_s2)))
        previous = target
    return out


def describe(check: MoveCheck, n_moves: int, limits: SafetyLimits, speed_m_s: float,
             acceleration_m_s2: float, reach: str = "any") -> str:
    """One line: pose index, target (m, deg), path length and the checks passed (``reach``: the arm class)."""
    path = "n/a (from the arm's current pose, checked when the run starts)" if check.path_length_m is None \
        else f"{check.path_length_m:.4f} m"
    head = f"move {check.index + 1}/{n_moves}: {format_pose(check.target)}; path {path}"
    if not check.ok:
        return f"{head}; REJECTED: " + "; ".join(check.problems)
    checks = ["workspace ok"]
    if check.min_standoff_m is not None:
        checks.append(f"standoff ok ({check.min_standoff_m:.4f} m >= {limits.min_standoff_m:.4f} m)")
    else:
        checks.append("standoff not checked (no [reference] plane)")
    checks.append(f"speed ok ({speed_m_s:.4g} <= {limits.max_speed_m_s:.4g} m/s)")
    checks.append(f"acceleration ok ({acceleration_m_s2:.4g} <= {limits.max_acceleration_m_s2:.4g} m/s^2)")
    checks.append("reach not limited ('any' arm)" if reach == "any" else f"reach ok ('{reach}' arm)")
    return f"{head}; checks: " + ", ".join(checks)


def describe_search(config: CellConfig) -> str:
    """Where the full-frame fit will look (human text: degrees, millimetres): its region and expected plane."""
    if "full_frame" not in config.plan.methods:
        return "no full-frame fit"
    ref = config.search_reference
    near = "no expected plane" if ref is None else \
        f"near [reference] within {ref.search_tolerance_deg:g} deg / {1000 * ref.search_tolerance_m:g} mm"
    return f"full-frame fit over the {describe_region(config.region)}, {near}"


def dry_run(config: CellConfig, emit: Callable[[str], None] = print) -> list[MoveCheck]:
    """Print every move of the plan with its checks; touch no device.

    The poses are those the run makes: generated views the arm class cannot take are
    moved within its reach (:mod:`cellcal.core.calibration.reach`), explicit ones are not.

    Returns:
        The checks of every move (all passed).

    Raises:
        SafetyError: After printing the moves up to the first offending one, naming it.
    """
    plan = config.plan
    limits = config.safety_limits()
    reach = arm_reach(config)
    poses = reachable_plan_poses(config)
    emit(f"dry run of {config.source} (cell '{config.cell.name}'): {len(poses)} moves at "
         f"{plan.speed_m_s:g} m/s, {plan.acceleration_m_s2:g} m/s^2; {describe_search(config)}; "
         "no device is connected, nothing moves")
    checks = check_moves(limits, poses, plan.speed_m_s, plan.acceleration_m_s2, reach=reach)
    for check in checks:
        emit(describe(check, len(poses), limits, plan.speed_m_s, plan.acceleration_m_s2, reach))
        if not check.ok:  # the reach and safety checks word the rejection, exactly as a real run would
            check_reach(config, poses[:check.index + 1])
            limits.check_plan(None, poses[:check.index + 1], plan.speed_m_s, plan.acceleration_m_s2)
            raise AssertionError("check_moves and SafetyLimits.check_plan disagree")  # same rules: unreachable
    emit(f"dry run OK: all {len(poses)} moves inside the safety envelope")
    return checks


__all__ = ["MoveCheck", "check_moves", "describe", "describe_search", "dry_run"]
