"""The cell's cameras: ``[[cameras]]`` (several, each on the flange or fixed in the base frame) or ``[camera]`` (one).

A cell with one camera keeps its ``[camera]`` table and ``[mount]`` (the camera is named ``camera`` and
stands on the flange). A cell with several lists them as ``[[cameras]]``, each with a ``name``, where it
is (``on = "flange"`` with a ``[cameras.mount]``, or ``on = "base"`` with a ``[cameras.pose]``: its pose
in the robot's base frame) and its backend's keys as ``[camera]`` has them (issue #40, ADR 0061).
:func:`parse_cameras` validates the list; :func:`single_camera_document` gives the document a
single-camera command reads for one of them.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from cellcal.core.calibration.sections import MountSection, Vec3
from cellcal.devices.base import CameraPlacement
from cellcal.devices.config import parse_section
from cellcal.devices.errors import ConfigError
from cellcal.devices.pose import Pose

__all__ = ["CAMERA_NAME", "CAMERA_PLACES", "CAPTURE_MODES", "DEFAULT_CAMERA_NAME", "MAX_CAMERAS", "CameraEntry",
           "CameraPoseSection", "CamerasSection", "PlateSection",
           "parse_cameras", "select_camera", "single_camera_document"]

#: Where a camera can stand.
CAMERA_PLACES = ("flange", "base")
#: How a camera captures beside the cell's others at a pose: at the same time, or by itself.
CAPTURE_MODES = ("together", "alone")
#: The name of the camera of a ``[camera]`` table.
DEFAULT_CAMERA_NAME = "camera"
#: Most cameras in one cell (an O3R VPU drives six heads; a cell rarely has more than a few cameras).
MAX_CAMERAS = 16
#: A camera's name: it names files, frames (``/tf``) and metrics, so letters, digits, ``_`` and ``-`` only.
CAMERA_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_-]{0,31}$")
#: Keys of a ``[[cameras]]`` entry that are cellcal's, not the backend's.
_PLACE_KEYS = ("name", "on", "mount", "pose", "capture")


@dataclass(frozen=True)
class CameraPoseSection:
    """``[cameras.pose]``: a fixed camera's frame in the robot's base frame (``T_base_camera``).

    Attributes:
        translation_m: The camera frame's origin in the base frame, metres.
        rpy_deg: The camera frame's roll, pitch, yaw about the base's x, y, z axes, degrees.
    """

    translation_m: Vec3 = field(metadata={"ge": -20.0, "le": 20.0})
    rpy_deg: Vec3 = field(metadata={"ge": -360.0, "le": 360.0})

    def pose(self) -> Pose:
        """The base -> camera transform (``T_base_camera``)."""
        return Pose.from_xyz_rpy(self.translation_m, np.radians(self.rpy_deg))


@dataclass(frozen=True)
class PlateSection:
    """``[plate]``: the flat plate the arm shows a fixed camera (``cellcal handeye`` for ``on = "base"``; ADR 0061).

    The plate frame sits at the centre of the measured face, in the flange frame; the face looks
    along the plate frame's -z, its width runs along x and its height along y (as ``[sim.plate]``).
    The plan puts the face's centre on the fixed camera's optical axis at ``distance_m``, face-on
    and tilted by every ``tilts_deg`` at eight azimuths, the flange rolled in turn.

    Attributes:
        size_m: The face's width and height, m.
        translation_m: The face's centre in the flange frame, m.
        rpy_deg: The plate frame's roll, pitch, yaw in the flange frame, degrees.
        estimate: Fit the plate's plane in the flange with the camera (False: the configured one is exact).
        distance_m: The plan's distance from the fixed camera to the face's centre, m.
        tilts_deg: The plan's angles between the face's normal and the camera's optical axis, degrees.
        region_share: The share of the face (per side) the plane fit looks at, around the predicted centre.
    """

    size_m: tuple[float, float] = field(default=(0.2, 0.15), metadata={"gt": 0.0, "le": 2.0})
    translation_m: Vec3 = field(default=(0.12, 0.0, 0.0), metadata={"ge": -2.0, "le": 2.0})
    rpy_deg: Vec3 = field(default=(0.0, 0.0, 0.0), metadata={"ge": -360.0, "le": 360.0})
    estimate: bool = True
    distance_m: float = field(default=0.6, metadata={"gt": 0.05, "le": 5.0})
    tilts_deg: tuple[float, ...] = field(default=(0.0, 20.0, 30.0, 45.0), metadata={
        "ge": 0.0, "lt": 80.0, "min_items": 2, "max_items": 8})
    region_share: float = field(default=0.6, metadata={"gt": 0.05, "le": 1.0})

    def pose(self) -> Pose:
        """``T_flange_plate``: the face's centre frame in the flange frame."""
        return Pose.from_xyz_rpy(self.translation_m, np.radians(self.rpy_deg))

    def corners_flange(self, share: float = 1.0) -> np.ndarray:
        """The face's corners (4 x 3, m, flange frame), the face scaled by ``share`` about its centre."""
        w, h = 0.5 * share * self.size_m[0], 0.5 * share * self.size_m[1]
        return self.pose().apply(np.array([[-w, -h, 0.0], [w, -h, 0.0], [w, h, 0.0], [-w, h, 0.0]]))


