"""Camera models: projection, back-projection (undistorting) and triangulation.

Conventions (OpenCV, see ``cellcal.devices.types``): the camera (optical) frame has x right,
y down, z forward along the optical axis, in metres; pixel ``(u, v)`` has its centre at
integer coordinates, ``u`` along columns and ``v`` along rows. Two models: the real lens,
:class:`~cellcal.devices.types.Intrinsics`, and the paper's :class:`NominalFovModel`.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from cellcal.devices.errors import CalibrationError
from cellcal.devices.pose import Pose
from cellcal.devices.types import Intrinsics

FloatArray = NDArray[np.float64]

__all__ = [
    "NominalFovModel",
    "normalized_to_pixels",
    "pixel_grid_rays",
    "pixel_rays",
    "pixels_to_normalized",
    "project",
    "triangulate",
    "undistort_pixels",
]

#: Pixel residual (px) above which an undistorted pixel counts as not converged.
UNDISTORT_FAIL_PX = 1e-4

_ZERO3 = np.zeros(3, dtype=np.float64)


def _as_points(values: ArrayLike, dim: int, what: str) -> FloatArray:
    """Validate an (N, dim) or (dim,) finite float array; returns it as (N, dim)."""
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise CalibrationError(f"{what} must be numeric, got {type(values).__name__}") from exc
    if arr.ndim == 1 and arr.shape == (dim,):
        arr = arr.reshape(1, dim)
    if arr.ndim != 2 or arr.shape[1] != dim:
        raise CalibrationError(f"{what} must have shape (N, {dim}), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        bad = int(np.count_nonzero(~np.all(np.isfinite(arr), axis=1)))
        raise CalibrationError(f"{what} contain NaN or inf in {bad} row(s)")
    return arr


#: OpenCV's lengths of a distortion vector, shortest first.
_OPENCV_DISTORTION_LENGTHS = (4, 5, 8, 12)
#: Points per ``cv2.projectPoints`` call: its Python binding always forms the Jacobian
#: (2 rows per point, 14-22 columns), which this bounds to a few MB.
_PROJECT_CHUNK = 1 << 15


def _short_distortion(intr: Intrinsics) -> FloatArray:
    """The distortion vector without its trailing zero terms (OpenCV's shortest valid length).

    Same pixels, and ``projectPoints`` forms 14 or 15 Jacobian columns instead of 22.
    """
    dist = intr.distortion
    nonzero = np.flatnonzero(dist)
    needed = int(nonzero[-1]) + 1 if nonzero.size else 0
    length = next(n for n in _OPENCV_DISTORTION_LENGTHS if n >= needed)
    return dist[:length]


def _fisheye_coefficients(intr: Intrinsics) -> FloatArray:
    """OpenCV's fisheye distortion vector ``(k1, k2, k3, k4)``."""
    return np.array([intr.k1, intr.k2, intr.k3, intr.k4], dtype=np.float64)


def _project_fisheye(intr: Intrinsics, xy: FloatArray, *, jacobian: bool = False
                     ) -> tuple[FloatArray, FloatArray | None]:
    """:func:`_project_normalized` for the fisheye model, with ``cv2.fisheye.projectPoints``.

    Its Jacobian columns are (fx, fy, cx, cy, k1..k4, rvec, tvec, skew): with zero rvec/tvec
    the derivative with respect to tvec's x and y (columns 11, 12) is d(u, v)/d(x, y).
    """
    n = xy.shape[0]
    obj = np.empty((n, 1, 3), dtype=np.float64)
    obj[:, 0, :2] = xy
    obj[:, 0, 2] = 1.0
    uv, jac = cv2.fisheye.projectPoints(obj, _ZERO3, _ZERO3, intr.camera_matrix, _fisheye_coefficients(intr))
    pixels = np.asarray(uv, dtype=np.float64).reshape(n, 2)
    if not jacobian:
        return pixels, None
    return pixels, np.asarray(jac, dtype=np.float64).reshape(n, 2, -1)[:, :, 11:13]


def _project_normalized(intr: Intrinsics, xy: FloatArray, *, jacobian: bool = False
                        ) -> tuple[FloatArray, FloatArray | None]:
    """Project normalized undistorted coordinates (x/z, y/z) to pixels with OpenCV.

    Returns the (N, 2) pixels and, if requested, the (N, 2, 2) Jacobian d(u, v)/d(x, y).
    With zero rvec/tvec the Jacobian with respect to tvec's x and y equals the
    derivative with respect to the point's x and y (the point has z = 1).
    """
    if intr.model == "fisheye":
        return _project_fisheye(intr, xy, jacobian=jacobian)
    n = xy.shape[0]
    dist = _short_distortion(intr)
    pixels = np.empty((n, 2), dtype=np.float64)
    jac_xy = np.empty((n, 2, 2), dtype=np.float64) if jacobian else None
    for lo in range(0, n, _PROJECT_CHUNK):  # chunks bound the Jacobian OpenCV forms anyway
        hi = min(n, lo + _PROJECT_CHUNK)
        obj = np.empty((hi - lo, 1, 3), dtype=np.float64)
        obj[:, 0, :2] = xy[lo:hi]
        obj[:, 0, 2] = 1.0
        uv, jac = cv2.projectPoints(obj, _ZERO3, _ZERO3, intr.camera_matrix, dist)
        pixels[lo:hi] = uv.reshape(hi - lo, 2)
        if jac_xy is not None:
            jac_xy[lo:hi] = np.asarray(jac, dtype=np.float64).reshape(hi - lo, 2, -1)[:, :, 3:5]
    return pixels, jac_xy


def normalized_to_pixels(intrinsics: Intrinsics, xy: ArrayLike) -> FloatArray:
    """Map normalized undistorted image coordinates ``(x/z, y/z)`` to distorted pixels.

    Args:
        intrinsics: Lens model.
        xy: Shape (N, 2) (or (2,)), dimensionless.

    Returns:
        Pixels, shape (N, 2).
    """
    pts = _as_points(xy, 2, "normalized coordinates")
    if pts.shape[0] == 0:
        return np.empty((0, 2))
    return _project_normalized(intrinsics, pts)[0]


def project(intrinsics: Intrinsics, points_cam: ArrayLike) -> FloatArray:
    """Project camera-frame points to pixels, lens distortion applied.

    Args:
        intrinsics: Lens model.
        points_cam: Points in the camera frame, metres, shape (N, 3) or (3,).

    Returns:
        Pixels ``(u, v)``, shape (N, 2).

    Raises:
        CalibrationError: On malformed input, NaN/inf, or a point with z <= 0 (behind
            or on the camera's plane), which has no image.
    """
    pts = _as_points(points_cam, 3, "camera-frame points")
    if pts.shape[0] == 0:
        return np.empty((0, 2))
    behind = pts[:, 2] <= 0.0
    if np.any(behind):
        first = int(np.argmax(behind))
        raise CalibrationError(
            f"{int(behind.sum())} point(s) have z <= 0 and cannot be projected "
            f"(first: row {first}, z={pts[first, 2]:.6g} m)")
    if intrinsics.model == "fisheye":
        return _project_fisheye(intrinsics, pts[:, :2] / pts[:, 2:3])[0]
    uv, _ = cv2.projectPoints(pts.reshape(-1, 1, 3), _ZERO3, _ZERO3,
                              intrinsics.camera_matrix, intrinsics.distortion)
    out: FloatArray = uv.reshape(-1, 2).astype(np.float64)
    return out


def _undistort(intr: Intrinsics, uv: FloatArray, iterations: int = 6
               ) -> tuple[FloatArray, FloatArray]:
    """Normalized undistorted coordinates of pixels plus the final pixel residual.

    The lens model is pinhole with Brown–Conrady radial / decentering / thin-prism
    distortion and the rational radial terms, evaluated with OpenCV
    (``cv2.projectPoints``). Its inverse seeds with ``cv2.undistortPointsIter``
    (fixed-point iteration to 1e-12 px), checks every pixel with one projection and
    polishes only the pixels above 1e-10 px with a few vectorised Newton steps using
    OpenCV's Jacobian of ``projectPoints``, so that ``project(pixel_rays(uv)) == uv`` to
    well below 1e-6 px.
    """
    if not intr.has_distortion and intr.model == "brown":
        xy = np.column_stack(((uv[:, 0] - intr.cx) / intr.fx, (uv[:, 1] - intr.cy) / intr.fy))
        return xy, np.zeros(uv.shape[0])
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-12)
    src = uv.reshape(-1, 1, 2)
    iterate = getattr(cv2, "undistortPointsIter", None)  # OpenCV 4.x name; 5.x folds it in
    if intr.model == "fisheye":  # OpenCV's fisheye inverse seeds; the check and Newton polish below are shared
        seed = cv2.fisheye.undistortPoints(src, intr.camera_matrix, _fisheye_coefficients(intr), criteria=criteria)
    elif iterate is not None:
        seed = iterate(src, intr.camera_matrix, intr.distortion, None, None, criteria)
    else:
        seed = cv2.undistortPoints(src, intr.camera_matrix, intr.distortion, None, None, None,  # type: ignore[call-overload]
                                   criteria)  # OpenCV 5's signature; 4.x's stubs do not know it
    xy = np.asarray(seed, dtype=np.float64).reshape(-1, 2)
    proj, _ = _project_normalized(intr, xy)     # one check of every pixel
    resid = np.hypot(proj[:, 0] - uv[:, 0], proj[:, 1] - uv[:, 1])
    todo = ~(resid < 1e-10)                      # the seed did not converge there (or NaN)
    if np.any(todo):
        xy[todo], resid[todo] = _newton(intr, uv[todo], xy[todo], iterations)
    return xy, resid


