"""The two tilt-measurement approaches of Parpală et al. (Appl. Sci. 2024, 14, 8687).

Nine points P1–P9 sit on a square of half-size ``p`` pixels around the image centre.
Each measured point becomes spherical ``(Theta, Phi, R)`` and then Cartesian; the
plane ``Z = a X + b Y + c`` through them gives the angle between the plane and the
optical axis (approach 2, "planar interpolation"). Approach 1 takes three points
(camera centre C, on-axis point O = P5, point Ay = P8 along the image y axis) and the
law of cosines. See ``../shared/spec/paper-method.md``.

All functions take SI units (metres, radians); the paper's millimetres and degrees
appear only in :mod:`cellcal.core.methods.paper_data` and the CLI. Phi comes from a camera
model: the paper's nominal field-of-view model (:class:`NominalFovModel`) or a real
lens model (:class:`~cellcal.devices.types.Intrinsics`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cellcal.core.geometry.planes import PlaneFit, fit_plane_ols
from cellcal.devices.errors import CalibrationError
from cellcal.devices.geometry.camera_model import NominalFovModel, pixel_rays
from cellcal.devices.types import Intrinsics

FloatArray = NDArray[np.float64]

__all__ = [
    "GRID_NAMES",
    "GridPoint",
    "PaperResult",
    "error_pct",
    "grid_phi_theta",
    "grid_pixels",
    "grid_points",
    "law_of_cosines_angle",
    "max_perimeter_px",
    "paper_methods",
    "plane_fit",
    "plane_fit_angle",
    "spherical_to_cartesian",
]

#: (name, x sign, y sign, nominal Theta in degrees) of the nine points.
_LAYOUT: tuple[tuple[str, int, int, float], ...] = (
    ("P1", 1, 1, 45.0),
    ("P2", 0, 1, 90.0),
    ("P3", -1, 1, 135.0),
    ("P4", 1, 0, 0.0),
    ("P5", 0, 0, 0.0),
    ("P6", -1, 0, 180.0),
    ("P7", 1, -1, 315.0),
    ("P8", 0, -1, 270.0),
    ("P9", -1, -1, 225.0),
)

#: Point names in the paper's order.
GRID_NAMES: tuple[str, ...] = tuple(row[0] for row in _LAYOUT)


@dataclass(frozen=True)
class GridPoint:
    """One measurement point of the P1–P9 grid.

    Attributes:
        name: ``"P1"`` ... ``"P9"``.
        dx_px: Offset from the image centre along image x (right), pixels.
        dy_px: Offset along image y (down, the camera frame's +y), pixels.
        theta_rad: The paper's nominal azimuth Theta, radians in [0, 2 pi).
    """

    name: str
    dx_px: float
    dy_px: float
    theta_rad: float


def max_perimeter_px(width_px: int, height_px: int, cx: float | None = None,
                     cy: float | None = None) -> float:
    """Largest perimeter (px) whose nine points stay inside the image.

    Pixel centres are at integers, so the image spans ``[0, width - 1]``; the centre
    defaults to the image centre ``((width - 1) / 2, (height - 1) / 2)``.
    """
    cx = (width_px - 1) / 2.0 if cx is None else cx
    cy = (height_px - 1) / 2.0 if cy is None else cy
    return float(min(cx, width_px - 1 - cx, cy, height_px - 1 - cy))


def grid_points(p_px: float, *, width_px: int = 224, height_px: int = 172,
                cx: float | None = None, cy: float | None = None) -> list[GridPoint]:
    """The nine points P1–P9 for perimeter ``p_px``.

    Args:
        p_px: Half-size of the square, pixels (> 0).
        width_px: Image width the grid must fit in (default: the paper's 224 px).
        height_px: Image height (default 172 px).
        cx: Centre column, default the image centre.
        cy: Centre row, default the image centre.

    Raises:
        CalibrationError: If ``p_px`` is not positive or the grid leaves the image.
    """
    try:
        p = float(p_px)
    except (TypeError, ValueError):
        raise CalibrationError(f"perimeter must be a number of pixels, got {p_px!r}") from None
    if not math.isfinite(p) or p <= 0:
        raise CalibrationError(f"perimeter must be a positive number of pixels, got {p_px!r}")
    limit = max_perimeter_px(width_px, height_px, cx, cy)
    if p > limit:
        raise CalibrationError(
            f"perimeter {p:g} px puts points outside the {width_px}x{height_px} image "
            f"(at most {limit:g} px from the centre)")
    return [GridPoint(name, sx * p, sy * p, math.radians(theta)) for name, sx, sy, theta in _LAYOUT]


def grid_pixels(intrinsics: Intrinsics, p_px: float) -> FloatArray:
    """Pixel coordinates ``(u, v)`` of P1–P9 around the principal point, shape (9, 2).

    Raises:
        CalibrationError: If the grid leaves the image.
    """
    pts = grid_points(p_px, width_px=intrinsics.width, height_px=intrinsics.height,
                      cx=intrinsics.cx, cy=intrinsics.cy)
    return np.array([[intrinsics.cx + g.dx_px, intrinsics.cy + g.dy_px] for g in pts])


def grid_phi_theta(points: Sequence[GridPoint], model: NominalFovModel | Intrinsics, *,
                   nominal_theta: bool = True) -> tuple[FloatArray, FloatArray]:
    """Phi and Theta (rad) of the grid points' rays under a camera model.

    Args:
        points: Output of :func:`grid_points`.
        model: The paper's nominal FOV model, or real intrinsics (offsets taken from
            the principal point; the rays are undistorted).
        nominal_theta: With the nominal model, use the grid's nominal Theta (what the
            paper did, e.g. exactly 45 deg at P1) rather than the ray's true azimuth.
            Ignored for intrinsics, whose Theta is always the ray's azimuth.

    Returns:
        ``(phi, theta)``, each shape (len(points),), radians.
    """
    dx = np.array([g.dx_px for g in points], dtype=np.float64)
    dy = np.array([g.dy_px for g in points], dtype=np.float64)
    if isinstance(model, NominalFovModel):
        phi, theta = model.phi_theta(dx, dy)
        if nominal_theta:
            theta = np.array([g.theta_rad for g in points], dtype=np.float64)
        return phi, theta
    if isinstance(model, Intrinsics):
        uv = np.column_stack((model.cx + dx, model.cy + dy))
        rays = pixel_rays(model, uv)
        phi = np.arccos(np.clip(rays[:, 2], -1.0, 1.0))
        theta = np.mod(np.arctan2(rays[:, 1], rays[:, 0]), 2.0 * math.pi)
        return phi, theta
    raise CalibrationError(f"camera model must be NominalFovModel or Intrinsics, got "
                           f"{type(model).__name__}")


def spherical_to_cartesian(r_m: ArrayLike, theta_rad: ArrayLike, phi_rad: ArrayLike) -> FloatArray:
    """Camera-frame points from spherical coordinates, shape (N, 3), metres.

    ``X = R sin(Phi) cos(Theta)``, ``Y = R sin(Phi) sin(Theta)``, ``Z = R cos(Phi)``
    with Phi from the optical axis and Theta the azimuth from +x toward +y.
    """
    r, th, ph = np.broadcast_arrays(np.asarray(r_m, dtype=np.float64),
                                    np.asarray(theta_rad, dtype=np.float64),
                                    np.asarray(phi_rad, dtype=np.float64))
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(th)) and np.all(np.isfinite(ph))):
        raise CalibrationError("spherical coordinates must be finite")
    s = np.sin(ph)
    return np.stack((r * s * np.cos(th), r * s * np.sin(th), r * np.cos(ph)), axis=-1)


def plane_fit(distances_m: ArrayLike, phi_rad: ArrayLike, theta_rad: ArrayLike) -> PlaneFit:
    """Approach 2's plane: least squares ``Z = a X + b Y + c`` through the measured points.

    Args:
        distances_m: Measured distance R of each point, metres (> 0).
        phi_rad: Angle of each point's ray from the optical axis, radians.
        theta_rad: Azimuth of each point's ray, radians.

    Raises:
        CalibrationError: Fewer than 3 points, non-positive/NaN distances, or a
            degenerate point set.
    """
    r = np.asarray(distances_m, dtype=np.float64)
    if r.ndim != 1:
        raise CalibrationError(f"distances must be a 1-D array, got shape {r.shape}")
    if not np.all(np.isfinite(r)) or np.any(r <= 0):
        raise CalibrationError("distances must be positive and finite")
    pts = spherical_to_cartesian(r, theta_rad, phi_rad)
    return fit_plane_ols(pts)


def plane_fit_angle(distances_m: ArrayLike, phi_rad: ArrayLike, theta_rad: ArrayLike) -> float:
    """Approach 2: angle (rad) between the fitted plane and the optical axis.

    Equals the paper's ``90 deg - arccos(1 / sqrt(a^2 + b^2 + 1))``.
    """
    return float(plane_fit(distances_m, phi_rad, theta_rad).plane.angle_to_optical_axis_rad())


def law_of_cosines_angle(co_m: float, cay_m: float, oay_m: float) -> float:
    """Approach 1: the angle at O between the optical axis and the plane (rad).

    ``arccos((CO^2 + OAy^2 - CAy^2) / (2 CO OAy))`` for the triangle camera centre C,
    on-axis plane point O and an in-plane point Ay.

    Args:
        co_m: Distance from C to O, metres.
        cay_m: Distance from C to Ay, metres.
        oay_m: In-plane distance from O to Ay, metres.

    Raises:
        CalibrationError: If a length is not positive and finite, or the three lengths
            violate the triangle inequality.
    """
    sides = {"CO": co_m, "CAy": cay_m, "OAy": oay_m}
    for name, value in sides.items():
        if not (isinstance(value, (int, float, np.floating, np.integer))
                and math.isfinite(value) and value > 0):
            raise CalibrationError(f"law of cosines: {name} must be a positive length, got {value!r}")
    co, cay, oay = float(co_m), float(cay_m), float(oay_m)
    cos_angle = (co * co + oay * oay - cay * cay) / (2.0 * co * oay)
    if not -1.0 <= cos_angle <= 1.0:
        raise CalibrationError(
            f"law of cosines: CO={co:g}, CAy={cay:g}, OAy={oay:g} do not form a triangle")
    return math.acos(cos_angle)


def error_pct(angle_rad: float, true_angle_rad: float) -> float:
    """The paper's relative error ``|angle - true| / true * 100`` (percent)."""
    if true_angle_rad == 0:
        raise CalibrationError("true angle must be non-zero")
    return abs(angle_rad - true_angle_rad) / abs(true_angle_rad) * 100.0


