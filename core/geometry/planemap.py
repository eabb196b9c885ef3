"""Pixel <-> measuring-plane mapping: an image detection becomes a robot target.

A :class:`PlaneMap` holds the calibrated camera (distortion included), the plane in the
camera frame and optionally ``T_base_camera``; it maps pixels to plane points (camera or
base frame) and back, vectorised over any leading shape. Unmappable inputs give NaN
(conventions in ADR 0002).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cellcal.core.geometry.planes import Plane
from cellcal.devices.errors import CalibrationError
from cellcal.devices.geometry.camera_model import UNDISTORT_FAIL_PX, _undistort, normalized_to_pixels
from cellcal.devices.pose import Pose
from cellcal.devices.types import Intrinsics

FloatArray = NDArray[np.float64]

__all__ = ["PlaneMap"]


def _as_array(values: ArrayLike, dim: int, what: str) -> FloatArray:
    """A float array of shape (..., dim); raises a one-line error otherwise."""
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise CalibrationError(f"{what} must be numeric with shape (..., {dim})") from None
    if arr.ndim == 0 or arr.shape[-1] != dim:
        raise CalibrationError(f"{what} must have shape (..., {dim}), got {arr.shape}")
    return arr


def _plane_from_dict(data: Any, what: str) -> Plane:
    try:
        return Plane.from_dict(data)
    except (KeyError, TypeError, ValueError):
        raise CalibrationError(f"{what} must be {{'normal': [3 numbers], 'offset_m': number}}") from None


def _pose_from_dict(data: Any, what: str) -> Pose:
    try:
        return Pose.from_dict(data)
    except (KeyError, TypeError, ValueError):
        raise CalibrationError(f"{what} must be a pose with translation_m and quaternion_xyzw") from None


def _intrinsics_from_dict(data: Any) -> Intrinsics:
    if not isinstance(data, Mapping):
        raise CalibrationError("the result has no camera_intrinsics (written by cellcal.calibration/2 and later)")
    try:
        return Intrinsics(**data)
    except TypeError as exc:
        raise CalibrationError(f"camera_intrinsics are malformed: {exc}") from None


@dataclass(frozen=True, eq=False)
class PlaneMap:
    """Pixel <-> point-on-the-measuring-plane mapping of one calibrated camera.

    Attributes:
        intrinsics: The camera's lens model (distortion honoured).
        plane_cam: The measuring plane in the camera frame, metres.
        camera_in_base: ``T_base_camera`` (camera pose in the robot base frame), or None
            when only camera-frame mapping is needed.
    """

    intrinsics: Intrinsics
    plane_cam: Plane
    camera_in_base: Pose | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.intrinsics, Intrinsics):
            raise CalibrationError(f"PlaneMap.intrinsics must be Intrinsics, got {type(self.intrinsics).__name__}")
        if not isinstance(self.plane_cam, Plane):
            raise CalibrationError(f"PlaneMap.plane_cam must be a Plane, got {type(self.plane_cam).__name__}")
        if self.camera_in_base is not None and not isinstance(self.camera_in_base, Pose):
            raise CalibrationError(
                f"PlaneMap.camera_in_base must be a Pose or None, got {type(self.camera_in_base).__name__}")

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_base_plane(cls, intrinsics: Intrinsics, plane_base: Plane, camera_in_base: Pose) -> PlaneMap:
        """From the plane in the base frame and the camera's current pose ``T_base_camera``.

        This is the robot's use: the calibrated (consensus) plane stays fixed in the base
        frame while the camera moves with the arm.
        """
        if not isinstance(camera_in_base, Pose):
            raise CalibrationError(f"camera_in_base must be a Pose, got {type(camera_in_base).__name__}")
        return cls(intrinsics, plane_base.transformed(camera_in_base.inv()), camera_in_base)

    @classmethod
    def from_pose_record(cls, record: Mapping[str, Any], *, plane_key: str = "full_frame") -> PlaneMap:
        """From one pose of a result document (``document["poses"][i]``).

        Uses the pose's ``camera_intrinsics``, its ``camera_pose`` (``T_base_camera`` from
        the arm's reported flange pose and the configured mount) and the plane measured
        there by ``plane_key`` (``record[plane_key]["plane_cam"]``).

        Raises:
            CalibrationError: If the record lacks any of these.
        """
        section = record.get(plane_key)
        if not isinstance(section, Mapping) or "plane_cam" not in section:
            raise CalibrationError(f"pose record has no '{plane_key}' plane (was the method run?)")
        return cls(_intrinsics_from_dict(record.get("camera_intrinsics")),
                   _plane_from_dict(section["plane_cam"], f"{plane_key}.plane_cam"),
                   _pose_from_dict(record.get("camera_pose"), "camera_pose"))

    @classmethod
    def from_document(cls, document: Mapping[str, Any], *, pose_index: int | None = None,
                      camera_in_base: Pose | None = None) -> PlaneMap:
        """From a calibration result document (``result.json`` loaded).

        Args:
            document: The result document.
            pose_index: Map with the plane measured at this pose (0-based) and that pose's
                camera pose. None: the consensus plane in the base frame over all poses,
                seen from ``camera_in_base``.
            camera_in_base: With ``pose_index=None``, the camera's current ``T_base_camera``
                (required); with a pose index, overrides the recorded camera pose.

        Raises:
            CalibrationError: If the document lacks what is needed.
        """
        poses = document.get("poses")
        if not isinstance(poses, list) or not poses:
            raise CalibrationError("result document has no poses")
        if pose_index is not None:
            if not -len(poses) <= pose_index < len(poses):
                raise CalibrationError(f"pose_index {pose_index} out of range for {len(poses)} poses")
            pm = cls.from_pose_record(poses[pose_index])
            return pm if camera_in_base is None else cls.from_base_plane(pm.intrinsics, pm.plane_base, camera_in_base)
        if camera_in_base is None:
            raise CalibrationError("mapping with the consensus plane needs the camera's current camera_in_base pose")
        cons = (document.get("summary") or {}).get("plane_consistency") or {}
        if "consensus_plane_base" not in cons:
            raise CalibrationError("result document has no consensus plane (summary.plane_consistency)")
        plane = _plane_from_dict(cons["consensus_plane_base"], "consensus_plane_base")
        return cls.from_base_plane(_intrinsics_from_dict(poses[0].get("camera_intrinsics")), plane, camera_in_base)

    # ------------------------------------------------------------------ frames
    def _base_pose(self) -> Pose:
        if self.camera_in_base is None:
            raise CalibrationError("this PlaneMap has no camera pose in the base frame (give camera_in_base)")
        return self.camera_in_base

    @property
    def plane_base(self) -> Plane:
        """The measuring plane in the base frame (needs ``camera_in_base``)."""
        return self.plane_cam.transformed(self._base_pose())

    def with_camera_pose(self, camera_in_base: Pose) -> PlaneMap:
        """The same base-frame plane seen from another camera pose (``T_base_camera``)."""
        return PlaneMap.from_base_plane(self.intrinsics, self.plane_base, camera_in_base)

    # ------------------------------------------------------------------ pixel -> plane
    def rays_cam(self, uv: ArrayLike) -> FloatArray:
        """Viewing rays ``(x/z, y/z, 1)`` (camera frame, not unit) through pixels ``(..., 2)``.

        NaN where the pixel is NaN/inf or the lens model does not invert there.
        """
        px = _as_array(uv, 2, "pixels")
        flat = px.reshape(-1, 2)
        rays = np.full((flat.shape[0], 3), np.nan)
        ok = np.all(np.isfinite(flat), axis=1)
        if np.any(ok):
            xy, resid = _undistort(self.intrinsics, np.ascontiguousarray(flat[ok]))
            good = resid <= UNDISTORT_FAIL_PX
            sub = np.full((xy.shape[0], 3), np.nan)
            sub[good, :2] = xy[good]
            sub[good, 2] = 1.0
            rays[ok] = sub
        return rays.reshape((*px.shape[:-1], 3))

    def pixel_to_camera(self, uv: ArrayLike) -> FloatArray:
        """Points on the plane (camera frame, metres) seen at pixels ``uv``.

        Args:
            uv: Distorted pixels ``(u, v)``, shape ``(..., 2)``.

        Returns:
            Shape ``(..., 3)``; NaN where the ray misses the plane (parallel or behind
            the camera) or the pixel does not undistort.

        Raises:
            CalibrationError: If ``uv`` is not numeric with a last axis of 2.
        """
        return self.plane_cam.intersect_rays(self.rays_cam(uv))

    def pixel_to_base(self, uv: ArrayLike) -> FloatArray:
        """Points on the plane in the robot base frame (metres), shape ``(..., 3)``.

        Raises:
            CalibrationError: Bad ``uv`` or no ``camera_in_base``.
        """
        pose = self._base_pose()
        return self._apply(pose, self.pixel_to_camera(uv))

    # ------------------------------------------------------------------ point -> pixel
    def camera_to_pixel(self, points_cam: ArrayLike) -> FloatArray:
        """Distorted pixels of camera-frame points (metres), shape ``(..., 3) -> (..., 2)``.

        Points need not lie on the plane. NaN for points with ``z <= 0`` or NaN/inf.

        Raises:
            CalibrationError: If the input is not numeric with a last axis of 3.
        """
        p = _as_array(points_cam, 3, "camera-frame points")
        flat = p.reshape(-1, 3)
        out = np.full((flat.shape[0], 2), np.nan)
        ok = np.all(np.isfinite(flat), axis=1) & (flat[:, 2] > 0.0)
        if np.any(ok):
            q = flat[ok]
            out[ok] = normalized_to_pixels(self.intrinsics, q[:, :2] / q[:, 2:3])
        return out.reshape((*p.shape[:-1], 2))

    def base_to_pixel(self, points_base: ArrayLike) -> FloatArray:
        """Distorted pixels of base-frame points (metres), shape ``(..., 3) -> (..., 2)``.

        Raises:
            CalibrationError: Bad input or no ``camera_in_base``.
        """
        p = _as_array(points_base, 3, "base-frame points")
        return self.camera_to_pixel(self._apply(self._base_pose().inv(), p))

    def in_image(self, uv: ArrayLike) -> NDArray[np.bool_]:
        """Whether pixels (shape ``(..., 2)``) lie inside the image (pixel centres 0..W-1, 0..H-1)."""
        px = _as_array(uv, 2, "pixels")
        with np.errstate(invalid="ignore"):
            out: NDArray[np.bool_] = ((px[..., 0] >= -0.5) & (px[..., 0] <= self.intrinsics.width - 0.5)
                                      & (px[..., 1] >= -0.5) & (px[..., 1] <= self.intrinsics.height - 0.5))
        return out

    @staticmethod
    def _apply(pose: Pose, points: FloatArray) -> FloatArray:
        """``pose`` applied to points of any leading shape (NaN rows stay NaN)."""
        flat = points.reshape(-1, 3)
        out: FloatArray = flat @ pose.rotation_matrix.T + pose.translation
        return out.reshape(points.shape)

    def __repr__(self) -> str:
        i = self.intrinsics
        base = "" if self.camera_in_base is None else f", camera_in_base={self.camera_in_base!r}"
        return f"PlaneMap({i.width}x{i.height} px, plane_cam={self.plane_cam!r}{base})"
