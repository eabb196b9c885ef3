"""The simulated cell's several cameras and the plate the arm holds: ``[[sim.cameras]]``, ``[sim.plate]``.

A camera of ``[[cameras]]`` other than the one a run drives is built with a
:class:`~cellcal.devices.base.CameraPlacement` (issue #40, ADR 0061): fixed in the base frame
(``on = "base"``) or on the flange (``on = "flange"``). Its true pose is its ``[[sim.cameras]]``
entry's (:class:`SimCameraTruth`), else the configured one (:func:`true_placement_pose`). The
plate (:class:`PlateConfig`) is fixed in the flange frame; every simulated camera sees it at the
arm's true flange pose (:meth:`PlateConfig.solid`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from cellcal.devices.base import CameraPlacement
from cellcal.devices.errors import ConfigError
from cellcal.devices.pose import Pose

from .scene import DEFAULT_REFLECTIVITY, MAX_REFLECTIVITY, Solid

__all__ = ["PLATE_FACE", "PlateConfig", "SimCameraTruth", "check_truth_names", "true_placement_pose",
           "truth_of"]

#: Face number of the plate's measured face among its solid's six (the plate frame's -z face: ``2 * axis``).
PLATE_FACE = 4
#: Most ``[[sim.cameras]]`` entries (as many as a cell has cameras at most).
MAX_SIM_CAMERAS = 16


@dataclass(frozen=True)
class SimCameraTruth:
    """One entry of ``[[sim.cameras]]``: where a camera of ``[[cameras]]`` truly stands.

    For a camera on the flange the pose is its true mount ``T_flange_camera``; for a fixed one its
    true ``T_base_camera``. A key left out is the configured one's (``[cameras.mount]`` or
    ``[cameras.pose]``), so an entry with neither key changes nothing. It applies to a camera built
    with a placement; the camera on the flange a run drives through ``[camera]``/``[mount]`` is
    built without one (the sim does not see its name) and stands at ``[sim.mount]``: a cell whose
    flange camera is run both ways (calibrated itself, carrying the plate for a fixed one) gives its
    truth in both.
    """

    name: str = field(metadata={"max_len": 32, "doc": "the camera's name in [[cameras]]"})
    translation_m: tuple[float, float, float] | None = field(default=None, metadata={
        "ge": -20.0, "le": 20.0,
        "doc": "true origin, m: in the flange frame (on the flange) or the base frame (fixed)"})
    rpy_deg: tuple[float, float, float] | None = field(default=None, metadata={
        "ge": -360.0, "le": 360.0, "doc": "true roll, pitch, yaw about the parent's fixed axes, degrees"})


@dataclass(frozen=True)
class PlateConfig:
    """``[sim.plate]``: a flat rectangular plate held by the arm, fixed in the flange frame.

    The plate frame sits at the centre of the plate's measured face; the face's outward normal is
    the plate frame's -z axis and the plate's body lies behind it (its +z side, ``thickness_m``
    deep); the face's width runs along the plate's x, its height along y. With the default pose
    (0.12 m along the flange's x, axes as the flange's) the plate is a paddle beside the flange
    facing the flange's -z, back toward the arm: a camera fixed above a tool that points down sees
    it, a camera on the flange looking along the flange's +z from below it does not.
    """

    size_m: tuple[float, float] = field(default=(0.2, 0.15), metadata={
        "gt": 0.0, "le": 2.0, "doc": "the face's width (plate x) and height (plate y), m"})
    thickness_m: float = field(default=0.005, metadata={"gt": 0.0, "le": 0.5,
                                                        "doc": "depth behind the face (plate +z), m"})
    translation_m: tuple[float, float, float] = field(default=(0.12, 0.0, 0.0), metadata={
        "ge": -2.0, "le": 2.0, "doc": "centre of the measured face in the flange frame, m"})
    rpy_deg: tuple[float, float, float] = field(default=(0.0, 0.0, 0.0), metadata={
        "ge": -360.0, "le": 360.0, "doc": "plate frame's roll, pitch, yaw in the flange frame, degrees "
                                          "(the face looks along the plate's -z)"})
    reflectivity: float = field(default=DEFAULT_REFLECTIVITY, metadata={
        "gt": 0.0, "le": MAX_REFLECTIVITY, "doc": "near-infrared reflectivity of the plate"})

    def pose(self) -> Pose:
        """``T_flange_plate``: the face's centre frame in the flange frame."""
        return Pose.from_xyz_rpy(np.asarray(self.translation_m), np.radians(self.rpy_deg))

    def face_plane(self, parent_plate: Pose | None = None) -> tuple[NDArray[np.float64], float]:
        """The measured face's plane ``n·x + c = 0`` in the flange frame, or in the frame of ``parent_plate``.

        Args:
            parent_plate: ``T_parent_flange`` (e.g. the true ``T_base_flange``); None: the flange frame.

        Returns:
            ``(n, c)``: the face's unit outward normal (3,) and offset, metres.
        """
        plate = self.pose() if parent_plate is None else parent_plate @ self.pose()
        normal = -plate.rotation_matrix[:, 2]  # the face looks along the plate's -z
        return normal, float(-normal @ plate.translation)

    def solid(self, flange: Pose) -> Solid:
        """The plate as a scene solid at the true flange pose ``flange`` (``T_base_flange``)."""
        plate = flange @ self.pose()
        rot = plate.rotation_matrix
        # the body's centre: half the thickness behind the face (plate +z)
        centre = plate.translation + rot[:, 2] * (self.thickness_m / 2.0)
        return Solid(rot, centre, (self.size_m[0], self.size_m[1], self.thickness_m), self.reflectivity)


def check_truth_names(truths: Sequence[SimCameraTruth], where: str = "sim.cameras") -> None:
    """Refuse two ``[[sim.cameras]]`` entries with one name (one line naming the second).

    Raises:
        ConfigError: A name given twice.
    """
    seen: dict[str, int] = {}
    for i, truth in enumerate(truths):
        if truth.name in seen:
            raise ConfigError(f"two entries are named {truth.name!r} ({where}[{seen[truth.name]}] and "
                              f"{where}[{i}]): one truth per camera", key=f"{where}[{i}].name")
        seen[truth.name] = i


def truth_of(truths: Sequence[SimCameraTruth], name: str) -> SimCameraTruth | None:
    """The ``[[sim.cameras]]`` entry named ``name``, or None."""
    return next((t for t in truths if t.name == name), None)


def true_placement_pose(placement: CameraPlacement, truth: SimCameraTruth | None) -> Pose:
    """A placed camera's true pose: ``T_flange_camera`` on the flange, ``T_base_camera`` fixed.

    Each of the truth's keys replaces the configured pose's part (translation, rotation); a key left
    out, or no truth, keeps the configured part.
    """
    configured = placement.pose
    if truth is None:
        return configured
    translation = configured.translation if truth.translation_m is None else np.asarray(truth.translation_m)
    if truth.rpy_deg is None:
        return configured.with_translation(translation)
    return Pose.from_xyz_rpy(translation, np.radians(truth.rpy_deg))
