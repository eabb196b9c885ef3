"""Planes and plane fits with first-order 1-sigma uncertainty: OLS and TLS (robust: :mod:`.robust_fit`).

A :class:`Plane` is ``{x : normal · x + offset_m = 0}`` with a unit ``normal``. Fits in the
camera frame (OpenCV: x right, y down, z along the optical axis; metres) orient the normal
toward the camera, so ``offset_m >= 0`` and the camera lies on the positive side. The fits
and their uncertainty: docs/adr/0007-full-frame-fit.md ("The plane fits of geometry.planes").
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cellcal.devices.errors import CalibrationError
from cellcal.devices.pose import Pose

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

__all__ = [
    "CameraPlaneAngles",
    "Plane",
    "PlaneFit",
    "fit_plane_ols",
    "fit_plane_tls",
    "plane_covariance",
    "tangent_basis",
    "validate_points",
]

#: Ratio of the second to the first scatter eigenvalue below which points are collinear.
_COLLINEAR_RATIO = 1e-10


class CameraPlaneAngles(NamedTuple):
    """Angles (rad, in [0, pi/2]) between a plane and the camera's coordinate planes."""

    xoy_rad: float
    xoz_rad: float
    yoz_rad: float


@dataclass(frozen=True, eq=False)
class Plane:
    """An oriented plane ``normal · x + offset_m = 0``.

    The constructor rescales a non-unit normal (and the offset with it); it keeps the
    orientation given. Use :meth:`oriented_toward_origin` to make the frame's origin lie
    on the positive side.

    Attributes:
        normal: Unit normal, shape (3,).
        offset_m: Signed distance of the frame's origin from the plane, metres.
    """

    normal: FloatArray
    offset_m: float

    def __post_init__(self) -> None:
        try:
            n = np.array(self.normal, dtype=np.float64).reshape(-1)
            d = float(self.offset_m)
        except (TypeError, ValueError) as exc:
            raise CalibrationError(f"plane normal/offset must be numeric: {exc}") from None
        if n.shape != (3,) or not np.all(np.isfinite(n)) or not math.isfinite(d):
            raise CalibrationError(f"plane needs a finite 3-vector normal and offset, got {n}, {d}")
        norm = float(np.linalg.norm(n))
        if norm < 1e-12:
            raise CalibrationError("plane normal must be non-zero")
        n = n / norm
        n.setflags(write=False)
        object.__setattr__(self, "normal", n)
        object.__setattr__(self, "offset_m", d / norm)

    @classmethod
    def from_point_normal(cls, point_m: ArrayLike, normal: ArrayLike) -> Plane:
        """The plane through ``point_m`` with the given normal (orientation kept)."""
        n = np.asarray(normal, dtype=np.float64)
        nn = n / np.linalg.norm(n)
        return cls(nn, -float(nn @ np.asarray(point_m, dtype=np.float64)))

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Plane:
        """Inverse of :meth:`to_dict` (``{"normal": [3 numbers], "offset_m": number}``).

        Raises:
            KeyError, TypeError, ValueError: If a key is missing or not numeric.
            CalibrationError: If the normal is not a finite non-zero 3-vector.
        """
        return cls(np.asarray(data["normal"], dtype=np.float64), float(data["offset_m"]))

    def to_dict(self) -> dict[str, Any]:
        """JSON form: ``{"normal": [3 numbers], "offset_m": number}``."""
        return {"normal": self.normal.tolist(), "offset_m": self.offset_m}

    def oriented_toward_origin(self) -> Plane:
        """The same plane with the normal pointing to the origin's side (offset >= 0).

        A plane through the origin gets a normal with negative z (facing a camera that
        looks along +z).
        """
        flip = self.offset_m < 0 or (self.offset_m == 0 and self.normal[2] > 0)
        return Plane(-self.normal, -self.offset_m) if flip else self

    # ------------------------------------------------------------------ geometry
    @property
    def point_m(self) -> FloatArray:
        """The plane's point closest to the origin, metres."""
        out: FloatArray = -self.offset_m * self.normal
        return out

    def signed_distance(self, points: ArrayLike) -> FloatArray:
        """Signed distances (m) of points (shape (N, 3) or (3,)); positive on the normal's side."""
        p = np.asarray(points, dtype=np.float64)
        if p.shape[-1:] != (3,):
            raise CalibrationError(f"points must have shape (N, 3), got {p.shape}")
        out: FloatArray = p @ self.normal + self.offset_m
        return out

    def project_points(self, points: ArrayLike) -> FloatArray:
        """Orthogonal projection of points onto the plane, metres."""
        p = np.asarray(points, dtype=np.float64)
        out: FloatArray = p - self.signed_distance(p)[..., None] * self.normal
        return out

    def angle_to_optical_axis_rad(self) -> float:
        """Angle between the plane and the camera's z (optical) axis, rad in [0, pi/2].

        ``pi/2`` when the camera looks perpendicularly at the plane. This is the
        figure of the paper's Table 4 (80 deg in its experiment).
        """
        return math.asin(min(1.0, abs(float(self.normal[2]))))

    def angles_to_camera_planes_rad(self) -> CameraPlaneAngles:
        """Dihedral angles (rad, [0, pi/2]) to the camera's XOY, XOZ and YOZ planes."""
        a = np.arccos(np.clip(np.abs(self.normal), 0.0, 1.0))
        return CameraPlaneAngles(xoy_rad=float(a[2]), xoz_rad=float(a[1]), yoz_rad=float(a[0]))

    def _facing_normal(self) -> FloatArray:
        """The normal as seen from the camera: pointing back toward it (n_z <= 0)."""
        return -self.normal if self.normal[2] > 0 else self.normal

    def tilt_about_x_rad(self) -> float:
        """Camera tilt about its own x axis relative to looking straight at the plane.

        Convention: a camera rotated right-handedly by ``alpha`` about its x axis from
        the perpendicular view sees the plane normal ``(0, -sin alpha, -cos alpha)``; this
        returns ``alpha = atan2(-n_y, -n_z)`` (the normal projected on the camera's y-z
        plane), in (-pi/2, pi/2] for a plane in front of the camera. With a tilt about
        one axis only it is exact; ``pi/2 - |alpha|`` is then the plane/optical-axis angle.
        """
        n = self._facing_normal()
        return math.atan2(-float(n[1]), -float(n[2]))

    def tilt_about_y_rad(self) -> float:
        """Camera tilt about its own y axis (same convention as :meth:`tilt_about_x_rad`).

        A right-handed rotation by ``beta`` about y from the perpendicular view gives the
        normal ``(sin beta, 0, -cos beta)``; returns ``beta = atan2(n_x, -n_z)``.
        """
        n = self._facing_normal()
        return math.atan2(float(n[0]), -float(n[2]))

    def distance_along_normal_m(self) -> float:
        """Perpendicular distance from the frame's origin to the plane, metres."""
        return abs(self.offset_m)

    def distance_along_optical_axis_m(self) -> float:
        """Distance (m) from the optical centre along +z to where the axis meets the plane.

        Raises:
            CalibrationError: If the optical axis is parallel to the plane or meets it
                behind the camera.
        """
        nz = float(self.normal[2])
        if abs(nz) < 1e-12:
            raise CalibrationError("the optical axis is parallel to the plane")
        t = -self.offset_m / nz
        if t <= 0:
            raise CalibrationError("the optical axis meets the plane behind the camera")
        return t

    def intersect_rays(self, rays: ArrayLike, origins_m: ArrayLike | None = None) -> FloatArray:
        """Points where rays meet the plane.

        Args:
            rays: Ray directions, shape (..., 3) (need not be unit; e.g. the (H, W, 3)
                output of :func:`cellcal.devices.geometry.camera_model.pixel_grid_rays`).
            origins_m: Ray origins, broadcastable to ``rays``; default the frame origin.

        Returns:
            Points, same shape as ``rays``, metres; NaN where a ray is parallel to the
            plane or meets it behind its origin.
        """
        r = np.asarray(rays, dtype=np.float64)
        if r.shape[-1:] != (3,):
            raise CalibrationError(f"rays must have shape (..., 3), got {r.shape}")
        o = np.zeros(3) if origins_m is None else np.asarray(origins_m, dtype=np.float64)
        denom = r @ self.normal
        num = -(o @ self.normal + self.offset_m)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = num / denom
        t = np.where((np.abs(denom) > 1e-15) & (t > 0), t, np.nan)
        out: FloatArray = o + t[..., None] * r
        return out

    def transformed(self, pose: Pose) -> Plane:
        """This plane (given in frame *b*) expressed in frame *a*, for ``pose = T_a_b``.

        The normal keeps pointing to the same physical side.
        """
        n_a = pose.apply_vector(self.normal)
        return Plane(n_a, self.offset_m - float(n_a @ pose.translation))

    def __repr__(self) -> str:
        n = ", ".join(f"{v:.6g}" for v in self.normal)
        return f"Plane(normal=[{n}], offset_m={self.offset_m:.6g})"


