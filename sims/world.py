"""The simulated world: scene + true camera mount + true arm state + simulated clock.

World frame == robot base frame (metres). One :class:`SimWorld` per configuration
document (:func:`world_from_context`) couples the simulated camera to the simulated
arm, so moving the arm moves the camera. Design: docs/adr/0014-simulated-cell.md.
"""

from __future__ import annotations

import threading
import time
import zlib
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from cellcal.devices.base import BackendContext
from cellcal.devices.config import parse_section
from cellcal.devices.errors import ConfigError
from cellcal.devices.pose import Pose
from cellcal.devices.scene_view import SceneSnapshot, publish_scene_view

from .charuco import CharucoConfig
from .kinematics import ArmErrors, ArmErrorsConfig
from .motion import Motion
from .scene import DEFAULT_REFLECTIVITY, MAX_REFLECTIVITY, Box, Scene
from .systematic import SystematicConfig
from .tof import ArtefactsConfig
from .work import EventConfig, WorkConfig, WorkPlan

#: Key of the shared world in ``BackendContext.shared``.
SHARED_KEY = "sim.world"


# ---------------------------------------------------------------------- config
@dataclass(frozen=True)
class MountConfig:
    """The hand-eye transform flange -> camera (the document's ``[mount]`` table).

    The rotation follows :meth:`Pose.from_xyz_rpy`: fixed-axis roll, pitch, yaw,
    ``Rz(yaw) @ Ry(pitch) @ Rx(roll)``; the pose maps camera coordinates into flange
    coordinates (``T_flange_camera``).
    """

    translation_m: tuple[float, float, float] = field(
        default=(0.0, 0.0, 0.0), metadata={"ge": -2.0, "le": 2.0, "doc": "camera origin in the flange frame, m"})
    rpy_deg: tuple[float, float, float] = field(
        default=(0.0, 0.0, 0.0), metadata={"ge": -360.0, "le": 360.0, "doc": "roll, pitch, yaw, degrees"})

    def pose(self) -> Pose:
        """``T_flange_camera``."""
        return Pose.from_xyz_rpy(np.asarray(self.translation_m), np.radians(self.rpy_deg))


@dataclass(frozen=True)
class BoxConfig:
    """One work object of ``[[sim.boxes]]`` (see :class:`~cellcal.sims.scene.Box`)."""

    center_xy_m: tuple[float, float] = field(metadata={"ge": -10.0, "le": 10.0,
                                                       "doc": "footprint centre in the plane frame, m"})
    size_m: tuple[float, float, float] = field(metadata={"gt": 0.0, "le": 5.0, "doc": "edge lengths, m"})
    yaw_deg: float = field(default=0.0, metadata={"ge": -360.0, "le": 360.0,
                                                  "doc": "rotation about the plane normal, degrees"})
    reflectivity: float = field(default=DEFAULT_REFLECTIVITY, metadata={
        "gt": 0.0, "le": MAX_REFLECTIVITY, "doc": "near-infrared reflectivity (1 = white, > 1 retro-reflective)"})

    def box(self) -> Box:
        """The scene object."""
        return Box(self.center_xy_m, self.size_m, float(np.radians(self.yaw_deg)), self.reflectivity)


