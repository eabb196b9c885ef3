"""What the cell looks like from the camera now: a small public interface for vendors' fake devices.

A simulated cell (``[arm] backend = "sim"``) moves a camera it does not render itself when
the camera is a vendor's. :class:`SceneView` lets that vendor's fake device ask the cell
where the measuring plane and the boxes are *in the camera frame at capture time*, so the
frames it renders follow the simulated arm. The simulated world implements it and
publishes itself in the :class:`~cellcal.devices.base.BackendContext` of the configuration
document; a backend finds it with :func:`scene_view` (ADR 0022)::

    view = scene_view(self.context)          # in _connect(): None outside a simulated cell
    snap = view.view_from_camera()           # in _capture(): plane and boxes, camera frame
    t_m = snap.plane_range(unit_rays)        # metres along each ray, inf where it misses
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .base import BackendContext
from .errors import CalibrationError
from .pose import Pose

#: Key of the scene view in ``BackendContext.shared``.
SCENE_VIEW_KEY = "cellcal.scene_view"

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class BoxView:
    """One box-shaped work object on the plane, in the camera (OpenCV optical) frame.

    Attributes:
        centre_m: Centre of the box, metres, shape (3,).
        rotation: 3x3 rotation camera <- box (columns: the box's x, y and up axes).
        size_m: Edge lengths along the box's x, y and up axes, metres.
    """

    centre_m: FloatArray
    rotation: FloatArray
    size_m: tuple[float, float, float]


@dataclass(frozen=True, eq=False)
class SceneSnapshot:
    """The measuring plane and the boxes as the camera sees them at one moment.

    Everything is in the camera's OpenCV optical frame (x right, y down, z forward), metres.

    Attributes:
        camera_pose: The camera's true pose in the robot base frame, ``T_base_camera``.
        plane_point_m: A point on the measuring plane (the foot of the perpendicular from
            the optical centre), shape (3,).
        plane_normal: Unit normal of the plane, pointing to the camera's side, shape (3,).
        boxes: The work objects on the plane.
        timestamp: The cell's clock at this moment, seconds since the Unix epoch.
    """

    camera_pose: Pose
    plane_point_m: FloatArray
    plane_normal: FloatArray
    boxes: tuple[BoxView, ...]
    timestamp: float

    @classmethod
    def from_base_frame(cls, camera_pose: Pose, plane_point_m: ArrayLike, plane_normal: ArrayLike,
                        boxes: tuple[tuple[ArrayLike, ArrayLike, tuple[float, float, float]], ...] = (),
                        timestamp: float = 0.0) -> SceneSnapshot:
        """Build a snapshot from a scene given in the robot base frame.

        Args:
            camera_pose: ``T_base_camera``.
            plane_point_m: A point on the plane, base frame, metres.
            plane_normal: The plane's normal, base frame (any length > 0).
            boxes: ``(centre_m, rotation base <- box, size_m)`` per box, base frame.
            timestamp: Seconds since the Unix epoch.

        Raises:
            CalibrationError: If the normal is zero or a value is not finite.
        """
        n_base = np.asarray(plane_normal, dtype=np.float64)
        norm = float(np.linalg.norm(n_base))
        if not (np.isfinite(norm) and norm > 1e-12):
            raise CalibrationError(f"plane_normal must be a finite non-zero vector, got {plane_normal!r}")
        cam_from_base = camera_pose.inv()
        # Plane point and normal into the camera frame (a normal turns like a direction).
        n = cam_from_base.apply_vector(n_base / norm)
        p = cam_from_base.apply(np.asarray(plane_point_m, dtype=np.float64))
        offset = float(n @ p)                               # signed distance of the plane from the origin
        if offset > 0:                                      # orient the normal towards the optical centre
            n, offset = -n, -offset
        foot = n * offset                                   # nearest plane point to the optical centre
        r_cam_base = cam_from_base.as_matrix()[:3, :3]
        views = tuple(BoxView(cam_from_base.apply(np.asarray(c, dtype=np.float64)),
                              r_cam_base @ np.asarray(r, dtype=np.float64),
                              (float(s[0]), float(s[1]), float(s[2]))) for c, r, s in boxes)
        return cls(camera_pose, foot, n, views, float(timestamp))

    @property
    def plane_distance_m(self) -> float:
        """Perpendicular distance from the optical centre to the plane, metres."""
        return float(np.linalg.norm(self.plane_point_m))

    def plane_range(self, rays: ArrayLike) -> FloatArray:
        """Distance along each ray from the optical centre to the plane (boxes ignored).

        Args:
            rays: Directions in the camera frame, shape (..., 3); unit length gives metres
                (radial distance), ``(x, y, 1)`` gives the Z-depth.

        Returns:
            Ray parameter per ray, shape (...); ``inf`` where the ray runs parallel to
            the plane or points away from it.
        """
        d = np.asarray(rays, dtype=np.float64)
        # Ray t*d meets the plane n.(x - p) = 0 at t = n.p / n.d.
        num = float(self.plane_normal @ self.plane_point_m)
        den = d @ self.plane_normal
        with np.errstate(divide="ignore", invalid="ignore"):
            t = num / den
        out: FloatArray = np.where(np.isfinite(t) & (t > 0), t, np.inf)
        return out


@runtime_checkable
class SceneView(Protocol):
    """Something that can tell a camera what the cell looks like from it now (the simulated world)."""

    def view_from_camera(self) -> SceneSnapshot:
        """The plane and boxes in the camera frame at this moment (the arm's current pose)."""
        ...


def publish_scene_view(context: BackendContext, view: SceneView) -> None:
    """Make ``view`` the scene view of every backend built from ``context``'s document."""
    context.shared[SCENE_VIEW_KEY] = view


def scene_view(context: BackendContext | None) -> SceneView | None:
    """The scene view of a configuration document, or None outside a simulated cell.

    Call it when connecting, not in the constructor: the simulated arm that publishes
    the view may be built after the camera.
    """
    found: Any = None if context is None else context.shared.get(SCENE_VIEW_KEY)
    return found if isinstance(found, SceneView) else None