@dataclass(frozen=True, eq=False)
class PlaneFit:
    """Result of a plane fit.

    Uncertainties are first-order 1-sigma values, the point noise estimated from the
    residuals as ``rms * sqrt(n / (n - 3))``.

    Attributes:
        plane: The fitted plane (camera-facing: offset_m >= 0).
        rms_m: RMS orthogonal residual of the points used in the fit, metres.
        n_points: Number of points used in the final fit.
        normal_sigma_rad: 1-sigma RMS angular uncertainty of the normal's direction,
            ``sqrt(trace(normal_covariance))``; None with only 3 points (no redundancy).
        offset_sigma_m: 1-sigma uncertainty of ``offset_m``; None with only 3 points.
        normal_covariance: 3x3 covariance of the unit normal (tangent to the sphere),
            or None with only 3 points.
        inliers: Boolean mask over the input points (robust fit), else None.
        method: ``"ols"``, ``"tls"`` or ``"robust"``.
    """

    plane: Plane
    rms_m: float
    n_points: int
    normal_sigma_rad: float | None
    offset_sigma_m: float | None
    normal_covariance: FloatArray | None = None
    inliers: BoolArray | None = None
    method: str = ""

    @property
    def inlier_fraction(self) -> float:
        """Fraction of input points used (1.0 for non-robust fits)."""
        if self.inliers is None:
            return 1.0
        return float(np.count_nonzero(self.inliers)) / max(self.inliers.size, 1)

    def angle_to_optical_axis_sigma_rad(self) -> float | None:
        """1-sigma of :meth:`Plane.angle_to_optical_axis_rad` (first order), rad."""
        if self.normal_covariance is None:
            return None
        n = self.plane.normal
        s = math.sqrt(max(1.0 - float(n[2]) ** 2, 1e-30))
        g = np.array([0.0, 0.0, math.copysign(1.0, float(n[2])) / s])
        return math.sqrt(max(float(g @ self.normal_covariance @ g), 0.0))


