"""The simulated cell's normal work and its accidents: ``[sim.work]`` and ``[[sim.events]]``.

With ``[sim.work]`` the simulated arm moves on its own, as a user's program would: from one
work pose to the next (straight lines, trapezoidal speed), dwelling at each, round and round,
on the simulated clock. Nobody commands it; ``cellcal track`` only reads it. A ``[[sim.events]]``
entry changes the truth at ``at_s`` simulated seconds: a new camera mount (a knock) or a new
plane (the table moved). The cell's configuration (``[mount]``, ``[reference]``) is untouched.
"""

from __future__ import annotations

from bisect import bisect_right
from dataclasses import dataclass, field

import numpy as np

from cellcal.devices.errors import ConfigError
from cellcal.devices.pose import Pose

from .motion import LinearMotion, Motion


class _Rest:
    """A dwell at one pose (a leg of no motion)."""

    duration_s = 0.0

    def __init__(self, pose: Pose) -> None:
        self.pose = pose

    def pose_at(self, t_s: float) -> Pose:
        return self.pose


@dataclass(frozen=True)
class WorkPose:
    """One pose of the work plan: the flange in the base frame."""

    translation_m: tuple[float, float, float] = field(metadata={"ge": -2.0, "le": 2.0,
                                                                "doc": "flange position, base frame, m"})
    rpy_deg: tuple[float, float, float] = field(default=(180.0, 0.0, 0.0), metadata={
        "ge": -360.0, "le": 360.0, "doc": "flange roll, pitch, yaw, degrees"})

    def pose(self) -> Pose:
        """``T_base_flange``."""
        return Pose.from_xyz_rpy(np.asarray(self.translation_m), np.radians(self.rpy_deg))


@dataclass(frozen=True)
class WorkConfig:
    """``[sim.work]``: the arm's own program, from the initial flange pose through ``poses``, repeated."""

    poses: list[WorkPose] = field(metadata={"min_items": 1, "max_items": 1024,
                                            "doc": "the work poses, visited in order"})
    speed_m_s: float = field(default=0.1, metadata={"gt": 0.0, "le": 1.0, "doc": "tool speed, m/s"})
    acceleration_m_s2: float = field(default=0.5, metadata={"gt": 0.0, "le": 50.0, "doc": "tool acceleration, m/s²"})
    dwell_s: float = field(default=1.0, metadata={"ge": 0.0, "le": 3600.0, "doc": "time at rest at each pose, s"})


@dataclass(frozen=True)
class EventConfig:
    """One ``[[sim.events]]`` entry: at ``at_s`` a new true mount, a new true plane, or both.

    ``camera`` names a camera of ``[[cameras]]``: the new mount is then that camera's new true pose in
    its parent frame (``T_flange_camera`` on the flange, ``T_base_camera`` fixed: a knocked fixed
    camera). Without it, the camera a run drives through ``[camera]``/``[mount]`` (``[sim.mount]``)
    moves, as it always has.
    """

    at_s: float = field(metadata={"ge": 0.0, "le": 1e7, "doc": "simulated seconds from the start"})
    mount_translation_m: tuple[float, float, float] | None = field(default=None, metadata={
        "ge": -2.0, "le": 2.0,
        "doc": "new true camera origin in the flange frame (or, with camera naming a fixed one, the base frame), m"})
    mount_rpy_deg: tuple[float, float, float] | None = field(default=None, metadata={
        "ge": -360.0, "le": 360.0, "doc": "new true mount (or fixed camera's) roll, pitch, yaw, degrees"})
    camera: str | None = field(default=None, metadata={
        "max_len": 32, "doc": "the camera of [[cameras]] the new mount is for (default: the camera the run drives)"})
    plane_point_m: tuple[float, float, float] | None = field(default=None, metadata={
        "ge": -10.0, "le": 10.0, "doc": "a point on the new true plane, base frame, m"})
    plane_normal: tuple[float, float, float] | None = field(default=None, metadata={
        "ge": -1e6, "le": 1e6, "doc": "the new true plane's normal, base frame"})

    def __post_init__(self) -> None:
        mount = (self.mount_translation_m is not None, self.mount_rpy_deg is not None)
        plane = (self.plane_point_m is not None, self.plane_normal is not None)
        if not any(mount + plane):
            raise ConfigError("changes nothing: give mount_translation_m and mount_rpy_deg, or plane_point_m and "
                              "plane_normal", key="sim.events")
        if mount[0] != mount[1]:
            raise ConfigError("a new mount needs both mount_translation_m and mount_rpy_deg", key="sim.events")
        if self.camera is not None and not any(mount):
            raise ConfigError("camera names whose pose changes: give mount_translation_m and mount_rpy_deg",
                              key="sim.events")
        if plane[0] != plane[1]:
            raise ConfigError("a new plane needs both plane_point_m and plane_normal", key="sim.events")
        if self.plane_normal is not None and float(np.linalg.norm(self.plane_normal)) < 1e-9:
            raise ConfigError("plane_normal must be a non-zero vector", key="sim.events")

    def mount(self) -> Pose | None:
        """The new ``T_flange_camera``, or None."""
        if self.mount_translation_m is None or self.mount_rpy_deg is None:
            return None
        return Pose.from_xyz_rpy(np.asarray(self.mount_translation_m), np.radians(self.mount_rpy_deg))


class WorkPlan:
    """The work as a function of simulated time: moves and dwells, repeated for ever.

    Args:
        start: The flange pose at time 0 (the first move starts there).
        config: The ``[sim.work]`` table.
    """

    def __init__(self, start: Pose, config: WorkConfig) -> None:
        targets = [p.pose() for p in config.poses]
        self._legs: list[tuple[float, Motion]] = []                 # (start time, a motion or a rest)
        t, here = 0.0, start
        for target in targets + targets[:1]:                          # the cycle closes on its first pose
            motion = LinearMotion(here, target, config.speed_m_s, config.acceleration_m_s2)
            if motion.duration_s > 0.0:
                self._legs.append((t, motion))
                t += motion.duration_s
            self._legs.append((t, _Rest(target)))
            t += config.dwell_s
            here = target
        # the first leg (from the start pose) is not repeated: the cycle runs from the first pose on
        self._lead_s = self._legs[1][0] if not isinstance(self._legs[0][1], _Rest) else 0.0
        self._lead_legs = 1 if self._lead_s > 0.0 else 0
        self.cycle_s = t - self._lead_s - config.dwell_s       # from the first pose back to it
        self._cycle = [(s - self._lead_s, leg) for s, leg in self._legs[self._lead_legs:]]
        self._starts = [s for s, _ in self._cycle]

    def pose_at(self, t_s: float) -> Pose:
        """The true flange pose ``t_s`` simulated seconds after the start."""
        if t_s < self._lead_s:
            return self._legs[0][1].pose_at(t_s)
        u = t_s - self._lead_s
        if self.cycle_s > 0.0:
            u = u % self.cycle_s                                       # the work repeats
        i = max(0, bisect_right(self._starts, u) - 1)
        start, leg = self._cycle[i]
        return leg.pose_at(u - start)
