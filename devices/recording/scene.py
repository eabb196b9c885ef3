"""The 3D scene of one frame, in a form every viewer format is written from (ADR 0020).

A :class:`Scene` holds a frame with what was made of it — the arm's flange pose, the
mount, the fitted plane and which points are its inliers — in plain numbers (no core
types), so the Foxglove messages (:mod:`.foxglove`), the ROS 2 bag (:mod:`.ros2`) and the
live view all draw the same geometry.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cellcal.devices.pose import Pose
from cellcal.devices.types import Frame

#: Frame ids of the scene (REP 105 style names; the camera frame is OpenCV's optical frame).
BASE_FRAME_ID = "base"
FLANGE_FRAME_ID = "flange"
CAMERA_FRAME_ID = "camera"

#: RGBA (0..1) of inlier points, outlier points, the plane patch and its normal arrow.
INLIER_RGBA = (0.1, 0.8, 0.2, 1.0)
OUTLIER_RGBA = (0.9, 0.15, 0.1, 1.0)
PLANE_RGBA = (0.2, 0.4, 1.0, 0.35)
NORMAL_RGBA = (1.0, 0.85, 0.0, 1.0)
#: Thickness of the drawn plane patch, metres.
PLANE_THICKNESS_M = 0.001
#: One point record: x, y, z (float32, m) then its colour bytes B, G, R, A.
POINT_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("bgra", "u1", (4,))])
POINT_STRIDE = POINT_DTYPE.itemsize
#: Byte offset of each field in a point record: x 0, y 4, z 8, the colour bytes from 12.
POINT_OFFSETS: dict[str, int] = {name: int(spec[1]) for name, spec in (POINT_DTYPE.fields or {}).items()}
#: Length of the drawn normal arrow as a fraction of the plane patch's larger side.
NORMAL_ARROW_FRACTION = 0.25
#: The normal arrow's length over its shaft's diameter.
NORMAL_ARROW_SHAFT_RATIO = 20


@dataclass(frozen=True)
class Scene:
    """One camera frame with its poses and the fitted plane.

    Attributes:
        frame: The camera frame (points in the camera frame, metres).
        base_flange: ``T_base_flange``, the flange pose the arm reported (None: no arm).
        flange_camera: ``T_flange_camera``, the mount (None: unknown).
        plane_normal: Unit normal of the fitted plane, camera frame (None: no plane).
        plane_offset_m: Its offset: ``normal · x + offset_m = 0`` on the plane, metres.
        inlier_mask: (H, W) bool, pixels the fit kept as inliers (None: not known).
        drift: Drift values of a monitored camera (names with SI units), or None.
        track: ``cellcal track``'s values for the frame (``cellcal.Track`` without time and frame id), or None.
        camera_frame_id: Frame id of the camera (distinct per camera in a multi-camera monitor).
    """

    frame: Frame
    base_flange: Pose | None = None
    flange_camera: Pose | None = None
    plane_normal: NDArray[np.float64] | None = None
    plane_offset_m: float | None = None
    inlier_mask: NDArray[np.bool_] | None = None
    drift: Mapping[str, float | str | None] | None = field(default=None)
    track: Mapping[str, Any] | None = field(default=None)
    camera_frame_id: str = CAMERA_FRAME_ID

    @property
    def timestamp(self) -> float:
        """The frame's time, seconds since the epoch."""
        return float(self.frame.timestamp)

    @property
    def has_plane(self) -> bool:
        """Whether a fitted plane is known."""
        return self.plane_normal is not None and self.plane_offset_m is not None


def scene_points(scene: Scene) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    """The frame's valid points (N, 3) float32 in the camera frame, metres, and which are inliers (N,).

    Without an inlier mask every valid point counts as an inlier.
    """
    # valid pixels with finite coordinates, in row-major pixel order
    keep = scene.frame.valid & np.all(np.isfinite(scene.frame.xyz), axis=-1)
    points = np.ascontiguousarray(scene.frame.xyz[keep], dtype=np.float32)
    inliers = scene.inlier_mask[keep] if scene.inlier_mask is not None else np.ones(len(points), dtype=bool)
    return points, np.asarray(inliers, dtype=bool)