@dataclass(frozen=True)
class CamerasSection:
    """``[[cameras]]``: one camera of a cell of several (cellcal's keys; the rest are its backend's).

    Attributes:
        name: Its name: files, frames and messages carry it (a letter, then letters, digits, ``_``, ``-``).
        on: ``"flange"`` (carried by the arm, with ``[cameras.mount]``) or ``"base"`` (fixed in the cell,
            with ``[cameras.pose]``).
        mount: A camera on the flange: its mount, as ``[mount]``.
        pose: A fixed camera: its pose in the base frame (where it is roughly).
        capture: ``"together"``: it captures at the same time as the cell's other cameras at each pose of a
            run; ``"alone"``: by itself, after them (a ToF or structured-light camera whose emitted light
            would disturb the others' or be disturbed by theirs).
    """

    name: str = field(metadata={"max_len": 32, "doc": "the camera's name (letters, digits, _ and -)"})
    on: Literal["flange", "base"] = field(metadata={"doc": "where it is: carried by the arm, or fixed in the cell"})
    mount: MountSection | None = None
    pose: CameraPoseSection | None = None
    capture: Literal["together", "alone"] = field(default="together", metadata={
        "doc": "at each pose: 'together' with the other cameras, or 'alone' after them (ToF or structured-light "
               "cameras whose emitted light would interfere with each other)"})


@dataclass(frozen=True)
class CameraEntry:
    """One camera of the cell.

    Attributes:
        name: Its name (``camera`` for a ``[camera]`` table).
        on: ``"flange"`` (moves with the arm; ``mount`` is ``T_flange_camera``) or ``"base"`` (fixed;
            ``pose_base`` is ``T_base_camera``, the configured start of its calibration).
        table: Its backend table as ``[camera]`` is: ``backend`` and the backend's own keys.
        mount: The ``[cameras.mount]`` table (flange cameras; None: the identity), raw as ``[mount]`` is.
        pose_base: A fixed camera's configured pose in the base frame (None for flange cameras).
        capture: ``"together"`` or ``"alone"`` (``[[cameras]] capture``; ADR 0061).
        mount_pose: A ``[[cameras]]`` camera on the flange: its ``[cameras.mount]`` as parsed
            (``T_flange_camera``; the identity without one); None for fixed cameras and a ``[camera]`` table.
    """

    name: str
    on: Literal["flange", "base"]
    table: Mapping[str, Any]
    mount: Mapping[str, Any] | None = None
    pose_base: Pose | None = None
    capture: Literal["together", "alone"] = "together"
    mount_pose: Pose | None = None

    def placement(self) -> CameraPlacement | None:
        """Where the camera is configured to stand (its parsed mount or base pose), None when not parsed here."""
        pose = self.pose_base if self.on == "base" else self.mount_pose
        return None if pose is None else CameraPlacement(self.name, self.on, pose)


def _entry(raw: object, index: int, source: str) -> CameraEntry:
    """One ``[[cameras]]`` entry validated (``cameras[index]`` in messages, the camera's name in the text)."""
    where = f"cameras[{index}]"
    if not isinstance(raw, Mapping):
        raise ConfigError(f"expected a table, got {type(raw).__name__}", source=source, key=where)
    # types, ranges and the place's literal as every table's; then what ties the keys together
    section = parse_section(CamerasSection, {k: raw[k] for k in _PLACE_KEYS if k in raw}, where=where, source=source)
    name = section.name
    if not CAMERA_NAME.match(name):
        raise ConfigError(f"needs a name of a letter, then up to 31 letters, digits, '_' or '-' (got {name!r})",
                          source=source, key=f"{where}.name")
    if not isinstance(raw.get("backend"), str):
        raise ConfigError(f"camera {name!r}: missing or non-string 'backend'", source=source, key=f"{where}.backend")
    if section.on == "flange" and section.pose is not None:
        raise ConfigError(f"camera {name!r} is on the flange: it has a [cameras.mount], not a pose in the base frame",
                          source=source, key=f"{where}.pose")
    if section.on == "base" and section.mount is not None:
        raise ConfigError(f"camera {name!r} is fixed (on = \"base\"): it has a [cameras.pose] in the base frame, "
                          "not a mount", source=source, key=f"{where}.mount")
    if section.on == "base" and section.pose is None:
        raise ConfigError(f"fixed camera {name!r} needs its [cameras.pose] (translation_m, rpy_deg in the base "
                          "frame: where it is roughly, the start of its calibration)", source=source,
                          key=f"{where}.pose")
    mount = raw.get("mount")
    table = {k: v for k, v in raw.items() if k not in _PLACE_KEYS}
    mount_pose = None
    if section.on == "flange":  # parsed once here: the builder and the capture of the cell's cameras read it
        mount_pose = Pose.identity() if section.mount is None else section.mount.pose()
    return CameraEntry(name, section.on, table, mount if isinstance(mount, Mapping) else None,
                       None if section.pose is None else section.pose.pose(), section.capture, mount_pose)


