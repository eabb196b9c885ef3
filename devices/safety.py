"""The safety envelope every arm command goes through.

:class:`SafeArm` wraps any :class:`RobotArm` and checks each ``move_linear`` against
:class:`SafetyLimits` before anything is sent to the backend; a violation raises
:class:`SafetyError` naming the offending pose, and the arm is not moved.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from .arm import RobotArm
from .arrival import MAX_ANGLE_TOLERANCE_RAD, MAX_POSITION_TOLERANCE_M, format_pose
from .errors import SafetyError
from .forwarding import ForwardingArm
from .pose import Pose

__all__ = ["MIN_PATH_SAMPLES", "PATH_SAMPLES_PER_M", "SafeArm", "SafetyLimits", "format_pose"]

#: Points per metre (and at least this many per move) at which a path is checked.
PATH_SAMPLES_PER_M = 200
MIN_PATH_SAMPLES = 16


@dataclass(frozen=True)
class SafetyLimits:
    """The motion envelope, in the robot base frame.

    Attributes:
        workspace_min_m: Lower corner of the allowed box for flange and camera, metres.
        workspace_max_m: Upper corner, metres.
        max_speed_m_s: Maximum commanded tool speed, m/s.
        max_acceleration_m_s2: Maximum commanded tool acceleration, m/s².
        min_standoff_m: Minimum distance from the camera origin to the measuring plane, m
            (checked only when ``plane_point_m`` / ``plane_normal`` are given).
        plane_point_m: A point on the measuring plane, base frame, metres.
        plane_normal: Normal of the measuring plane, base frame (need not be unit);
            the camera must stay on the side it points to.
        mount: Camera pose in the flange frame (hand-eye transform).
        arrival_tolerance_m: How close a finished move must read back to its target, m;
            None keeps the arm's own default (see :class:`~cellcal.devices.arrival.ArrivalTolerance`).
        arrival_tolerance_rad: The same for the orientation, rad; None keeps the arm's default.
    """

    workspace_min_m: tuple[float, float, float]
    workspace_max_m: tuple[float, float, float]
    max_speed_m_s: float
    max_acceleration_m_s2: float
    min_standoff_m: float = 0.0
    plane_point_m: tuple[float, float, float] | None = None
    plane_normal: tuple[float, float, float] | None = None
    mount: Pose = field(default_factory=Pose.identity)
    arrival_tolerance_m: float | None = None
    arrival_tolerance_rad: float | None = None

    def __post_init__(self) -> None:
        lo, hi = np.asarray(self.workspace_min_m, float), np.asarray(self.workspace_max_m, float)
        if lo.shape != (3,) or hi.shape != (3,) or not np.all(np.isfinite(lo)) or not np.all(np.isfinite(hi)):
            raise SafetyError("workspace corners must be 3 finite numbers each (metres)")
        if np.any(lo >= hi):
            raise SafetyError(f"workspace_min_m {lo.tolist()} must be < workspace_max_m {hi.tolist()} per axis")
        for name in ("max_speed_m_s", "max_acceleration_m_s2"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise SafetyError(f"{name} must be positive and finite, got {v!r}")
        if not (math.isfinite(self.min_standoff_m) and self.min_standoff_m >= 0):
            raise SafetyError(f"min_standoff_m must be >= 0, got {self.min_standoff_m!r}")
        if (self.plane_point_m is None) != (self.plane_normal is None):
            raise SafetyError("plane_point_m and plane_normal must be given together")
        if self.plane_normal is not None and not np.linalg.norm(self.plane_normal) > 0:
            raise SafetyError("plane_normal must be non-zero")
        for name, top in (("arrival_tolerance_m", MAX_POSITION_TOLERANCE_M),
                          ("arrival_tolerance_rad", MAX_ANGLE_TOLERANCE_RAD)):
            v = getattr(self, name)
            if v is not None and not (math.isfinite(v) and 0 < v <= top):
                raise SafetyError(f"{name} must be in (0, {top:.4g}], got {v!r}")

    def _plane(self) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
        if self.plane_point_m is None or self.plane_normal is None:
            return None
        n = np.asarray(self.plane_normal, float)
        return np.asarray(self.plane_point_m, float), n / np.linalg.norm(n)

    def violations(self, start: Pose | None, target: Pose, speed: float, acceleration: float) -> list[str]:
        """Every rule a move from ``start`` to ``target`` would break (empty when safe).

        Args:
            start: Current flange pose, or None to check the target pose alone.
            target: Commanded flange pose.
            speed: Commanded speed, m/s.
            acceleration: Commanded acceleration, m/s².
        """
        problems: list[str] = []
        if not speed <= self.max_speed_m_s:
            problems.append(f"speed {speed:.4g} m/s exceeds max {self.max_speed_m_s:.4g} m/s")
        if not acceleration <= self.max_acceleration_m_s2:
            problems.append(
                f"acceleration {acceleration:.4g} m/s^2 exceeds max {self.max_acceleration_m_s2:.4g} m/s^2"
            )
        flange, camera = self.path(start, target)
        lo, hi = np.asarray(self.workspace_min_m), np.asarray(self.workspace_max_m)
        for what, pts in (("flange", flange), ("camera", camera)):
            outside = np.any((pts < lo - 1e-12) | (pts > hi + 1e-12), axis=1)
            if np.any(outside):
                p = pts[int(np.argmax(outside))]
                where = "target" if outside[-1] and not np.any(outside[:-1]) else "path"
                problems.append(
                    f"{what} leaves the workspace box on the {where} at ({p[0]:.4f}, {p[1]:.4f}, {p[2]:.4f}) m"
                )
        plane = self._plane()
        if plane is not None:
            point, normal = plane
            d = (camera - point) @ normal
            if np.min(d) < self.min_standoff_m:
                problems.append(
                    f"camera comes within {np.min(d):.4f} m of the measuring plane "
                    f"(min standoff {self.min_standoff_m:.4f} m)"
                )
        return problems

    def path(self, start: Pose | None, target: Pose) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Sampled flange and camera positions (each (K, 3), metres) along a linear move."""
        if start is None:
            flange = target.translation[None, :].copy()
            camera = target.apply(self.mount.translation)[None, :]
        else:
            length = start.distance_to(target)
            k = max(MIN_PATH_SAMPLES, math.ceil(length * PATH_SAMPLES_PER_M) + 1)
            s = np.linspace(0.0, 1.0, k)
            flange = start.translation + s[:, None] * (target.translation - start.translation)
            # the flange turns at a constant rate about one axis (spherical linear interpolation)
            camera = np.array([start.interpolate(target, f).apply(self.mount.translation) for f in s])
        return flange, camera

    def check(self, start: Pose | None, target: Pose, speed: float, acceleration: float) -> None:
        """Raise :class:`SafetyError` naming the target pose and every violated rule."""
        problems = self.violations(start, target, speed, acceleration)
        if problems:
            raise SafetyError(f"move to {format_pose(target)} rejected: " + "; ".join(problems))

    def check_plan(self, start: Pose | None, targets: Sequence[Pose], speed: float, acceleration: float, *,
                   first_index: int = 1) -> None:
        """Check a whole sequence of moves before the first one is made.

        Args:
            start: Current flange pose, or None to check the first target alone.
            targets: Commanded flange poses, in the order they will be visited.
            speed: Commanded speed, m/s.
            acceleration: Commanded acceleration, m/s².
            first_index: The 1-based plan number of ``targets[0]`` in messages (a
                resumed run checks only the poses still to do, e.g. from pose 4 on).

        Raises:
            SafetyError: Naming the first offending pose (1-based plan number) and why.
        """
        previous = start
        for i, target in enumerate(targets, first_index):
            problems = self.violations(previous, target, speed, acceleration)
            if problems:
                raise SafetyError(f"plan pose {i} ({format_pose(target)}) rejected: " + "; ".join(problems))
            previous = target


class SafeArm(ForwardingArm):
    """A :class:`RobotArm` that forwards to another one after checking every move.

    The whole straight-line path of the flange and of the camera (sampled, with the
    orientation interpolated as controllers do) must stay inside the workspace box,
    speed and acceleration within their maxima, and the camera no closer to the
    measuring plane than the minimum standoff.

    The arrival tolerance of ``limits``, where given, is handed to ``inner``, which checks
    every move's arrival (ADR 0016).

    Args:
        inner: The arm to protect. Its life cycle is driven through this wrapper.
        limits: The envelope.
    """

    def __init__(self, inner: RobotArm, limits: SafetyLimits) -> None:
        super().__init__(inner)
        self.limits = limits
        if limits.arrival_tolerance_m is not None or limits.arrival_tolerance_rad is not None:
            self.arrival_tolerance = inner.arrival_tolerance.with_overrides(limits.arrival_tolerance_m,
                                                                            limits.arrival_tolerance_rad)

    def _move_linear(self, pose: Pose, speed: float, acceleration: float, timeout: float) -> None:
        start = self.inner.get_pose(min(timeout, self.default_timeout_s))
        self.limits.check(start, pose, speed, acceleration)
        super()._move_linear(pose, speed, acceleration, timeout)