# ---------------------------------------------------------------------- validation
def validate_points(points: ArrayLike, *, what: str = "points") -> FloatArray:
    """Check an (N, 3) finite array with N >= 3 and return it as float64.

    Raises:
        CalibrationError: Wrong shape, fewer than 3 points, or NaN/inf values.
    """
    try:
        p = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError):
        raise CalibrationError(f"{what} must be a numeric (N, 3) array") from None
    if p.ndim != 2 or p.shape[1] != 3:
        raise CalibrationError(f"{what} must have shape (N, 3), got {p.shape}")
    if p.shape[0] < 3:
        raise CalibrationError(f"a plane fit needs at least 3 points, got {p.shape[0]}")
    if math.isfinite(float(p.sum())):  # fast path: NaN/inf would propagate into the sum
        return p
    finite = np.isfinite(p).all(axis=1)
    if not finite.all():
        bad = np.flatnonzero(~finite)
        raise CalibrationError(
            f"{what} contain NaN or inf in {bad.size} row(s) (first: row {int(bad[0])})")
    return p


def scatter(p: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Centroid, ascending eigenvalues and eigenvectors (columns) of the scatter matrix.

    Shifts by the first point before the BLAS products (cheap and keeps precision when
    the cloud is far from the origin).
    """
    n = p.shape[0]
    c0 = p[0]
    q = p - c0
    mu = (np.ones(n) @ q) / n
    s = q.T @ q - n * np.outer(mu, mu)
    w, v = np.linalg.eigh(s)
    return c0 + mu, np.maximum(w, 0.0), v


def check_spread(w: FloatArray, what: str = "points") -> None:
    """Raise CalibrationError unless the scatter eigenvalues ``w`` (ascending) span a plane."""
    if w[2] <= 0.0:
        raise CalibrationError(f"{what} are all coincident; no plane is defined")
    if w[1] <= _COLLINEAR_RATIO * w[2]:
        raise CalibrationError(f"{what} are collinear; no unique plane is defined")


def tls_fit(p: FloatArray, method: str, inliers: BoolArray | None = None) -> PlaneFit:
    """Total least squares on validated points ``p`` (N, 3), metres, with its first-order uncertainty.

    Args:
        p: Output of :func:`validate_points` (or a subset of it).
        method: Recorded in :attr:`PlaneFit.method`.
        inliers: The mask ``p`` was taken with (a robust fit's), recorded in the fit.
    """
    n_pts = p.shape[0]
    c, w, v = scatter(p)
    check_spread(w, "inlier points" if inliers is not None else "points")
    normal = v[:, 0]
    plane = Plane(normal, -float(normal @ c)).oriented_toward_origin()
    n = plane.normal
    resid = p @ n + plane.offset_m  # (not the eigenvalue: that loses precision near zero)
    rss = float(resid @ resid)
    rms = math.sqrt(rss / n_pts)
    if n_pts <= 3:
        return PlaneFit(plane, rms, n_pts, None, None, None, inliers, method)
    sigma2 = rss / (n_pts - 3)
    # first-order covariance of the normal: sum over in-plane directions e_k of
    # sigma^2 / lambda_k e_k e_k^T (lambda_k: scatter eigenvalues of the in-plane axes)
    e1, e2 = v[:, 2], v[:, 1]
    cov_n = sigma2 * (np.outer(e1, e1) / w[2] + np.outer(e2, e2) / w[1])
    var_d = sigma2 / n_pts + float(c @ cov_n @ c)
    return PlaneFit(plane, rms, n_pts, math.sqrt(float(np.trace(cov_n))), math.sqrt(var_d),
                    cov_n, inliers, method)


# ---------------------------------------------------------------------- fits
def fit_plane_tls(points: ArrayLike) -> PlaneFit:
    """Total least squares plane (minimises orthogonal distances).

    Args:
        points: Shape (N, 3), metres, N >= 3.

    Returns:
        The fit; uncertainty from the residual scatter (None for N == 3).

    Raises:
        CalibrationError: Fewer than 3 points, NaN/inf, or coincident/collinear points.
    """
    return tls_fit(validate_points(points), "tls")


def fit_plane_ols(points: ArrayLike) -> PlaneFit:
    """The paper's fit: ordinary least squares ``z = a x + b y + c``.

    Minimises vertical (z) residuals, i.e. assumes the error is along the optical
    axis. ``rms_m`` is still the orthogonal residual. The uncertainty propagates the
    regression covariance ``s^2 (A^T A)^-1`` of ``(a, b, c)`` to the unit normal
    ``(a, b, -1) / sqrt(a^2 + b^2 + 1)`` and the offset.

    Raises:
        CalibrationError: Fewer than 3 points, NaN/inf, points collinear in x-y (a plane
            containing the z direction cannot be written as ``z = f(x, y)``).
    """
    p = validate_points(points)
    n_pts = p.shape[0]
    # centred design for conditioning: z - zc = a (x - xc) + b (y - yc)
    c0 = (np.ones(n_pts) @ p) / n_pts
    q = p - c0
    if not np.any(q):
        raise CalibrationError("points are all coincident; no plane is defined")
    a2 = q[:, :2]
    ata = a2.T @ a2
    ev = np.linalg.eigvalsh(ata)
    if ev[0] <= _COLLINEAR_RATIO * max(ev[1], 1e-300):
        raise CalibrationError(
            "points are collinear in x-y; z = a x + b y + c is undefined (use fit_plane_tls)")
    ab = np.linalg.solve(ata, a2.T @ q[:, 2])
    a, b = float(ab[0]), float(ab[1])
    c = float(c0[2] - a * c0[0] - b * c0[1])
    s = math.sqrt(a * a + b * b + 1.0)
    plane = Plane(np.array([a, b, -1.0]) / s, c / s).oriented_toward_origin()
    rms = float(np.sqrt(np.mean(plane.signed_distance(p) ** 2)))
    if n_pts <= 3:
        return PlaneFit(plane, rms, n_pts, None, None, None, None, "ols")
    vres = q[:, 2] - a2 @ ab
    s2 = float(vres @ vres) / (n_pts - 3)
    # covariance of (a, b, c): slopes ~ s2 (A^T A)^-1 (centred), the centred intercept
    # ~ s2 / n independent of them, and c = zc - a xc - b yc
    cov_c = np.zeros((3, 3))
    cov_c[:2, :2] = s2 * np.linalg.inv(ata)
    cov_c[2, 2] = s2 / n_pts
    jc = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-c0[0], -c0[1], 1.0]])
    cov_abc = jc @ cov_c @ jc.T
    # n = sign * (a, b, -1)/s ;  d = sign * c / s
    u = np.array([a, b, -1.0])
    jn = np.zeros((3, 3))
    jn[:, 0] = (np.array([1.0, 0.0, 0.0]) - u * a / s**2) / s
    jn[:, 1] = (np.array([0.0, 1.0, 0.0]) - u * b / s**2) / s
    jd = np.array([-c * a / s**3, -c * b / s**3, 1.0 / s])
    cov_n = jn @ cov_abc @ jn.T
    var_d = float(jd @ cov_abc @ jd)
    # (flipping the orientation changes neither covariance)
    return PlaneFit(plane, rms, n_pts, math.sqrt(float(np.trace(cov_n))), math.sqrt(var_d),
                    cov_n, None, "ols")


def plane_covariance(normal_covariance: ArrayLike, offset_sigma_m: float, normal_offset_covariance: ArrayLike
                     ) -> FloatArray:
    """The 4x4 covariance of a plane observation (unit normal, offset) from a fit's parts.

    Args:
        normal_covariance: 3x3 covariance of the unit normal (tangent to the sphere).
        offset_sigma_m: 1-sigma of the offset, m.
        normal_offset_covariance: Their cross-covariance, shape (3,), m.
    """
    cov = np.zeros((4, 4))
    cov[:3, :3] = normal_covariance                       # the normal's block
    cov[3, 3] = offset_sigma_m ** 2                       # the offset's variance, m^2
    cov[:3, 3] = cov[3, :3] = normal_offset_covariance    # their correlation
    return cov


def tangent_basis(normal: FloatArray) -> FloatArray:
    """Two orthonormal vectors across ``normal`` (3x2; columns), the first as close to x as possible."""
    n = normal / np.linalg.norm(normal)
    ref = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    a = ref - (ref @ n) * n  # the reference axis made perpendicular to the normal
    a /= np.linalg.norm(a)
    return np.column_stack([a, np.cross(n, a)])