@dataclass(frozen=True)
class PaperResult:
    """Both approaches on one P1–P9 data set.

    Attributes:
        perimeter_px: The data set's perimeter, pixels.
        law_of_cosines_rad: Approach 1's angle, radians.
        plane_fit_rad: Approach 2's angle, radians.
        fit: The approach-2 plane fit (camera frame, metres).
    """

    perimeter_px: float
    law_of_cosines_rad: float
    plane_fit_rad: float
    fit: PlaneFit


def paper_methods(points_m: Mapping[str, ArrayLike], perimeter_px: float,
                  model: NominalFovModel | Intrinsics | None = None) -> PaperResult:
    """Run both approaches on one data set exactly as the paper did.

    R of every point is its z value, CO and CAy are the z values of P5 and P8, OAy is
    ``|y|`` of P8; Phi comes from ``model`` (default: the paper's nominal 60 x 45 deg
    over 224 x 172 px) and Theta is the grid's nominal Theta.

    Args:
        points_m: Camera-frame ``(x, y, z)`` in metres for each of ``"P1"``..``"P9"``.
        perimeter_px: The perimeter the points were taken at, pixels.
        model: Camera model for Phi.

    Raises:
        CalibrationError: Missing points, a perimeter outside the image, or degenerate
            measurements.
    """
    missing = [n for n in GRID_NAMES if n not in points_m]
    if missing:
        raise CalibrationError(f"data set lacks point(s) {', '.join(missing)}")
    mdl = NominalFovModel.o3r222() if model is None else model
    if isinstance(mdl, NominalFovModel):
        grid = grid_points(perimeter_px, width_px=mdl.width_px, height_px=mdl.height_px)
    else:
        grid = grid_points(perimeter_px, width_px=mdl.width, height_px=mdl.height,
                           cx=mdl.cx, cy=mdl.cy)
    xyz = np.array([np.asarray(points_m[g.name], dtype=np.float64).reshape(3) for g in grid])
    phi, theta = grid_phi_theta(grid, mdl)
    fit = plane_fit(xyz[:, 2], phi, theta)
    p5, p8 = xyz[GRID_NAMES.index("P5")], xyz[GRID_NAMES.index("P8")]
    loc = law_of_cosines_angle(float(p5[2]), float(p8[2]), abs(float(p8[1])))
    return PaperResult(float(perimeter_px), loc, fit.plane.angle_to_optical_axis_rad(), fit)
