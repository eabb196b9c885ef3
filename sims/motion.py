"""Flange trajectories of the simulated arm: trapezoidal speed profiles along straight lines.

A :class:`Motion` is a planned flange trajectory on the simulated clock; :class:`LinearMotion`
is the one the sim arm runs (and ``[sim.work]`` strings together): a straight line in
position, slerp in orientation, one trapezoidal speed profile. Both the arm
(:mod:`cellcal.sims.arm`) and the world's work plan (:mod:`cellcal.sims.work`) build on it,
so neither imports the other for it. Poses in the base frame, metres, radians, seconds.
"""

from __future__ import annotations

import math
from typing import Protocol

import numpy as np

from cellcal.devices.pose import Pose

#: Effective radius converting a rotation angle into path length, metres per radian.
ROTATION_RADIUS_M = 0.1


class Motion(Protocol):
    """A planned flange trajectory (e.g. :class:`LinearMotion`, or a dwell)."""

    @property
    def duration_s(self) -> float: ...

    def pose_at(self, t_s: float) -> Pose: ...


def trapezoid_duration(distance: float, speed: float, acceleration: float) -> float:
    """Time (s) to travel ``distance`` (m) from rest to rest with a trapezoidal profile."""
    if distance <= 0.0:
        return 0.0
    if distance >= speed * speed / acceleration:
        return distance / speed + speed / acceleration
    return 2.0 * math.sqrt(distance / acceleration)


def trapezoid_position(t: float, distance: float, speed: float, acceleration: float) -> float:
    """Distance (m) travelled after ``t`` seconds along the trapezoidal profile."""
    total = trapezoid_duration(distance, speed, acceleration)
    if t <= 0.0 or total <= 0.0:
        return 0.0
    if t >= total:
        return distance
    v_peak = min(speed, math.sqrt(distance * acceleration))
    t_acc = v_peak / acceleration
    d_acc = 0.5 * acceleration * t_acc * t_acc
    if t < t_acc:
        return 0.5 * acceleration * t * t
    if t <= total - t_acc:
        return d_acc + v_peak * (t - t_acc)
    tr = total - t
    return distance - 0.5 * acceleration * tr * tr


class LinearMotion:
    """A straight-line flange motion with a trapezoidal profile.

    Straight line in position, slerp in orientation, both following one trapezoidal
    speed profile over the path length ``L = max(|Δp|, angle · 0.1 m)`` (so pure
    rotations take time too): ``T = L/v + v/a`` when ``L >= v²/a``, else
    ``T = 2·sqrt(L/a)``.

    Args:
        start, target: Flange poses in the base frame.
        speed: m/s; acceleration: m/s².
    """

    def __init__(self, start: Pose, target: Pose, speed: float, acceleration: float) -> None:
        self.start = start
        self.target = target
        self.speed = float(speed)
        self.acceleration = float(acceleration)
        self._dp = target.translation - start.translation
        self._drot = start.rotvec_to(target)
        self.length_m = max(float(np.linalg.norm(self._dp)), float(np.linalg.norm(self._drot)) * ROTATION_RADIUS_M)
        self._duration = trapezoid_duration(self.length_m, self.speed, self.acceleration)

    @property
    def duration_s(self) -> float:
        """Simulated duration, seconds."""
        return self._duration

    def pose_at(self, t_s: float) -> Pose:
        """Flange pose ``t_s`` simulated seconds after the start."""
        if t_s >= self._duration:
            return self.target
        return self.pose_at_fraction(trapezoid_position(t_s, self.length_m, self.speed, self.acceleration)
                                     / self.length_m)

    def pose_at_fraction(self, s: float) -> Pose:
        """Flange pose after the fraction ``s`` (0..1) of the path."""
        return self.start.interpolate(self.target, s)
