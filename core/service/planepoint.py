"""``pixel_to_base``: pixels of a camera on the flange -> points on the calibrated plane (base frame) with 1-sigma.

The geometry is :class:`~cellcal.core.geometry.planemap.PlaneMap`'s (the same points to
rounding); this module does it for a whole batch in a few numpy passes and adds the
first-order propagation of the calibration's 9x9 covariance: the mount ``T_flange_camera``
(turn about the flange axes, rad, applied on the left; shift, m, flange frame: the
parameterisation of the hand-eye fit) and the plane (tilts about two axes across its
normal through an anchor point, rad; its height along the normal at that point, m). The
lens model and the flange pose of the request are taken as exact.

For a pixel with viewing ray ``r`` (camera frame), flange pose ``F`` and mount ``X``: the
ray leaves ``o = R_F t_X + t_F`` along ``d = R_F R_X r`` and meets the plane
``n.p + c = 0`` at ``p = o + s d``, ``s = -(n.o + c) / (n.d)``. With ``P = I - d n^T / (n.d)``
(the projection onto the plane along the ray):

* mount turn phi: ``dp = -s P R_F [R_X r]x phi``; mount shift rho: ``dp = P R_F rho``;
* plane tilt t about axis ``a`` through anchor ``q``: ``dp = -d t ((a x n).(p - q)) / (n.d)``;
  plane height h along ``n``: ``dp = d h / (n.d)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cellcal.core.geometry.planemap import PlaneMap
from cellcal.core.geometry.planes import Plane, tangent_basis
from cellcal.devices.errors import CalibrationError
from cellcal.devices.geometry.camera_model import UNDISTORT_FAIL_PX, _undistort
from cellcal.devices.pose import Pose
from cellcal.devices.types import Intrinsics

FloatArray = NDArray[np.float64]

__all__ = ["MAX_PIXELS", "PlaneCalibration", "pixel_rays", "pixel_to_base", "quaternion_matrix"]

#: Most pixels one ``pixel_to_base`` call maps.
MAX_PIXELS = 100_000
#: Newton steps of the lens model's inverse after the first, for pixels it left above :data:`_CONVERGED_PX`.
_NEWTON_STEPS = 8
#: Residual, px, below which the inverse has converged (as the lens model's own inverse).
_CONVERGED_PX = 1e-10
#: Lens models whose whole-pixel inverse is kept (:func:`_seed_table`).
_MAX_SEED_TABLES = 16
_SEEDS: dict[str, tuple[FloatArray, FloatArray]] = {}


@dataclass(frozen=True, eq=False)
class PlaneCalibration:
    """What ``pixel_to_base`` needs of a camera's calibration.

    Attributes:
        intrinsics: The camera's lens model (taken as exact).
        mount: ``T_flange_camera``.
        plane: The measuring plane in the base frame (``normal . p + offset_m = 0``).
        anchor_m: The point of the plane its tilts turn about, base frame, m.
        covariance: 9x9 of (mount turn about the flange x, y, z, rad; mount shift, m; plane tilt about
            the two axes of :func:`~cellcal.core.geometry.planes.tangent_basis` of its normal, rad;
            plane height along the normal at ``anchor_m``, m).
    """

    intrinsics: Intrinsics
    mount: Pose
    plane: Plane
    anchor_m: FloatArray
    covariance: FloatArray

    def __post_init__(self) -> None:
        cov = np.asarray(self.covariance, dtype=np.float64)
        if cov.shape != (9, 9) or not np.all(np.isfinite(cov)):
            raise CalibrationError("a calibration's covariance must be a finite 9x9 matrix")
        object.__setattr__(self, "covariance", 0.5 * (cov + cov.T))  # symmetric to rounding
        object.__setattr__(self, "anchor_m", np.asarray(self.anchor_m, dtype=np.float64).reshape(3))
        normal = np.asarray(self.plane.normal, dtype=np.float64)
        axes = tangent_basis(normal)  # the plane's tilt axes (columns)
        # kept for every call: how the normal turns per radian about each tilt axis, and C = F F^T
        object.__setattr__(self, "_turns", np.cross(axes.T, normal))
        object.__setattr__(self, "_factor", _factor(self.covariance))

    def plane_map(self, flange: Pose) -> PlaneMap:
        """The :class:`PlaneMap` of the camera at flange pose ``flange`` (``T_base_flange``)."""
        return PlaneMap.from_base_plane(self.intrinsics, self.plane, flange @ self.mount)


def _distort(intr: Intrinsics, x: FloatArray, y: FloatArray, jacobian: bool
             ) -> tuple[FloatArray, FloatArray, tuple[FloatArray, ...] | None]:
    """OpenCV's Brown-Conrady model with rational and thin-prism terms: distorted normalized ``(xd, yd)``
    of undistorted ``(x, y)``, and its 2x2 Jacobian ``(dxd/dx, dxd/dy, dyd/dx, dyd/dy)`` if asked."""
    r2 = x * x + y * y
    num = 1.0 + r2 * (intr.k1 + r2 * (intr.k2 + r2 * intr.k3))  # radial numerator
    den = 1.0 + r2 * (intr.k4 + r2 * (intr.k5 + r2 * intr.k6))  # rational denominator
    g = num / den
    xy = x * y
    xd = x * g + 2.0 * intr.p1 * xy + intr.p2 * (r2 + 2.0 * x * x) + r2 * (intr.s1 + intr.s2 * r2)
    yd = y * g + intr.p1 * (r2 + 2.0 * y * y) + 2.0 * intr.p2 * xy + r2 * (intr.s3 + intr.s4 * r2)
    if not jacobian:
        return xd, yd, None
    dnum = intr.k1 + r2 * (2.0 * intr.k2 + 3.0 * intr.k3 * r2)  # d num / d r2
    dden = intr.k4 + r2 * (2.0 * intr.k5 + 3.0 * intr.k6 * r2)
    dg = (dnum * den - num * dden) / (den * den)  # d g / d r2; d r2 / dx = 2x
    sx = intr.s1 + 2.0 * intr.s2 * r2  # d (thin prism x) / d r2
    sy = intr.s3 + 2.0 * intr.s4 * r2
    jxx = g + 2.0 * x * x * dg + 2.0 * intr.p1 * y + 6.0 * intr.p2 * x + 2.0 * x * sx
    jxy = 2.0 * x * y * dg + 2.0 * intr.p1 * x + 2.0 * intr.p2 * y + 2.0 * y * sx
    jyx = 2.0 * x * y * dg + 2.0 * intr.p1 * x + 2.0 * intr.p2 * y + 2.0 * x * sy
    jyy = g + 2.0 * y * y * dg + 6.0 * intr.p1 * y + 2.0 * intr.p2 * x + 2.0 * y * sy
    return xd, yd, (jxx, jxy, jyx, jyy)


def _seed_table(intr: Intrinsics) -> tuple[FloatArray, FloatArray]:
    """The undistorted normalized ``x`` and ``y`` of every whole pixel from -1 to the size, flat ((H + 2) (W + 2),
    row by row), by the lens model's own inverse; kept per lens model (the seeds of :func:`pixel_rays`)."""
    key = repr(intr)
    table = _SEEDS.get(key)
    if table is None:
        u, v = np.meshgrid(np.arange(-1.0, intr.width + 1.0), np.arange(-1.0, intr.height + 1.0))
        xy, _ = _undistort(intr, np.column_stack([u.ravel(), v.ravel()]))
        table = (np.ascontiguousarray(xy[:, 0]), np.ascontiguousarray(xy[:, 1]))
        if len(_SEEDS) >= _MAX_SEED_TABLES:
            _SEEDS.pop(next(iter(_SEEDS)))
        _SEEDS[key] = table
    return table