def _newton(intr: Intrinsics, uv: FloatArray, xy: FloatArray, iterations: int) -> tuple[FloatArray, FloatArray]:
    """Newton steps on OpenCV's projection and its Jacobian; (xy, final pixel residual)."""
    for _ in range(iterations):
        proj, jac = _project_normalized(intr, xy, jacobian=True)
        assert jac is not None
        err = proj - uv
        if np.all(np.hypot(err[:, 0], err[:, 1]) < 1e-10):
            break
        det = jac[:, 0, 0] * jac[:, 1, 1] - jac[:, 0, 1] * jac[:, 1, 0]
        ok = np.abs(det) > 1e-300
        safe = np.where(ok, det, 1.0)
        dx = (jac[:, 1, 1] * err[:, 0] - jac[:, 0, 1] * err[:, 1]) / safe
        dy = (-jac[:, 1, 0] * err[:, 0] + jac[:, 0, 0] * err[:, 1]) / safe
        step = np.column_stack((np.where(ok, dx, 0.0), np.where(ok, dy, 0.0)))
        xy = xy - step
    proj, _ = _project_normalized(intr, xy)
    err = proj - uv
    return xy, np.hypot(err[:, 0], err[:, 1])


def pixels_to_normalized(intrinsics: Intrinsics, uv: ArrayLike) -> FloatArray:
    """Undistort pixels into normalized image coordinates ``(x/z, y/z)``.

    Args:
        intrinsics: Lens model.
        uv: Distorted pixels, shape (N, 2) or (2,).

    Returns:
        Shape (N, 2), dimensionless.

    Raises:
        CalibrationError: On malformed input or if the distortion model cannot be
            inverted at some pixel (residual above :data:`UNDISTORT_FAIL_PX`).
    """
    pts = _as_points(uv, 2, "pixels")
    if pts.shape[0] == 0:
        return np.empty((0, 2))
    xy, resid = _undistort(intrinsics, pts)
    bad = ~(resid <= UNDISTORT_FAIL_PX)
    if np.any(bad):
        first = int(np.argmax(bad))
        raise CalibrationError(
            f"cannot undistort {int(bad.sum())} pixel(s) (first: ({pts[first, 0]:.3f}, "
            f"{pts[first, 1]:.3f}) px): the distortion model does not invert there")
    return xy