def parse_cameras(document: Mapping[str, Any], source: str) -> tuple[CameraEntry, ...]:
    """The cell's cameras from ``[[cameras]]`` or ``[camera]`` (with ``[mount]``).

    Raises:
        ConfigError: Both or neither given, an entry without a name or a place, two cameras with one name,
            more than :data:`MAX_CAMERAS`.
    """
    listed = document.get("cameras")
    if listed is None:
        camera = document.get("camera")
        if not isinstance(camera, Mapping):
            raise ConfigError("missing table (it needs at least backend = \"...\"), or list the cell's cameras "
                              "as [[cameras]]", source=source, key="camera")
        return (CameraEntry(DEFAULT_CAMERA_NAME, "flange", camera, document.get("mount")),)
    if not isinstance(listed, Sequence) or isinstance(listed, str | bytes) or not listed:
        raise ConfigError(f"expected a table per camera ([[cameras]]), one or more; got {type(listed).__name__}",
                          source=source, key="cameras")
    if "camera" in document:
        raise ConfigError("give the cameras either as one [camera] or as [[cameras]], not both",
                          source=source, key="cameras")
    if len(listed) > MAX_CAMERAS:
        raise ConfigError(f"at most {MAX_CAMERAS} cameras, got {len(listed)}", source=source, key="cameras")
    if "mount" in document:
        raise ConfigError("with [[cameras]], each camera on the flange has its own [cameras.mount]",
                          source=source, key="mount")
    entries = tuple(_entry(raw, i, source) for i, raw in enumerate(listed))
    seen: dict[str, int] = {}
    for i, entry in enumerate(entries):
        if entry.name in seen:
            raise ConfigError(f"two cameras are named {entry.name!r} (cameras[{seen[entry.name]}] and "
                              f"cameras[{i}]): names must differ", source=source, key=f"cameras[{i}].name")
        seen[entry.name] = i
    return entries


def select_camera(entries: Sequence[CameraEntry], name: str | None, source: str,
                  allow_fixed: bool = False) -> CameraEntry:
    """The camera a single-camera command runs: ``name``, or the first on the flange.

    Args:
        entries: The cell's cameras.
        name: The one asked for (``--camera``), or None.
        source: For messages.
        allow_fixed: The command runs a fixed camera too (``handeye``); None then still picks the first on the
            flange, or the first camera when none is.

    Raises:
        ConfigError: No camera of that name (the names listed), or the camera is fixed (``on = "base"``)
            and the command runs only cameras the arm carries.
    """
    if name is None:
        flange = [e for e in entries if e.on == "flange"]
        if not flange and allow_fixed:
            return entries[0]
        if not flange:
            raise ConfigError("no camera on the flange (on = \"flange\"): the calibrating commands run a camera "
                              "the arm carries; a cell of fixed cameras alone is not runnable yet",
                              source=source, key="cameras")
        return flange[0]
    for i, entry in enumerate(entries):
        if entry.name == name:
            if entry.on != "flange" and not allow_fixed:
                raise ConfigError(f"camera {name!r} is fixed (on = \"base\"): the calibrating commands run a "
                                  "camera on the flange", source=source, key=f"cameras[{i}].on")
            return entry
    raise ConfigError(f"no camera named {name!r}; the cell has: {', '.join(e.name for e in entries)}",
                      source=source, key="cameras")


def single_camera_document(document: Mapping[str, Any], entry: CameraEntry) -> dict[str, Any]:
    """The document a single-camera command reads for ``entry`` (a camera on the flange).

    ``[[cameras]]`` is replaced by ``[camera]`` (the entry's backend table) and ``[mount]`` (its mount).
    """
    out = {k: v for k, v in document.items() if k not in ("cameras", "camera", "mount")}
    out["camera"] = dict(entry.table)
    if entry.mount is not None:
        out["mount"] = dict(entry.mount)
    return out
