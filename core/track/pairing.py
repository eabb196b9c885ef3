"""The arm's flange pose at a camera frame's time: a bounded history of read-back poses, interpolated.

Between the two read-back samples around a frame's time the translation is interpolated
linearly and the rotation at a constant rate about one axis (slerp). A frame is skipped
with a reason when no sample lies close enough on both sides, or when the arm moves or
turns so fast over that interval that a timing error would move the pose by more than
the arm's own read-back noise (ADR 0040).
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from cellcal.devices.pose import Pose

#: Default largest interval between the two samples around a frame, s (a 100 Hz stream has 0.01 s).
MAX_GAP_S = 0.1
#: Default largest flange speed over that interval, m/s (1 ms of timing error = 50 µm).
MAX_LINEAR_SPEED_M_S = 0.05
#: Default largest flange turn rate over that interval, rad/s (1 ms of timing error = 0.1 mrad).
MAX_TURN_RATE_RAD_S = 0.1

SKIP_NO_POSE = "no arm pose near the frame time"
SKIP_FAST = "arm moving too fast"
SKIP_TURNING = "arm turning too fast"


@dataclass(frozen=True)
class Skip:
    """Why a frame gets no flange pose.

    Attributes:
        reason: One of :data:`SKIP_NO_POSE`, :data:`SKIP_FAST`, :data:`SKIP_TURNING` (counter key).
        detail: The figures behind it, for a log line.
    """

    reason: str
    detail: str = ""


class PoseHistory:
    """A bounded buffer of ``(t_s, T_base_flange)`` samples read from the arm.

    Args:
        capacity: Samples kept (the oldest are dropped); 512 at 125 Hz is 4 s.
        max_gap_s: Largest interval between the samples around a frame, s.
        max_linear_speed_m_s: Largest flange speed between them, m/s.
        max_turn_rate_rad_s: Largest flange turn rate between them, rad/s.
    """

    def __init__(self, capacity: int = 512, *, max_gap_s: float = MAX_GAP_S,
                 max_linear_speed_m_s: float = MAX_LINEAR_SPEED_M_S,
                 max_turn_rate_rad_s: float = MAX_TURN_RATE_RAD_S) -> None:
        if capacity < 2:
            raise ValueError(f"PoseHistory needs a capacity of at least 2, got {capacity}")
        self.capacity = capacity
        self.max_gap_s = max_gap_s
        self.max_linear_speed_m_s = max_linear_speed_m_s
        self.max_turn_rate_rad_s = max_turn_rate_rad_s
        self._times: deque[float] = deque(maxlen=capacity)
        self._poses: deque[Pose] = deque(maxlen=capacity)
        #: Samples dropped because their time was not after the newest one.
        self.dropped = 0

    def __len__(self) -> int:
        return len(self._times)

    @property
    def newest_s(self) -> float | None:
        """Time of the newest sample, s (None when empty)."""
        return self._times[-1] if self._times else None

    def add(self, t_s: float, flange: Pose) -> None:
        """Append a read-back sample; one not later than the newest is dropped (and counted)."""
        if not math.isfinite(t_s) or (self._times and t_s <= self._times[-1]):
            self.dropped += 1  # out of order or repeated: the stream's newer sample stands
            return
        self._times.append(float(t_s))
        self._poses.append(flange)

    def pending(self, t_s: float) -> bool:
        """Whether a frame at ``t_s`` is newer than the newest sample (wait for the arm before pairing)."""
        return not self._times or t_s > self._times[-1]

    def at(self, t_s: float) -> Pose | Skip:
        """The interpolated ``T_base_flange`` at a frame's time, or why there is none."""
        times = self._times
        k = bisect.bisect_left(times, t_s)  # first sample at or after the frame (deque: O(n), n bounded)
        if k < len(times) and times[k] == t_s:
            lo = hi = k  # a sample exactly at the frame time
        elif 0 < k < len(times):
            lo, hi = k - 1, k  # the samples on either side
        else:
            where = "before the oldest" if k == 0 and times else "after the newest"
            return Skip(SKIP_NO_POSE, f"frame at {t_s:.4f} s is {where} arm pose" if times else "no arm pose yet")
        # speed over the interval around the frame (or the segments around an exact hit)
        a_idx, b_idx = (max(lo - 1, 0), min(hi + 1, len(times) - 1)) if lo == hi else (lo, hi)
        gap = times[b_idx] - times[a_idx]
        if lo != hi and gap > self.max_gap_s:
            return Skip(SKIP_NO_POSE, f"arm samples {gap * 1e3:.0f} ms apart around the frame "
                                      f"(limit {self.max_gap_s * 1e3:.0f} ms)")
        a, b = self._poses[a_idx], self._poses[b_idx]
        if gap > 0:
            speed = a.distance_to(b) / gap  # flange speed, m/s
            if speed > self.max_linear_speed_m_s:
                return Skip(SKIP_FAST, f"{speed * 1e3:.0f} mm/s (limit {self.max_linear_speed_m_s * 1e3:.0f} mm/s)")
            rate = a.angle_to(b) / gap  # flange turn rate, rad/s
            if rate > self.max_turn_rate_rad_s:
                return Skip(SKIP_TURNING, f"{np.degrees(rate):.1f} deg/s "
                                          f"(limit {np.degrees(self.max_turn_rate_rad_s):.1f} deg/s)")
        if lo == hi:
            return self._poses[lo]
        fraction = (t_s - times[lo]) / (times[hi] - times[lo])  # 0 at the earlier sample, 1 at the later
        return self._poses[lo].interpolate(self._poses[hi], fraction)  # linear + slerp


__all__ = ["MAX_GAP_S", "MAX_LINEAR_SPEED_M_S", "MAX_TURN_RATE_RAD_S", "SKIP_FAST", "SKIP_NO_POSE", "SKIP_TURNING",
           "PoseHistory", "Skip"]