def undistort_pixels(intrinsics: Intrinsics, uv: ArrayLike) -> FloatArray:
    """Undistort pixels into ideal (distortion-free) pixels of the same camera matrix.

    Returns:
        Shape (N, 2), pixels.
    """
    xy = pixels_to_normalized(intrinsics, uv)
    return np.column_stack((xy[:, 0] * intrinsics.fx + intrinsics.cx,
                            xy[:, 1] * intrinsics.fy + intrinsics.cy))


def _unit_rays(xy: FloatArray) -> FloatArray:
    rays = np.empty((xy.shape[0], 3), dtype=np.float64)
    rays[:, :2] = xy
    rays[:, 2] = 1.0
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    return rays


def pixel_rays(intrinsics: Intrinsics, uv: ArrayLike) -> FloatArray:
    """Unit ray directions in the camera frame through (distorted) pixels.

    A point at radial distance ``d`` metres along pixel ``uv`` is ``d * ray``; a point
    at depth ``z`` is ``z / ray[2] * ray``.

    Args:
        intrinsics: Lens model.
        uv: Pixels, shape (N, 2) or (2,).

    Returns:
        Unit vectors, shape (N, 3), with positive z.

    Raises:
        CalibrationError: On malformed input or where the distortion does not invert.
    """
    return _unit_rays(pixels_to_normalized(intrinsics, uv))


