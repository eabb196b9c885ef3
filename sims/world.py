"""The simulated world: scene + true camera mount + true arm state + simulated clock.

World frame == robot base frame (metres). One :class:`SimWorld` per configuration
document (:func:`world_from_context`) couples the simulated cameras to the simulated
arm, so moving the arm moves the cameras on it and the plate it holds. Design:
docs/adr/0014-simulated-cell.md; several cameras and the plate: :mod:`cellcal.sims.placement`.
"""

from __future__ import annotations

import zlib
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from cellcal.devices.base import BackendContext, CameraPlacement
from cellcal.devices.config import parse_section
from cellcal.devices.errors import ConfigError
from cellcal.devices.pose import Pose
from cellcal.devices.scene_view import SceneSnapshot, publish_scene_view

from .arm_state import SimArmModel, SimClock
from .charuco import CharucoConfig
from .kinematics import ArmErrors, ArmErrorsConfig
from .placement import MAX_SIM_CAMERAS, PlateConfig, SimCameraTruth, check_truth_names, true_placement_pose, truth_of
from .scene import DEFAULT_REFLECTIVITY, MAX_REFLECTIVITY, Box, Scene
from .systematic import SystematicConfig
from .tof import ArtefactsConfig
from .work import EventConfig, WorkConfig, WorkPlan

__all__ = ["SHARED_KEY", "BoxConfig", "MountConfig", "SimArmModel", "SimClock", "SimConfig", "SimWorld",
           "parse_mount", "world_from_context"]

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
    otherwise, which is how a mount error is simulated. In a cell of several cameras
    (``[[cameras]]``) ``[[sim.cameras]]`` gives the true poses of the cameras built with a
    placement, and ``[sim.plate]`` a plate the arm holds (:mod:`cellcal.sims.placement`).
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
    cameras: list[SimCameraTruth] = field(default_factory=list, metadata={
        "max_items": MAX_SIM_CAMERAS, "doc": "true poses of the cameras of [[cameras]] built with a placement, "
                                             "by name (default: where they are configured)"})
    plate: PlateConfig | None = field(default=None, metadata={
        "doc": "a flat plate the arm holds, fixed in the flange frame (every simulated camera sees it)"})

    def __post_init__(self) -> None:
        if float(np.linalg.norm(self.plane_normal)) < 1e-9:
            raise ConfigError("must be a non-zero vector", key="sim.plane_normal")
        check_truth_names(self.cameras)

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


# ---------------------------------------------------------------------- the world
class SimWorld:
    """Scene + true mount + true arm state + clock + seed + the camera's artefacts and systematic errors.

    The camera renders from :meth:`camera_pose` = true flange pose @ true mount; a camera of
    ``[[cameras]]`` built with a placement renders from its own pose (:meth:`place_camera`), and every
    camera sees the plate the arm holds, if any, in :meth:`scene_at`.

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
        #: The plate the arm holds (``[sim.plate]``), or None.
        self.plate: PlateConfig | None = None
        #: True poses of the placed cameras by name (``[[sim.cameras]]``).
        self.camera_truths: tuple[SimCameraTruth, ...] = ()
        #: The cameras built with a placement in this world, by name (:meth:`place_camera`).
        self.placed: dict[str, CameraPlacement] = {}
        #: New true poses of placed cameras from ``[[sim.events]]`` naming them (a knocked camera), by name.
        self.moved: dict[str, Pose] = {}
        #: How many cameras were built without one (the camera a run drives through ``[camera]``/``[mount]``).
        self.driven_cameras = 0
        #: The cell's cameras' names when the builder gave them (``BackendContext.camera_names``), else empty.
        self.cell_camera_names: tuple[str, ...] = ()

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
        world.plate = config.plate
        world.camera_truths = tuple(config.cameras)
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
        return self.on_flange(flange, self.mount)

    def on_flange(self, flange: Pose, mount: Pose) -> Pose:
        """``T_base_camera`` of a camera with true mount ``mount`` when the flange truly stands at ``flange``.

        With :attr:`camera_flange` set (``camera_on_arm = false``) the camera stays at ``camera_flange @ mount``.
        """
        fixed = self.camera_flange
        return (flange if fixed is None else fixed) @ mount

    def place_camera(self, placement: CameraPlacement) -> Pose:
        """Register a camera of ``[[cameras]]`` built with ``placement``; returns its true pose.

        The pose is its ``[[sim.cameras]]`` entry's, else the configured one
        (:func:`~cellcal.sims.placement.true_placement_pose`): ``T_flange_camera`` for a camera on
        the flange (it renders from :meth:`on_flange`), ``T_base_camera`` for a fixed one.
        """
        self.placed[placement.name] = placement
        return true_placement_pose(placement, truth_of(self.camera_truths, placement.name))

    def check_camera_truths(self, source: str | None = None) -> None:
        """Refuse ``[[sim.cameras]]`` entries that name no camera of the cell (once every camera is built).

        The placed cameras are known by name; the camera a run drives through ``[camera]``/``[mount]``
        (built without a placement) is not, so one entry naming no placed camera is taken as naming it
        when such a camera was built in this world, and none otherwise.

        Raises:
            ConfigError: One line naming the first entry too many and the placed cameras.
        """
        for i, event in enumerate(self.events):
            if event.camera is not None and self.cell_camera_names and event.camera not in self.cell_camera_names:
                raise ConfigError(f"{event.camera!r} names no camera of the cell (its cameras: "
                                  f"{', '.join(self.cell_camera_names)})", source=source, key=f"sim.events[{i}].camera")
        if self.cell_camera_names:  # the cell named its cameras: the truths must name them, exactly
            for i, truth in enumerate(self.camera_truths):
                if truth.name not in self.cell_camera_names:
                    raise ConfigError(f"{truth.name!r} names no camera of the cell (its cameras: "
                                      f"{', '.join(self.cell_camera_names)})", source=source,
                                      key=f"sim.cameras[{i}].name")
            return
        unmatched = [i for i, truth in enumerate(self.camera_truths) if truth.name not in self.placed]
        allowed = 1 if self.driven_cameras else 0
        if len(unmatched) > allowed:
            names = " and ".join(repr(self.camera_truths[i].name) for i in unmatched)
            placed = ", ".join(sorted(self.placed)) or "none"
            one = "; one may name the camera the run drives through [camera]" if allowed else ""
            i = unmatched[allowed]
            raise ConfigError(f"{names} name no camera of the cell: {self.camera_truths[i].name!r} is one too many "
                              f"(placed: {placed}{one})", source=source, key=f"sim.cameras[{i}].name")

    def scene_at(self, flange: Pose | None = None) -> Scene:
        """The scene a frame sees: :attr:`scene`, plus the plate at the true flange pose ``flange`` (None: now)."""
        plate = self.plate
        if plate is None:
            return self.scene
        return self.scene.with_solids((plate.solid(self.true_flange_pose() if flange is None else flange),))

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
            if mount is not None and event.camera is not None and event.camera in self.placed:
                self.moved[event.camera] = mount  # a placed camera's new true pose in its parent frame
            elif mount is not None:
                self.mount = mount  # the camera the run drives (unnamed, or named as the one not placed)
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