@dataclass(frozen=True)
class SimConfig:
    """The ``[sim]`` table: the simulated cell's ground truth.

    It sets the plane, the boxes, the initial flange pose, the seed, the ToF camera's
    artefacts (``[sim.artefacts]``, all on by default), the cameras' systematic depth errors
    (``[sim.systematic]``, on by default; ADR 0054), whether the camera rides on the
    arm (``camera_on_arm``; false simulates a rig error) and optionally a mount that
    overrides the document's ``[mount]`` table: the calibrator reads ``[mount]`` as its
    *nominal* mount, the sim uses it as the *true* one unless ``[sim.mount]`` says
    otherwise, which is how a mount error is simulated.
    """

    plane_point_m: tuple[float, float, float] = field(
        default=(0.0, 0.0, 0.0), metadata={"ge": -10.0, "le": 10.0, "doc": "a point on the plane, base frame, m"})
    plane_normal: tuple[float, float, float] = field(
        default=(0.0, 0.0, 1.0), metadata={"ge": -1e6, "le": 1e6, "doc": "plane normal, base frame (normalised)"})
    plane_reflectivity: float = field(default=DEFAULT_REFLECTIVITY, metadata={
        "gt": 0.0, "le": MAX_REFLECTIVITY, "doc": "near-infrared reflectivity of the plane"})
    boxes: list[BoxConfig] = field(default_factory=list, metadata={"doc": "work objects on the plane"})
    artefacts: ArtefactsConfig = field(default_factory=ArtefactsConfig, metadata={
        "doc": "the ToF camera's artefacts (mixed pixels, multipath, amplitude noise, drift)"})
    systematic: SystematicConfig = field(default_factory=SystematicConfig, metadata={
        "doc": "the cameras' systematic depth errors (stereo f·B, offset, bow; ToF offset, scale, wiggle, bow)"})
    mount: MountConfig | None = field(default=None, metadata={
        "doc": "true flange->camera mount; default: the document's [mount] table"})
    charuco: CharucoConfig | None = field(default=None, metadata={
        "doc": "a ChArUco board printed on the plane (seen in the amplitude image)"})
    initial_flange_translation_m: tuple[float, float, float] = field(
        default=(0.3, 0.0, 0.5), metadata={"ge": -2.0, "le": 2.0, "doc": "flange position at start, base frame, m"})
    initial_flange_rpy_deg: tuple[float, float, float] = field(
        default=(180.0, 0.0, 0.0), metadata={"ge": -360.0, "le": 360.0,
                                             "doc": "flange orientation at start (tool pointing down), degrees"})
    seed: int | None = field(default=None, metadata={"ge": 0, "doc": "seed of the world; default [cell] seed"})
    work: WorkConfig | None = field(default=None, metadata={
        "doc": "the arm's own work program (moves on its own from the start; cellcal track reads it)"})
    events: list[EventConfig] = field(default_factory=list, metadata={
        "doc": "changes of the true mount or plane at given simulated times"})
    camera_on_arm: bool = field(default=True, metadata={
        "doc": "false: the camera stays where the arm's initial pose put it and its view does not follow the "
               "arm (a camera not on the arm that moves: a rig or config error)"})
    arm_errors: ArmErrorsConfig = field(default_factory=ArmErrorsConfig, metadata={
        "doc": "the arm's kinematic errors (joint zero offsets, link lengths): the flange stands off the pose the "
               "arm reports, smoothly with the pose (on by default; enabled = false: the ideal arm)"})

    def __post_init__(self) -> None:
        if float(np.linalg.norm(self.plane_normal)) < 1e-9:
            raise ConfigError("must be a non-zero vector", key="sim.plane_normal")

    def scene(self) -> Scene:
        """The scene this config describes."""
        return Scene(np.asarray(self.plane_point_m, dtype=np.float64),
                     np.asarray(self.plane_normal, dtype=np.float64),
                     tuple(b.box() for b in self.boxes), self.plane_reflectivity)

    def initial_flange_pose(self) -> Pose:
        """``T_base_flange`` at start."""
        return Pose.from_xyz_rpy(np.asarray(self.initial_flange_translation_m),
                                 np.radians(self.initial_flange_rpy_deg))


def parse_mount(table: Mapping[str, Any] | None, *, source: str | None = None,
                where: str = "mount") -> MountConfig:
    """Read the document's ``[mount]`` table (keys ``translation_m``, ``rpy_deg``).

    Other keys in that table belong to the calibrator and are skipped here (it
    validates them); the two keys the sim needs are checked strictly.

    Raises:
        ConfigError: If ``translation_m`` or ``rpy_deg`` is malformed.
    """
    table = dict(table or {})
    known = {"translation_m", "rpy_deg"}
    cfg: MountConfig = parse_section(MountConfig, {k: v for k, v in table.items() if k in known},
                                     where=where, source=source)
    return cfg


# ---------------------------------------------------------------------- clock and arm state
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