@functools.lru_cache(maxsize=16)
def pixel_grid_rays(intrinsics: Intrinsics) -> FloatArray:
    """Unit rays through every pixel centre, shape (H, W, 3), cached per intrinsics.

    The returned array is read-only (it is shared between callers). Pixels where the
    distortion model does not invert (only possible with extreme distortion at the
    image corners) hold NaN.
    """
    h, w = intrinsics.height, intrinsics.width
    vv, uu = np.mgrid[0:h, 0:w]
    uv = np.column_stack((uu.ravel(), vv.ravel())).astype(np.float64)
    xy, resid = _undistort(intrinsics, uv)
    rays = _unit_rays(xy)
    rays[~(resid <= UNDISTORT_FAIL_PX)] = np.nan
    grid = rays.reshape(h, w, 3)
    grid.setflags(write=False)
    return grid


@dataclass(frozen=True)
class NominalFovModel:
    """The paper's camera model: a constant angle per pixel along each image axis.

    A pixel offset ``(dx, dy)`` from the image centre (px, x right, y down) has the
    axis angles ``phi_x = dx * fov_x / width`` and ``phi_y = dy * fov_y / height``; its
    ray is ``(tan phi_x, tan phi_y, 1)`` normalized, so its angle from the optical axis
    is ``Phi = atan(hypot(tan phi_x, tan phi_y))`` (the paper's corner formula; equal to
    ``|phi_x|`` or ``|phi_y|`` on the axes).

    Attributes:
        width_px: Image width, pixels.
        height_px: Image height, pixels.
        fov_x_rad: Full horizontal field of view, radians.
        fov_y_rad: Full vertical field of view, radians.
    """

    width_px: int
    height_px: int
    fov_x_rad: float
    fov_y_rad: float

    def __post_init__(self) -> None:
        for name in ("width_px", "height_px"):
            v = getattr(self, name)
            if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v <= 0:
                raise CalibrationError(
                    f"NominalFovModel.{name} must be a positive integer, got {v!r}")
        for name in ("fov_x_rad", "fov_y_rad"):
            v = float(getattr(self, name))
            if not (0.0 < v < math.pi):
                raise CalibrationError(f"NominalFovModel.{name} must be in (0, pi) rad, got {v!r}")
            object.__setattr__(self, name, v)

    @classmethod
    def o3r222(cls) -> NominalFovModel:
        """The paper's camera: 224 x 172 px, nominal 60 x 45 deg."""
        return cls(224, 172, math.radians(60.0), math.radians(45.0))

    @property
    def rad_per_px_x(self) -> float:
        """Angular resolution along x, rad/px."""
        return self.fov_x_rad / self.width_px

    @property
    def rad_per_px_y(self) -> float:
        """Angular resolution along y, rad/px."""
        return self.fov_y_rad / self.height_px

    def axis_angles(self, dx_px: ArrayLike, dy_px: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """``(phi_x, phi_y)`` in radians for pixel offsets from the image centre."""
        dx = np.asarray(dx_px, dtype=np.float64)
        dy = np.asarray(dy_px, dtype=np.float64)
        if not (np.all(np.isfinite(dx)) and np.all(np.isfinite(dy))):
            raise CalibrationError("pixel offsets must be finite")
        phi_x = dx * self.rad_per_px_x
        phi_y = dy * self.rad_per_px_y
        if np.any(np.abs(phi_x) >= math.pi / 2) or np.any(np.abs(phi_y) >= math.pi / 2):
            raise CalibrationError("pixel offset maps to an axis angle of 90 deg or more")
        return phi_x, phi_y

    def phi_theta(self, dx_px: ArrayLike, dy_px: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Spherical angles of the rays through pixel offsets.

        Args:
            dx_px: Offset(s) from the image centre along x, pixels.
            dy_px: Offset(s) along y, pixels.

        Returns:
            ``(phi, theta)`` in radians: ``phi`` from the optical axis in [0, pi/2),
            ``theta`` the azimuth ``atan2(tan phi_y, tan phi_x)`` in [0, 2 pi). (The
            paper's table uses the grid's nominal Theta, e.g. 45 deg at a corner; with
            unequal angular resolutions the true ray azimuth differs slightly.)
        """
        phi_x, phi_y = self.axis_angles(dx_px, dy_px)
        tx, ty = np.tan(phi_x), np.tan(phi_y)
        phi = np.arctan(np.hypot(tx, ty))
        theta = np.mod(np.arctan2(ty, tx), 2.0 * math.pi)
        return phi, theta

    def rays(self, dx_px: ArrayLike, dy_px: ArrayLike) -> FloatArray:
        """Unit ray directions (camera frame) through pixel offsets, shape (..., 3)."""
        phi_x, phi_y = self.axis_angles(dx_px, dy_px)
        tx, ty = np.broadcast_arrays(np.tan(phi_x), np.tan(phi_y))
        v = np.stack((tx, ty, np.ones_like(tx)), axis=-1)
        out: FloatArray = v / np.linalg.norm(v, axis=-1, keepdims=True)
        return out


def triangulate(intrinsics: Intrinsics | Sequence[Intrinsics], poses_cam_in_world: Sequence[Pose],
                pixels: ArrayLike) -> FloatArray:
    """Triangulate one point seen in two or more posed views (linear least squares).

    Finds the point minimising the sum of squared perpendicular distances to the
    viewing rays; exact for noise-free data.

    Args:
        intrinsics: One lens model for all views, or one per view.
        poses_cam_in_world: ``T_world_cam`` of each view (maps camera-frame points into
            the world frame), metres.
        pixels: One distorted pixel ``(u, v)`` per view, shape (N, 2).

    Returns:
        The point in the world frame, metres, shape (3,).

    Raises:
        CalibrationError: Fewer than two views, mismatched lengths, or (near-)parallel
            rays that do not fix the point.
    """
    n = len(poses_cam_in_world)
    uv = _as_points(pixels, 2, "pixels")
    if n < 2:
        raise CalibrationError(f"triangulation needs at least 2 views, got {n}")
    if uv.shape[0] != n:
        raise CalibrationError(f"got {n} poses but {uv.shape[0]} pixels")
    if isinstance(intrinsics, Intrinsics):
        intr_list: list[Intrinsics] = [intrinsics] * n
    else:
        intr_list = list(intrinsics)
        if len(intr_list) != n:
            raise CalibrationError(f"got {n} poses but {len(intr_list)} intrinsics")
    origins = np.empty((n, 3))
    dirs = np.empty((n, 3))
    for i, (intr, pose) in enumerate(zip(intr_list, poses_cam_in_world, strict=True)):
        ray = pixel_rays(intr, uv[i])[0]
        origins[i] = pose.translation
        dirs[i] = pose.apply_vector(ray)
    # sum_i (I - d_i d_i^T) (p - o_i) = 0
    proj = np.eye(3)[None, :, :] - dirs[:, :, None] * dirs[:, None, :]
    a = proj.sum(axis=0)
    b = np.einsum("nij,nj->i", proj, origins)
    eig = np.linalg.eigvalsh(a)
    if eig[0] < 1e-12 * max(eig[-1], 1.0):
        raise CalibrationError("viewing rays are (nearly) parallel; the point is not fixed")
    point: FloatArray = np.linalg.solve(a, b)
    return point