def plane_patch(scene: Scene) -> tuple[Pose, float, float]:
    """Where to draw the fitted plane: the patch's pose in the camera frame and its size (metres).

    The patch is centred on the inliers' centroid projected onto the plane; its z axis is
    the plane normal and its x axis the camera's x axis projected onto the plane; its
    size spans the inliers' extent along those axes.

    Raises:
        ValueError: If the scene has no plane.
    """
    from scipy.spatial.transform import Rotation

    if scene.plane_normal is None or scene.plane_offset_m is None:
        raise ValueError("the scene has no fitted plane")
    n = np.asarray(scene.plane_normal, dtype=np.float64)
    n = n / np.linalg.norm(n)
    d = float(scene.plane_offset_m)
    points, inliers = scene_points(scene)
    chosen = points[inliers] if np.any(inliers) else points
    # centre: the inliers' centroid projected onto the plane (the foot of the origin when there are none)
    centroid = chosen.mean(axis=0).astype(np.float64) if len(chosen) else np.zeros(3)
    centre = centroid - (n @ centroid + d) * n
    # in-plane x: the camera's x axis minus its normal component (its y axis if x is along the normal)
    x_axis = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x_axis = x_axis - (x_axis @ n) * n
    x_axis /= np.linalg.norm(x_axis)
    y_axis = np.cross(n, x_axis)
    rotation = Rotation.from_matrix(np.column_stack([x_axis, y_axis, n]))
    # extent: the inliers' span along the two in-plane axes (at least 1 cm)
    rel = chosen.astype(np.float64) - centre if len(chosen) else np.zeros((1, 3))
    size_x = max(float(np.ptp(rel @ x_axis)), 0.01)
    size_y = max(float(np.ptp(rel @ y_axis)), 0.01)
    return Pose(rotation, centre), size_x, size_y


def normal_arrow(scene: Scene, patch: Pose) -> Pose:
    """The pose of an arrow along the plane normal from the patch centre (its x axis is the normal)."""
    from scipy.spatial.transform import Rotation

    # rotate the arrow's +x onto the patch's +z (the normal): a fixed -90 deg turn about y
    return Pose(patch.rotation * Rotation.from_euler("y", -np.pi / 2), patch.translation)


def bgra_bytes(inliers: NDArray[np.bool_]) -> NDArray[np.uint8]:
    """(N, 4) uint8 colour per point in memory order B, G, R, A (the packed ``rgb`` of PCL and RViz).

    :data:`INLIER_RGBA` for inliers, :data:`OUTLIER_RGBA` for the rest.
    """
    # RGBA 0..1 -> bytes, reordered to B, G, R, A
    good = np.round(np.asarray(INLIER_RGBA)[[2, 1, 0, 3]] * 255).astype(np.uint8)
    bad = np.round(np.asarray(OUTLIER_RGBA)[[2, 1, 0, 3]] * 255).astype(np.uint8)
    return np.where(inliers[:, None], good, bad).astype(np.uint8)


def packed_points(scene: Scene) -> tuple[bytes, int]:
    """Point records ``x, y, z`` (float32 little-endian, m) and ``b, g, r, a`` (uint8): bytes and count.

    The layout (16 bytes a point, :data:`POINT_STRIDE`) both ``foxglove.PointCloud`` and
    ``sensor_msgs/PointCloud2`` describe.
    """
    points, inliers = scene_points(scene)
    out = np.empty(len(points), dtype=POINT_DTYPE)
    # each field filled from its column
    out["x"], out["y"], out["z"] = points[:, 0], points[:, 1], points[:, 2]
    out["bgra"] = bgra_bytes(inliers)
    return out.tobytes(), len(points)