# ---------------------------------------------------------------------- the world
class SimWorld:
    """Scene + true mount + true arm state + clock + seed + the camera's artefacts and systematic errors.

    The camera renders from :meth:`camera_pose` = true flange pose @ true mount.

    Attributes:
        scene: The measuring plane and boxes (world == base frame).
        mount: True ``T_flange_camera``.
        arm: True arm state.
        clock: Simulated clock shared by every simulated device.
        seed: Root seed; devices derive their own streams with :meth:`rng`.
        artefacts: The simulated ToF camera's artefacts (default: all on).
        systematic: The simulated cameras' systematic depth errors (default: on, ADR 0054;
            :meth:`~cellcal.sims.systematic.SystematicConfig.off` for an ideal camera).
    """

    def __init__(self, scene: Scene, mount: Pose, flange_pose: Pose | None = None, seed: int = 0,
                 clock: SimClock | None = None, artefacts: ArtefactsConfig | None = None,
                 systematic: SystematicConfig | None = None) -> None:
        self.scene = scene
        self.mount = mount
        self.clock = clock or SimClock()
        self.arm = SimArmModel(flange_pose or SimConfig().initial_flange_pose(), self.clock)
        self.seed = int(seed)
        self.artefacts = artefacts or ArtefactsConfig()
        self.systematic = systematic or SystematicConfig()
        #: A ChArUco board on the plane (``[sim.charuco]``), or None.
        self.charuco: CharucoConfig | None = None
        #: Changes of the truth still to come (``[[sim.events]]``), earliest first.
        self.events: list[EventConfig] = []
        #: The flange pose the camera stays at when it is not on the arm (``[sim] camera_on_arm = false``), or None.
        self.camera_flange: Pose | None = None
        #: The arm's kinematic errors (``[sim.arm_errors]``), or None for the ideal arm: :attr:`arm` holds the pose
        #: the controller believes (and reports, with noise); the flange truly stands at
        #: :meth:`true_flange_pose`.
        self.arm_errors: ArmErrors | None = None

    @classmethod
    def from_config(cls, config: SimConfig, mount: MountConfig | None = None, seed: int = 0) -> SimWorld:
        """Build from a ``[sim]`` config; ``config.mount`` beats ``mount``, ``config.seed`` beats ``seed``."""
        m = config.mount or mount or MountConfig()
        world = cls(config.scene(), m.pose(), config.initial_flange_pose(),
                    seed if config.seed is None else config.seed, artefacts=config.artefacts,
                    systematic=config.systematic)
        world.charuco = config.charuco
        world.arm_errors = config.arm_errors.errors()
        world.events = sorted(config.events, key=lambda e: e.at_s)
        if not config.camera_on_arm:
            world.camera_flange = config.initial_flange_pose()
        if config.work is not None:
            world.arm.start_work(WorkPlan(config.initial_flange_pose(), config.work))
        return world

    def camera_pose(self) -> Pose:
        """True camera pose in the base frame, ``T_base_camera = T_base_flange @ T_flange_camera``.

        With :attr:`camera_flange` set the camera stays at ``camera_flange @ mount`` while the arm moves.
        """
        self.apply_events()
        flange = self.true_flange_pose()  # also brings the simulated clock up to the motion under way
        fixed = self.camera_flange
        return (flange if fixed is None else fixed) @ self.mount

    def true_flange_pose(self) -> Pose:
        """Where the flange truly stands now: the arm's believed pose moved by its kinematic errors, if any."""
        believed = self.arm.flange_pose()
        errors = self.arm_errors
        return believed if errors is None else errors.true_pose(believed)

    def apply_events(self) -> None:
        """Make every ``[[sim.events]]`` change whose time has come (called before each frame is rendered)."""
        now = self.clock.elapsed_s
        while self.events and self.events[0].at_s <= now:
            event = self.events.pop(0)
            mount = event.mount()
            if mount is not None:
                self.mount = mount
            if event.plane_point_m is not None and event.plane_normal is not None:
                s = self.scene
                self.scene = Scene(np.asarray(event.plane_point_m, dtype=np.float64),
                                   np.asarray(event.plane_normal, dtype=np.float64), s.boxes, s.plane_reflectivity)

    def view_from_camera(self) -> SceneSnapshot:
        """The plane and boxes in the true camera frame now (:class:`~cellcal.devices.scene_view.SceneView`)."""
        s = self.scene
        boxes = tuple(zip(s._box_centre, s._box_rot, (b.size_m for b in s.boxes), strict=True))  # type: ignore[attr-defined]
        return SceneSnapshot.from_base_frame(self.camera_pose(), s.plane_point_m, s.plane_normal, boxes,
                                             self.clock.now())

    def bump_mount(self, delta: Pose) -> Pose:
        """Jolt the camera on its mount: from now on the true mount is ``mount @ delta``.

        Simulates a camera knocked on its bracket (tests of the drift monitor). Frames
        rendered after this call see the moved camera; the nominal ``[mount]`` of the
        configuration is not touched.

        Args:
            delta: The camera's displacement expressed in its own (optical) frame:
                ``T_camera_old_camera_new`` (rotation about the camera's axes, metres).

        Returns:
            The new true mount ``T_flange_camera``.
        """
        self.mount = self.mount @ delta  # one attribute assignment: atomic for readers
        return self.mount

    def rng(self, stream: str, seed: int | None = None) -> np.random.Generator:
        """A generator for one named stream (``"camera"``, ``"arm"``), from ``seed`` or the world's seed."""
        root = self.seed if seed is None else int(seed)
        return np.random.default_rng([root, zlib.crc32(stream.encode())])


def world_from_context(context: BackendContext | None) -> SimWorld:
    """The single world of a configuration document, created on first use.

    Reads ``context.document["sim"]`` (:class:`SimConfig`) and ``["mount"]``
    (:class:`MountConfig`), seeds from ``[sim] seed`` or ``context.seed``, and keeps
    the world in ``context.shared["sim.world"]`` so every simulated backend built
    from the same context sees the same world.

    Raises:
        ConfigError: If the ``[sim]`` or ``[mount]`` table is malformed (naming the key).
    """
    if context is None:
        context = BackendContext()
    world = context.shared.get(SHARED_KEY)
    if isinstance(world, SimWorld):
        return world
    doc = context.document or {}
    sim_cfg = parse_section(SimConfig, doc.get("sim", {}), where="sim", source=context.source)
    mount_cfg = parse_mount(doc.get("mount"), source=context.source) if "mount" in doc else None
    if sim_cfg.mount is None and "from_handeye" in (doc.get("mount") or {}):
        # the estimate is the cell's belief, not the simulated truth: the sim needs that stated
        raise ConfigError("a simulated cell whose [mount] comes from_handeye needs its true mount in [sim.mount]",
                          source=context.source, key="sim.mount")
    world = SimWorld.from_config(sim_cfg, mount_cfg, seed=context.seed)
    context.shared[SHARED_KEY] = world
    publish_scene_view(context, world)  # the public face of the world for vendors' cameras (ADR 0022)
    return world
