"""The tables of a cell configuration as typed, validated dataclasses (ADR 0004).

One dataclass per table: ``[cell]``, ``[mount]``, ``[handeye]``, ``[reference]``, ``[region]``,
``[safety]``, ``[plan]`` (with ``[[plan.poses]]``) and ``[monitor]``; each field's metadata
bounds what :func:`~cellcal.devices.config.parse_section` accepts, ``__post_init__`` checks
what spans fields. The document as a whole (which tables, the backends, ``from_handeye``)
is :mod:`cellcal.core.calibration.config`'s. SI units unless a key says otherwise (``_deg``,
``_px``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import cv2
import numpy as np

from cellcal.core.methods.fullframe.expected import DEFAULT_SEARCH_TOLERANCE_DEG, DEFAULT_SEARCH_TOLERANCE_M
from cellcal.core.methods.grid import DEFAULT_PERIMETERS_PX, DEFAULT_WINDOW_PX
from cellcal.devices.errors import ConfigError
from cellcal.devices.pose import Pose

__all__ = [
    "ALL_METHODS",
    "MAX_POLYGON_VERTICES",
    "MAX_POSES",
    "CellSection",
    "DepthcalSection",
    "HandEyeParameter",
    "HandEyeSection",
    "MethodName",
    "MonitorSection",
    "MountSection",
    "PlanPose",
    "PlanSection",
    "ReferenceSection",
    "RegionSection",
    "SafetySection",
    "Vec3",
]

Vec3 = tuple[float, float, float]
MethodName = Literal["law_of_cosines", "plane_fit", "plane_fit_nominal", "full_frame"]
ALL_METHODS: tuple[MethodName, ...] = ("law_of_cosines", "plane_fit", "plane_fit_nominal", "full_frame")
#: Most poses a plan may have.
MAX_POSES = 1000


@dataclass(frozen=True)
class CellSection:
    """``[cell]``: identity of the cell, the seed of all simulated randomness, strict mode.

    ``strict = true`` is ``cellcal calibrate --strict`` for this cell: a cross-pose verdict
    saying the poses' planes disagree in the base frame fails the run (exit 1).

    Attributes:
        name: The cell's name, written into every result and report.
        seed: The seed of every random generator of the simulated devices.
        strict: Whether disagreeing poses fail the run (as ``--strict``).
    """

    name: str = field(default="cell", metadata={"max_len": 100})
    seed: int = field(default=0, metadata={"ge": 0, "le": 2**32 - 1})  # what every random generator takes
    strict: bool = False


@dataclass(frozen=True)
class MountSection:
    """``[mount]``: the camera frame in the flange frame (hand-eye transform).

    Attributes:
        translation_m: The camera frame's origin in the flange frame, metres.
        rpy_deg: The camera frame's roll, pitch, yaw about the flange's x, y, z axes, degrees.
        from_handeye: A ``handeye.json`` of ``cellcal handeye`` (relative to the configuration
            file) whose estimated mount replaces ``translation_m`` / ``rpy_deg``.
    """

    translation_m: Vec3 = field(default=(0.0, 0.0, 0.0), metadata={"ge": -2.0, "le": 2.0})
    rpy_deg: Vec3 = field(default=(0.0, 0.0, 0.0), metadata={"ge": -360.0, "le": 360.0})
    #: A ``handeye.json`` of ``cellcal handeye`` (relative to the configuration file) whose
    #: estimated mount replaces ``translation_m`` / ``rpy_deg``.
    from_handeye: str | None = field(default=None, metadata={"max_len": 4096})

    def pose(self) -> Pose:
        """The flange -> camera transform (``T_flange_camera``)."""
        return Pose.from_xyz_rpy(self.translation_m, np.radians(self.rpy_deg))


#: Parameters of the hand-eye estimate a ``[handeye] given`` list may hold at their configured values
#: (mount rotation about the flange axes, mount translation, the base-frame plane's tilts and offset).
HandEyeParameter = Literal["mount_rot_x", "mount_rot_y", "mount_rot_z", "mount_x", "mount_y", "mount_z",
                           "plane_tilt_a", "plane_tilt_b", "plane_offset"]


@dataclass(frozen=True)
class HandEyeSection:
    """``[handeye]``: the plan and the fit of ``cellcal handeye`` (docs/adr/0018-handeye.md).

    The automatic plan views ``target_m`` (default: ``[plan] target_m``) from ``height_m``
    along the optical axis at every ``inclinations_deg`` (optical axis vs. plane), the tool
    pitched toward the base and rolled about its axis by every ``rolls_deg``. ``reach``
    (default: the arm's own) limits the orientations. ``given`` parameters are held at the
    configured ``[mount]`` / ``[reference]`` values instead of estimated; ``given_sigma``
    gives some of them a 1-sigma (m or rad) that enters the intervals (a prior). When the
    residuals exceed the stated noise (chi2 test, each tail at ``noise_test_level``) the
    intervals are scaled by sqrt(chi2/dof), and beyond ``max_interval_scale`` the fit is
    refused (docs/adr/0030-handeye-noise-model.md).

    Attributes:
        height_m: The camera's distance from ``target_m`` along its optical axis at each view, metres.
        reach: The arm's reach model that limits the plan's orientations (``xarm5``; ``any``: none).
        arm_rotation_sigma_deg: The 1-sigma of the arm's read-back orientation, degrees (0: exact).
        confidence: The level of the reported intervals (0.95: 95 % intervals).
    """

    inclinations_deg: tuple[float, ...] = field(default=(80.0, 65.0),
                                                metadata={"ge": 10.0, "le": 90.0, "min_items": 1, "max_items": 20})
    rolls_deg: tuple[float, ...] = field(default=(0.0, 90.0, 180.0, 270.0),
                                         metadata={"ge": -360.0, "le": 360.0, "min_items": 1, "max_items": 72})
    height_m: float = field(default=0.45, metadata={"ge": 0.05, "le": 10.0})
    target_m: Vec3 | None = field(default=None, metadata={"ge": -10.0, "le": 10.0})
    reach: Literal["any", "xarm5"] | None = None
    given: tuple[HandEyeParameter, ...] = field(default=(), metadata={"max_items": 9})
    arm_translation_sigma_m: float = field(default=2.5e-5, metadata={"ge": 0.0, "le": 0.01})
    arm_rotation_sigma_deg: float = field(default=0.0, metadata={"ge": 0.0, "le": 1.0})
    confidence: float = field(default=0.95, metadata={"ge": 0.5, "le": 0.9999})
    given_sigma: dict[str, float] = field(default_factory=dict)  # parameter name -> 1-sigma, m or rad
    noise_test_level: float = field(default=0.01, metadata={"ge": 1e-9, "le": 0.5})
    max_interval_scale: float = field(default=10.0, metadata={"ge": 1.0, "le": 1e6})
    # the ChArUco board of --method charuco|both (the simulator prints it where [sim.charuco] says)
    charuco_squares: tuple[int, int] = field(default=(7, 5), metadata={"ge": 2, "le": 40})
    charuco_square_m: float = field(default=0.04, metadata={"gt": 0.001, "le": 1.0})
    charuco_marker_ratio: float = field(default=0.75, metadata={"ge": 0.3, "le": 0.95})
    charuco_dictionary: Literal["4X4_50", "4X4_100", "5X5_50", "5X5_100", "6X6_50", "6X6_250"] = "4X4_50"

    def __post_init__(self) -> None:
        if len(set(self.given)) != len(self.given):
            raise ValueError("handeye.given lists a parameter twice")
        for name, sigma in self.given_sigma.items():
            key = f"handeye.given_sigma.{name}"
            if name not in self.given:
                raise ConfigError(f"not in handeye.given ({', '.join(self.given) or 'empty'}): only a given "
                                  "parameter takes a sigma", key=key)
            if isinstance(sigma, bool) or not isinstance(sigma, (int, float)) or not 0 < sigma <= 1.0:
                raise ConfigError(f"expected a number > 0 and <= 1 (metres or radians), got {sigma!r}", key=key)


@dataclass(frozen=True)
class ReferenceSection:
    """``[reference]``: the measuring plane as the cell believes it, base frame.

    With ``search`` (default) and a ``[mount]`` table, the full-frame fit at each pose looks
    for the plane within ``search_tolerance_deg`` (normal) and ``search_tolerance_m``
    (distance from the camera) of this one seen from the camera, so that a floor, a wall or
    a box top is not taken for it; ``search = false`` lets the whole image decide (ADR 0031).

    Attributes:
        plane_point_m: A point of the measuring plane, base frame, metres.
        plane_normal: The plane's normal, base frame (any length; normalised).
    """

    plane_point_m: Vec3 = field(default=(0.0, 0.0, 0.0), metadata={"ge": -10.0, "le": 10.0})
    plane_normal: Vec3 = field(default=(0.0, 0.0, 1.0), metadata={"ge": -1e6, "le": 1e6})  # norm cannot overflow
    search: bool = True
    search_tolerance_deg: float = field(default=DEFAULT_SEARCH_TOLERANCE_DEG, metadata={"gt": 0.0, "le": 90.0})
    search_tolerance_m: float = field(default=DEFAULT_SEARCH_TOLERANCE_M, metadata={"gt": 0.0, "le": 10.0})

    def __post_init__(self) -> None:
        if not np.linalg.norm(self.plane_normal) > 0:
            raise ValueError("reference.plane_normal must be non-zero")

    @property
    def search_tolerance_rad(self) -> float:
        """``search_tolerance_deg`` in radians."""
        return math.radians(self.search_tolerance_deg)


#: Most vertices a ``[region] polygon_px`` may have.
MAX_POLYGON_VERTICES = 1000
#: Largest |u| or |v| of a polygon vertex, pixels (far beyond any depth image).
MAX_PIXEL_COORD = 100_000.0
#: Smallest area a region polygon may enclose, square pixels.
MIN_POLYGON_AREA_PX2 = 1.0


@dataclass(frozen=True)
class RegionSection:
    """``[region]``: the region of interest of the full-frame fit and its gates (ADR 0031).

    ``polygon_px``: vertices ``[u, v]`` of a polygon in pixels of the depth image (pixel
    centres at integer coordinates, ``u`` along the columns, ``v`` down the rows).
    ``box_min_m`` / ``box_max_m``: opposite corners of an axis-aligned box in the base frame,
    metres; at each pose the region holds the pixels whose ray (from the camera pose the
    arm reports, with ``[mount]``) passes through the box. Both given: the pixels in both.
    Neither (an empty table, or no table): the whole image.

    Attributes:
        polygon_px: The polygon's vertices ``[u, v]``, pixels.
        box_min_m: The box's lower corner (x, y, z), base frame, metres.
        box_max_m: The box's upper corner (x, y, z), base frame, metres.
    """

    polygon_px: tuple[tuple[float, float], ...] | None = field(
        default=None, metadata={"min_items": 3, "max_items": MAX_POLYGON_VERTICES})
    box_min_m: Vec3 | None = field(default=None, metadata={"ge": -10.0, "le": 10.0})
    box_max_m: Vec3 | None = field(default=None, metadata={"ge": -10.0, "le": 10.0})

    def __post_init__(self) -> None:
        if self.polygon_px is not None:
            for i, (u, v) in enumerate(self.polygon_px):
                if max(abs(u), abs(v)) > MAX_PIXEL_COORD:
                    raise ConfigError(f"vertex ({u:g}, {v:g}) px is beyond +-{MAX_PIXEL_COORD:g} px",
                                      key=f"polygon_px[{i}]")
            area = cv2.contourArea(np.asarray(self.polygon_px, np.float32))   # shoelace area, px^2
            if not area >= MIN_POLYGON_AREA_PX2:
                raise ConfigError(f"the polygon encloses {area:g} px^2 (vertices on one line?); "
                                  f"at least {MIN_POLYGON_AREA_PX2:g} px^2", key="polygon_px")
        if (self.box_min_m is None) != (self.box_max_m is None):
            missing = "box_min_m" if self.box_min_m is None else "box_max_m"
            raise ConfigError("a base-frame box needs both box_min_m and box_max_m", key=missing)
        if self.box_min_m is not None and self.box_max_m is not None:
            for axis, lo, hi in zip("xyz", self.box_min_m, self.box_max_m, strict=True):
                if not lo < hi:
                    raise ConfigError(f"must exceed box_min_m on every axis ({axis}: {hi:g} <= {lo:g} m)",
                                      key="box_max_m")

    @property
    def whole_image(self) -> bool:
        """Whether no region is set (the fit and its gates see the whole image)."""
        return self.polygon_px is None and self.box_min_m is None


@dataclass(frozen=True)
class SafetySection:
    """``[safety]``: the motion envelope every arm command is checked against, and how a move must arrive.

    Ranges are those of a real cell (ADR 0016): a workspace within 10 m of the base, speeds
    from 0.1 mm/s, an arrival tolerance of at most 100 mm / 10 deg (unset: the arm's own
    default, 1 mm / 0.1 deg for an industrial arm).

    Attributes:
        workspace_min_m: The envelope's lower corner (x, y, z) for the flange, base frame, metres.
        workspace_max_m: The envelope's upper corner (x, y, z) for the flange, base frame, metres.
        max_speed_m_s: The fastest tool speed any command may ask, m/s.
        max_acceleration_m_s2: The largest tool acceleration any command may ask, m/s^2.
        min_standoff_m: The least distance from the camera's origin to the measuring plane, metres.
        arrival_tolerance_m: How far from its target a finished move may end, metres.
        arrival_tolerance_deg: How far from its target orientation a finished move may end, degrees.
    """

    workspace_min_m: Vec3 = field(default=(-0.7, -0.7, 0.0), metadata={"ge": -10.0, "le": 10.0})
    workspace_max_m: Vec3 = field(default=(0.7, 0.7, 1.0), metadata={"ge": -10.0, "le": 10.0})
    max_speed_m_s: float = field(default=0.25, metadata={"ge": 1e-4, "le": 3.0})
    max_acceleration_m_s2: float = field(default=2.0, metadata={"ge": 1e-3, "le": 150.0})
    min_standoff_m: float = field(default=0.15, metadata={"ge": 0, "le": 10.0})
    arrival_tolerance_m: float | None = field(default=None, metadata={"ge": 1e-6, "le": 0.1})
    arrival_tolerance_deg: float | None = field(default=None, metadata={"ge": 1e-4, "le": 10.0})

    def __post_init__(self) -> None:
        for axis, lo, hi in zip("xyz", self.workspace_min_m, self.workspace_max_m, strict=True):
            if not lo < hi:
                raise ValueError(f"safety.workspace_min_m must be < workspace_max_m on {axis} ({lo} >= {hi})")


@dataclass(frozen=True)
class PlanPose:
    """One explicit flange pose of ``[[plan.poses]]``, base frame.

    Attributes:
        xyz_m: The flange position, base frame, metres.
        rpy_deg: The flange orientation as roll, pitch, yaw about the base's x, y, z axes, degrees.
    """

    xyz_m: Vec3 = field(metadata={"ge": -10.0, "le": 10.0})
    rpy_deg: Vec3 = field(default=(180.0, 0.0, 0.0), metadata={"ge": -360.0, "le": 360.0})

    def pose(self) -> Pose:
        """The flange pose."""
        return Pose.from_xyz_rpy(self.xyz_m, np.radians(self.rpy_deg))


@dataclass(frozen=True)
class PlanSection:
    """``[plan]``: where to measure and how.

    ``nominal_fov_deg`` is the datasheet field of view (x, y) used by the paper's
    ``plane_fit_nominal`` method; by default the pinhole field of view of the intrinsics.

    Unless explicit ``poses`` are given, one camera pose is generated per height: the
    optical axis hits ``target_m`` on the reference plane at ``height`` metres, tilted
    so it makes ``inclination_deg`` with the plane, by a rotation about the camera's
    ``tilt_axis`` (the paper's experiment: 0.46/0.59/0.61 m at 80 deg). Each height is
    repeated at every ``azimuths_deg`` (the pose turned about the plane normal through
    the target): views from several sides are what makes the cross-pose consistency of
    the plane a real check on the hand-eye transform; the default, one azimuth, is the
    paper's plan.

    Attributes:
        tilt_axis: The camera axis (``x`` or ``y``) the tilt turns about.
        target_m: Where the optical axis meets the reference plane, base frame, metres.
        poses: Explicit flange poses (``[[plan.poses]]``) instead of the generated ones.
        perimeters_px: Half-sizes of the P1-P9 grid squares around the image centre, pixels.
        methods: The paper's methods to run at each pose.
        frames_per_pose: Frames captured at each pose (measured together).
        window_px: The odd side of the median window around each grid point, pixels.
        settle_s: The wait after a move before the first capture, seconds.
        speed_m_s: The tool speed of the plan's moves, m/s (capped by ``[safety]``).
        acceleration_m_s2: The tool acceleration of the plan's moves, m/s^2 (capped by ``[safety]``).
        move_timeout_s: The deadline of one move, seconds.
        capture_timeout_s: The deadline of one capture, seconds.
        nominal_fov_deg: The datasheet field of view (x, y), degrees.
    """

    heights_m: tuple[float, ...] = field(default=(0.46, 0.59, 0.61),
                                         metadata={"ge": 0.01, "le": 10.0, "min_items": 1, "max_items": 100})
    inclination_deg: float = field(default=80.0, metadata={"ge": 1, "le": 90})
    tilt_axis: Literal["x", "y"] = "x"
    azimuths_deg: tuple[float, ...] = field(default=(0.0,),
                                            metadata={"ge": -360, "le": 360, "min_items": 1, "max_items": 360})
    target_m: Vec3 = field(default=(0.3, 0.0, 0.0), metadata={"ge": -10.0, "le": 10.0})
    poses: tuple[PlanPose, ...] = field(default=(), metadata={"max_items": MAX_POSES})
    perimeters_px: tuple[int, ...] = field(default=DEFAULT_PERIMETERS_PX,
                                           metadata={"ge": 1, "le": 10000, "min_items": 1, "max_items": 100})
    methods: tuple[MethodName, ...] = field(default=ALL_METHODS, metadata={"min_items": 1})
    frames_per_pose: int = field(default=1, metadata={"ge": 1, "le": 100})
    window_px: int = field(default=DEFAULT_WINDOW_PX, metadata={"ge": 1, "le": 15})
    settle_s: float = field(default=0.0, metadata={"ge": 0, "le": 60})
    # a collaborative arm's slowest useful and fastest possible tool motion (the envelope's own caps)
    speed_m_s: float = field(default=0.2, metadata={"ge": 0.001, "le": 3.0})
    acceleration_m_s2: float = field(default=1.0, metadata={"ge": 0.01, "le": 150.0})
    move_timeout_s: float = field(default=60.0, metadata={"ge": 0.1, "le": 3600})
    capture_timeout_s: float = field(default=2.0, metadata={"ge": 0.01, "le": 600})
    nominal_fov_deg: tuple[float, float] | None = field(default=None, metadata={"gt": 0, "lt": 180})

    def __post_init__(self) -> None:
        n_poses = len(self.poses) or len(self.heights_m) * len(self.azimuths_deg)
        if n_poses > MAX_POSES:
            raise ValueError(f"plan has {n_poses} poses (heights x azimuths); at most {MAX_POSES}")
        if self.window_px % 2 != 1:
            raise ValueError(f"plan.window_px must be odd, got {self.window_px}")
        if len(set(self.methods)) != len(self.methods):
            raise ValueError("plan.methods lists a method twice")


@dataclass(frozen=True)
class MonitorSection:
    """``[monitor]``: the live drift monitor (``cellcal monitor``, :mod:`cellcal.core.monitor.monitor`).

    Per frame the plane's tilt and height (along the optical axis) are compared with a
    baseline; drift is flagged when the median deviation over the last
    ``window_frames`` frames exceeds its threshold, and cleared only once both medians
    stay below ``hysteresis_ratio`` times their thresholds for ``clear_s`` seconds of
    frame time. Each effective threshold is at least ``noise_sigmas`` times the
    frame-to-frame noise measured over the ``baseline_frames`` first frames, so plain
    noise cannot flag whatever the configured value.
    """

    period_s: float = field(default=0.1, metadata={"ge": 0, "le": 3600, "doc": "min. wall time between captures, s"})
    capture_timeout_s: float = field(default=2.0, metadata={"ge": 0.01, "le": 600, "doc": "per-capture timeout, s"})
    connect_timeout_s: float = field(default=10.0, metadata={"ge": 0.1, "le": 600, "doc": "per-camera connect, s"})
    baseline_frames: int = field(default=20, metadata={"ge": 2, "le": 100000, "doc": "frames for baseline/noise"})
    tilt_threshold_deg: float = field(default=0.2, metadata={"ge": 0.001, "le": 90, "doc": "tilt drift threshold, deg"})
    height_threshold_m: float = field(default=0.002, metadata={"ge": 1e-5, "le": 10,
                                                              "doc": "height drift threshold, m"})
    noise_sigmas: float = field(default=6.0, metadata={"ge": 0, "le": 1000,
                                                       "doc": "thresholds >= this many measured noise sigmas"})
    window_frames: int = field(default=5, metadata={"ge": 1, "le": 10000, "doc": "median window, frames"})
    hysteresis_ratio: float = field(default=0.5, metadata={"ge": 0.01, "le": 1, "doc": "clear level / threshold"})
    clear_s: float = field(default=1.0, metadata={"ge": 0, "le": 86400, "doc": "time below the clear level, s"})
    status_every_s: float = field(default=1.0, metadata={"ge": 0.01, "le": 86400, "doc": "CLI status line period, s"})

    @property
    def tilt_threshold_rad(self) -> float:
        """``tilt_threshold_deg`` in radians."""
        return math.radians(self.tilt_threshold_deg)


@dataclass(frozen=True)
class DepthcalSection:
    """``[depthcal]``: the plan and the fit of ``cellcal depthcal`` (docs/adr/0057-depthcal-command.md).

    The plan views ``target_m`` (default: ``[plan] target_m``) from every height (along the
    optical axis; default: three heights spread over the ``[plan]`` heights, at least 0.3 m
    apart end to end) at every inclination; a tilted view is taken at two tool rolls 90
    degrees apart, the pair turning by 180 degrees from one height to the next, so that the
    plane's slope crosses the image in four directions. From one height to the next the
    target moves by ``offset_m`` across the base's y axis (-, 0, +): other arm configurations,
    another part of the table. Frames are fitted uncorrected; every ``holdout_every``-th is
    held out of the fit to measure its error before and after.

    Attributes:
        heights_m: The camera's distances from the target along its optical axis, metres (unset: from ``[plan]``).
        inclinations_deg: The optical axis' angles with the plane, degrees (90: looking straight at it).
        rolls_deg: Tool rolls about its axis the tilted views take, in pairs, degrees.
        offset_m: The target's move across the base's y axis from one height to the next, metres.
        target_m: Where the optical axis meets the plane, base frame, metres (unset: ``[plan] target_m``).
        field_max_order: The highest order of the image field tried (chosen by held-out error).
        holdout_every: Every this-many-th view is held out of the fit.
        frames_per_pose: Frames captured at each pose (each frame a view of its own).
        max_points_per_view: Pixels of a view the fit uses at most (a seeded sample).
        wiggle_period_m: A ToF camera's wiggling period in range, metres (unset: the measurement model's when it
            allows for a wiggle, else none).
    """

    heights_m: tuple[float, ...] | None = field(default=None, metadata={"ge": 0.05, "le": 10.0, "min_items": 1,
                                                                         "max_items": 20})
    inclinations_deg: tuple[float, ...] = field(default=(90.0, 80.0, 70.0),
                                                metadata={"ge": 10.0, "le": 90.0, "min_items": 1, "max_items": 20})
    rolls_deg: tuple[float, ...] = field(default=(0.0, 90.0, 180.0, 270.0),
                                         metadata={"ge": -360.0, "le": 360.0, "min_items": 1, "max_items": 72})
    offset_m: float = field(default=0.05, metadata={"ge": 0.0, "le": 1.0})
    target_m: Vec3 | None = field(default=None, metadata={"ge": -10.0, "le": 10.0})
    field_max_order: int = field(default=3, metadata={"ge": 0, "le": 4})
    holdout_every: int = field(default=4, metadata={"ge": 2, "le": 1000})
    frames_per_pose: int = field(default=1, metadata={"ge": 1, "le": 20})
    max_points_per_view: int = field(default=16000, metadata={"ge": 100, "le": 1_000_000})
    wiggle_period_m: float | None = field(default=None, metadata={"gt": 0.0, "le": 100.0})
