"""A stand-in for ACME's own client library of the R1 arm controller (what a vendor SDK would be).

A real backend imports its vendor's SDK lazily, in ``_connect``; this module plays that
SDK, with the habits real arm SDKs have: millimetres and degrees, Euler angles
(fixed-axis roll, pitch, yaw), an asynchronous ``move_l`` that returns at once, a
``moving()`` flag to poll, integer error codes. The "controller" is a model in this
process: a straight line in position (and a slerp in orientation) along a trapezoidal
speed profile, driven by the clock, faster than real time by ``time_scale``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

#: Error code of a move the controller refused (outside its reach).
ERR_UNREACHABLE = 31
#: Reach of the R1 (flange distance from the base origin), mm.
REACH_MM = 850.0
#: Link lengths of the R1's shoulder and elbow (the joint angles it reports), mm.
UPPER_ARM_MM, FOREARM_MM = 425.0, 425.0


class R1Error(RuntimeError):
    """What the SDK raises for a refused command; ``code`` is the controller's error code."""

    def __init__(self, code: int, text: str) -> None:
        super().__init__(f"R1 error {code}: {text}")
        self.code = code


class R1Controller:
    """One connection to an R1 controller (here: the in-process model).

    Args:
        time_scale: Wall seconds per controller second (0.01: motion 100x faster than real).
        home_mm_deg: Start pose, ``(x, y, z)`` mm and ``(roll, pitch, yaw)`` degrees.
        clock: Monotonic clock, seconds.
    """

    model = "R1"
    serial = "R1-000042"
    firmware = "3.2.1"

    def __init__(self, time_scale: float = 1.0,
                 home_mm_deg: Sequence[float] = (400.0, 0.0, 500.0, 180.0, 0.0, 0.0),
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.time_scale = time_scale
        self._clock = clock
        self._xyz = np.asarray(home_mm_deg[:3], dtype=float)
        self._rot = Rotation.from_euler("xyz", home_mm_deg[3:], degrees=True)
        self._motion: tuple[float, float, np.ndarray, np.ndarray, Slerp, float, float, float] | None = None
        self.error_code = 0

    # ------------------------------------------------------------- state
    def _now(self) -> float:
        """Controller time, seconds (wall time / time_scale)."""
        return self._clock() / self.time_scale if self.time_scale > 0 else math.inf

    def _settle(self) -> None:
        """Advance a running move to now; end it once its time is up."""
        if self._motion is None:
            return
        start, duration, a, b, slerp, length, v, acc = self._motion
        t = self._now() - start
        if t >= duration:
            self._xyz, self._rot, self._motion = b, slerp(1.0), None
            return
        s = _travelled(t, length, v, acc) / length if length > 0 else t / duration
        self._xyz = a + (b - a) * s
        self._rot = slerp(min(1.0, s))

    def get_position(self) -> list[float]:
        """``[x, y, z, roll, pitch, yaw]`` of the flange: mm and degrees, base frame."""
        self._settle()
        return [*self._xyz.tolist(), *self._rot.as_euler("xyz", degrees=True).tolist()]

    def get_joints(self) -> list[float]:
        """The six joint angles, degrees (base, shoulder, elbow, three wrist axes)."""
        self._settle()
        x, y, z = self._xyz
        r = min(math.hypot(x, y, z), UPPER_ARM_MM + FOREARM_MM - 1e-9)
        elbow = math.acos(max(-1.0, min(1.0, (r * r - UPPER_ARM_MM**2 - FOREARM_MM**2)
                                        / (2 * UPPER_ARM_MM * FOREARM_MM))))
        shoulder = math.atan2(z, math.hypot(x, y)) + math.atan2(FOREARM_MM * math.sin(elbow),
                                                                UPPER_ARM_MM + FOREARM_MM * math.cos(elbow))
        wrist = self._rot.as_euler("zyx", degrees=True)
        return [math.degrees(math.atan2(y, x)), math.degrees(shoulder), -math.degrees(elbow), *wrist.tolist()]

    def moving(self) -> bool:
        """Whether a move is running."""
        self._settle()
        return self._motion is not None

    # ------------------------------------------------------------- commands
    def move_l(self, pose_mm_deg: Sequence[float], speed_mm_s: float, acc_mm_s2: float) -> None:
        """Start a straight-line move to ``[x, y, z, roll, pitch, yaw]`` (mm, degrees); returns at once.

        Raises:
            R1Error: If the controller is in error or the target is out of reach (nothing moves).
        """
        if self.error_code:
            raise R1Error(self.error_code, "clear the error first")
        b = np.asarray(pose_mm_deg[:3], dtype=float)
        if float(np.linalg.norm(b)) > REACH_MM:
            self.error_code = ERR_UNREACHABLE
            raise R1Error(ERR_UNREACHABLE, f"target {np.round(b, 1).tolist()} mm is out of reach")
        self._settle()
        target = Rotation.from_euler("xyz", pose_mm_deg[3:], degrees=True)
        length = float(np.linalg.norm(b - self._xyz))
        turn_deg = math.degrees((target * self._rot.inv()).magnitude())
        # the orientation turns at most 90 deg/s: a pure turn takes time too
        duration = max(_duration(length, speed_mm_s, acc_mm_s2), turn_deg / 90.0)
        slerp = Slerp([0.0, 1.0], Rotation.concatenate([self._rot, target]))
        self._motion = (self._now(), duration, self._xyz.copy(), b, slerp, length, speed_mm_s, acc_mm_s2)

    def halt(self) -> None:
        """Stop where the arm is now (the model stops at once)."""
        self._settle()
        self._motion = None

    def clear_error(self) -> None:
        """Clear the error state."""
        self.error_code = 0


def _duration(length: float, v: float, a: float) -> float:
    """Time of a trapezoidal (or triangular) profile over ``length``, seconds."""
    if length <= 0:
        return 0.0
    if length >= v * v / a:  # reaches the cruise speed
        return length / v + v / a
    return 2.0 * math.sqrt(length / a)


def _travelled(t: float, length: float, v: float, a: float) -> float:
    """Distance along the profile at time ``t``, same units as ``length``."""
    if length < v * v / a:  # triangular: the peak speed is below v
        v = math.sqrt(length * a)
    ramp = v / a
    total = _duration(length, v, a) if length >= v * v / a else 2.0 * ramp
    if t <= ramp:
        return 0.5 * a * t * t
    if t >= total - ramp:
        left = max(0.0, total - t)
        return length - 0.5 * a * left * left
    return 0.5 * a * ramp * ramp + v * (t - ramp)