def _seed(intr: Intrinsics, uv: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Bilinear guesses of the undistorted ``(x, y)`` of pixels ``uv`` from :func:`_seed_table` (clamped at its rim)."""
    tx, ty = _seed_table(intr)
    cols, rows = intr.width + 2, intr.height + 2
    u = np.clip(uv[:, 0] + 1.0, 0.0, cols - 1.0)  # the pixel's place in the table, clamped
    v = np.clip(uv[:, 1] + 1.0, 0.0, rows - 1.0)
    if not (np.isfinite(u).all() and np.isfinite(v).all()):
        u, v = np.nan_to_num(u), np.nan_to_num(v)  # any seed: such a pixel is refused after the Newton steps
    u0 = np.minimum(u.astype(np.intp), cols - 2)
    v0 = np.minimum(v.astype(np.intp), rows - 2)
    a, b = u - u0, v - v0
    i00 = v0 * cols + u0
    out = []
    for t in (tx, ty):
        c00, c01, c10, c11 = t.take(i00), t.take(i00 + 1), t.take(i00 + cols), t.take(i00 + cols + 1)
        out.append(c00 + a * (c01 - c00) + b * ((c10 - c00) + a * (c11 - c10 - c01 + c00)))  # bilinear
    return out[0], out[1]


def _newton_step(intr: Intrinsics, x: FloatArray, y: FloatArray, xd0: FloatArray, yd0: FloatArray
                 ) -> tuple[FloatArray, FloatArray]:
    """One Newton step of the lens model's inverse at ``(x, y)`` toward the distorted ``(xd0, yd0)``."""
    xd, yd, jac = _distort(intr, x, y, jacobian=True)
    assert jac is not None
    jxx, jxy, jyx, jyy = jac
    ex, ey = xd - xd0, yd - yd0
    det = jxx * jyy - jxy * jyx
    return x - (jyy * ex - jxy * ey) / det, y - (jxx * ey - jyx * ex) / det  # the 2x2 solve, per pixel


def _residual2_px(intr: Intrinsics, x: FloatArray, y: FloatArray, xd0: FloatArray, yd0: FloatArray) -> FloatArray:
    """The squared pixel distance between ``(x, y)`` distorted and the pixel, px²."""
    xd, yd, _ = _distort(intr, x, y, jacobian=False)
    ex, ey = (xd - xd0) * intr.fx, (yd - yd0) * intr.fy
    out: FloatArray = ex * ex + ey * ey
    return out


def pixel_rays(intr: Intrinsics, uv: FloatArray) -> FloatArray:
    """Viewing rays ``(x/z, y/z, 1)`` (camera frame) of distorted pixels ``uv`` (N, 2); NaN where not invertible.

    The Brown model is inverted here: a bilinear guess from the whole pixels' inverse (the lens
    model's own, :func:`_seed_table`), then vectorised Newton steps on the model's analytic
    Jacobian until 1e-10 px (one step for pixels in the image): the same rays as
    :meth:`PlaneMap.rays_cam` to about 1e-12. Other lens models go through :meth:`PlaneMap.rays_cam`.
    """
    if intr.model != "brown":
        return PlaneMap(intr, Plane(np.array([0.0, 0.0, 1.0]), -1.0)).rays_cam(uv)
    xd0 = (uv[:, 0] - intr.cx) / intr.fx  # distorted normalized coordinates
    yd0 = (uv[:, 1] - intr.cy) / intr.fy
    with np.errstate(all="ignore"):  # a diverging pixel turns NaN and is refused below
        x, y = _newton_step(intr, *_seed(intr, uv), xd0, yd0)
        resid2 = _residual2_px(intr, x, y, xd0, yd0)
        todo = np.flatnonzero(~(resid2 < _CONVERGED_PX**2))  # few: those far outside the image, or NaN
        for _ in range(_NEWTON_STEPS):
            if todo.size == 0:
                break
            x[todo], y[todo] = _newton_step(intr, x[todo], y[todo], xd0[todo], yd0[todo])
            resid2[todo] = _residual2_px(intr, x[todo], y[todo], xd0[todo], yd0[todo])
            todo = todo[~(resid2[todo] < _CONVERGED_PX**2)]
    good = resid2 <= UNDISTORT_FAIL_PX**2  # NaN residuals (and NaN pixels) fail this too
    rays = np.empty((uv.shape[0], 3))
    rays[:, 0], rays[:, 1], rays[:, 2] = x, y, 1.0
    if not good.all():
        rays[~good] = np.nan
    return rays


def quaternion_matrix(q: FloatArray) -> FloatArray:
    """The rotation matrix of a unit quaternion ``(x, y, z, w)`` (normalised first)."""
    x, y, z, w = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _factor(cov: FloatArray) -> FloatArray:
    """``F`` (9, rank) with ``F F^T = cov`` (symmetric, positive semi-definite): its eigenvectors scaled, those of
    eigenvalues below 1e-15 of the largest dropped (a configured mount has none: 3 columns instead of 9)."""
    values, vectors = np.linalg.eigh(cov)
    keep = values > max(float(values[-1]), 0.0) * 1e-15
    out: FloatArray = vectors[:, keep] * np.sqrt(values[keep])
    return out if out.shape[1] else np.zeros((9, 1))


def pixel_to_base(calibration: PlaneCalibration, flange: Pose | tuple[FloatArray, FloatArray], uv: FloatArray
                  ) -> tuple[FloatArray, FloatArray]:
    """Points on the calibrated plane seen at pixels ``uv`` from flange pose ``flange``, with their 1-sigma.

    Args:
        calibration: The camera's calibration.
        flange: ``T_base_flange`` at which the pixels were seen (taken as exact), or its (rotation matrix,
            translation, m).
        uv: Distorted pixels, (N, 2), N <= :data:`MAX_PIXELS`.

    Returns:
        Points (N, 3) in the base frame, m, and their 1-sigma along the base axes (N, 3), m; NaN rows
        where the ray misses the plane (parallel, behind the camera) or the pixel does not undistort.

    Raises:
        CalibrationError: If ``uv`` is not (N, 2) or has more than :data:`MAX_PIXELS` rows.
    """
    uv = np.asarray(uv, dtype=np.float64)
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise CalibrationError(f"pixels must have shape (N, 2), got {uv.shape}")
    if uv.shape[0] > MAX_PIXELS:
        raise CalibrationError(f"{uv.shape[0]} pixels, more than the {MAX_PIXELS} one request may map")
    cal = calibration
    r_f, t_f = (flange.rotation_matrix, flange.translation) if isinstance(flange, Pose) else flange
    r = r_f @ cal.mount.rotation_matrix  # T_base_camera = T_base_flange T_flange_camera
    o = r_f @ cal.mount.translation + t_f  # the camera's origin, base frame
    n = np.asarray(cal.plane.normal, dtype=np.float64)
    rays = pixel_rays(cal.intrinsics, uv)  # (N, 3), z = 1
    # the rays in the base frame, one row per axis (3, N): every array below is (3, N) or (N,), contiguous
    d = r[:, 0:1] * rays[:, 0] + r[:, 1:2] * rays[:, 1] + r[:, 2:3] * rays[:, 2]
    denom = n @ d
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -(float(n @ o) + cal.plane.offset_m) / denom
        ok = (np.abs(denom) > 1e-15) & (s > 0)  # as Plane.intersect_rays: parallel or behind the camera: no point
        s[~ok] = np.nan
        along = d / denom  # d / (n.d): how the point slides per unit of the plane's equation
    points = o[:, None] + s * d
    # first order: dp = M theta, theta = (mount turn and shift in the base frame, plane tilts a, b, height);
    # m[k] is column k of M for every pixel, (3, N)
    m = np.empty((9, 3, uv.shape[0]))
    sd = s * d
    for k in range(3):
        i, j = (k + 1) % 3, (k + 2) % 3
        m[k, k] = 0.0  # s (e_k x d): the point's move for a turn about base axis k through the camera ...
        m[k, i] = -sd[j]
        m[k, j] = sd[i]
        m[k] -= along * (sd[i] * n[j] - sd[j] * n[i])  # ... slid back onto the plane along the ray: n.(e_k x sd)
        m[3 + k] = along * -n[k]  # a shift of the camera: (I - along n^T) e_k
        m[3 + k, k] += 1.0
    rel = points - cal.anchor_m[:, None]
    turns: FloatArray = cal._turns  # type: ignore[attr-defined]
    for k in range(2):
        m[6 + k] = along * -(turns[k] @ rel)  # tilt about axis k through the anchor
    m[8] = along
    flat = m.reshape(9, -1)
    factor: FloatArray = cal._factor.copy()  # type: ignore[attr-defined]  # C = F F^T
    factor[0:3] = r_f @ factor[0:3]  # the mount's turn and shift seen in the base frame
    factor[3:6] = r_f @ factor[3:6]
    g = factor.T @ flat  # (rank, 3N)
    var = np.einsum("ij,ij->j", g, g)  # diag(M C M^T), pixel by pixel
    sigma = np.sqrt(var.reshape(3, -1))
    return points.T, sigma.T
