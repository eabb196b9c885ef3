"""The true state of the simulated arm and the simulated clock (:class:`SimArmModel`, :class:`SimClock`).

Both belong to one :class:`~cellcal.sims.world.SimWorld` (which re-exports them): the clock advances
only through simulated events, the arm model holds the true flange pose and the motion under way.
ADR 0014.
"""

from __future__ import annotations

import threading
import time

from cellcal.devices.pose import Pose

from .motion import Motion
from .work import WorkPlan

__all__ = ["SimArmModel", "SimClock"]

class SimClock:
    """Simulated time: seconds since the world was made, plus a Unix epoch offset.

    It advances only through simulated events (arm motions, camera frame periods),
    never by itself, so results do not depend on the machine's speed.
    """

    def __init__(self, start_epoch_s: float | None = None) -> None:
        self._lock = threading.Lock()
        self._epoch0 = time.time() if start_epoch_s is None else float(start_epoch_s)
        self._elapsed = 0.0

    @property
    def elapsed_s(self) -> float:
        """Simulated seconds since the start."""
        with self._lock:
            return self._elapsed

    def now(self) -> float:
        """Simulated time as seconds since the Unix epoch."""
        with self._lock:
            return self._epoch0 + self._elapsed

    def advance(self, dt_s: float) -> float:
        """Move time forward by ``dt_s`` >= 0 seconds; returns the new elapsed time."""
        with self._lock:
            self._elapsed += max(0.0, float(dt_s))
            return self._elapsed

    def advance_to(self, elapsed_s: float) -> float:
        """Move time forward to ``elapsed_s`` (never backwards); returns the new elapsed time."""
        with self._lock:
            self._elapsed = max(self._elapsed, float(elapsed_s))
            return self._elapsed


class SimArmModel:
    """The true state of the simulated arm: flange pose and the motion under way.

    Thread-safe. While a motion runs, its simulated time is
    ``(wall time since start) / time_scale`` (capped at its duration); with
    ``time_scale == 0`` a motion completes the moment it starts. The clock is advanced
    to the motion's simulated time whenever the arm state is looked at.
    """

    def __init__(self, flange_pose: Pose, clock: SimClock) -> None:
        self.lock = threading.RLock()
        self._pose = flange_pose
        self._clock = clock
        self._motion: Motion | None = None
        self._time_scale = 0.0
        self._sim_start = 0.0
        self._wall_start = 0.0
        self._motion_t = 0.0
        self._work: WorkPlan | None = None

    @property
    def clock(self) -> SimClock:
        """The world's clock."""
        return self._clock

    def start_work(self, plan: WorkPlan) -> None:
        """Follow ``plan`` on the simulated clock from now on (the arm's own program; ``[sim.work]``)."""
        with self.lock:
            self._work = plan
            self._update()

    @property
    def working(self) -> bool:
        """Whether the arm follows its own work plan (a commanded motion ends it)."""
        return self._work is not None

    def start_motion(self, motion: Motion, time_scale: float) -> None:
        """Start ``motion`` now (replacing any motion under way at its current pose; a work plan ends)."""
        with self.lock:
            self._update()
            self._work = None
            self._motion = motion
            self._time_scale = max(0.0, float(time_scale))
            self._sim_start = self._clock.elapsed_s
            self._wall_start = time.monotonic()
            self._motion_t = 0.0
            self._update()

    def _update(self) -> None:
        if self._work is not None:  # the arm's own program: where it is at the clock's time
            self._pose = self._work.pose_at(self._clock.elapsed_s)
            return
        m = self._motion
        if m is None:
            return
        if self._time_scale <= 0.0 or m.duration_s <= 0.0:
            t = m.duration_s
        else:
            t = min(m.duration_s, (time.monotonic() - self._wall_start) / self._time_scale)
        self._motion_t = t
        self._pose = m.pose_at(t)
        self._clock.advance_to(self._sim_start + t)
        if t >= m.duration_s:
            self._motion = None

    def flange_pose(self) -> Pose:
        """True flange pose in the base frame now (``T_base_flange``)."""
        with self.lock:
            self._update()
            return self._pose

    def set_flange_pose(self, pose: Pose) -> None:
        """Teleport the flange (cancels any motion); for set-up and tests."""
        with self.lock:
            self._motion = None
            self._pose = pose

    def is_moving(self) -> bool:
        """Whether a motion is under way."""
        with self.lock:
            self._update()
            return self._motion is not None

    def progress(self) -> float:
        """Fraction 0..1 of the current motion's duration done (1.0 when idle)."""
        with self.lock:
            self._update()
            m = self._motion
            if m is None:
                return 1.0
            return self._motion_t / m.duration_s if m.duration_s > 0 else 1.0

    def remaining_s(self) -> float:
        """Simulated seconds left in the current motion (0 when idle)."""
        with self.lock:
            self._update()
            m = self._motion
            return 0.0 if m is None else max(0.0, m.duration_s - self._motion_t)

    def halt(self) -> Pose:
        """Stop the motion where it is now; returns the flange pose it stopped at."""
        with self.lock:
            self._update()
            self._motion = None
            return self._pose
