"""The P1–P9 grid of the paper's methods: its points around the principal point, what fits an image, its samples.

Nine points on a square of half-size ``perimeter`` pixels (the paper's "perimeter") around
the principal point, in the paper's order and with its nominal azimuths Theta; the
perimeters an image (with the sampling windows) can hold and, in one line, why not; the
points' rays under a camera model; robust samples of depth frames at the points. The
paper's two tilt measurements on it are :mod:`cellcal.core.methods.paper`. Pixels for the
grid, radians for angles.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cellcal.core.geometry.sampling import Sample, sample_points
from cellcal.devices.errors import CalibrationError
from cellcal.devices.geometry.camera_model import NominalFovModel, pixel_rays
from cellcal.devices.types import Frame, Intrinsics

FloatArray = NDArray[np.float64]

__all__ = [
    "DEFAULT_PERIMETERS_PX",
    "DEFAULT_WINDOW_PX",
    "GRID_METHODS",
    "GRID_NAMES",
    "GridPoint",
    "camera_grid",
    "grid_phi_theta",
    "grid_pixels",
    "grid_points",
    "largest_perimeter_px",
    "max_perimeter_px",
    "perimeter_problem",
    "sample_grid",
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

#: The methods evaluated on the P1-P9 grid at every perimeter (configuration names).
GRID_METHODS: tuple[str, ...] = ("law_of_cosines", "plane_fit", "plane_fit_nominal")

#: The default plan's grid half-sizes (``[plan] perimeters_px``, the paper's), pixels.
DEFAULT_PERIMETERS_PX: tuple[int, ...] = (20, 30, 40, 50)

#: The default sampling window around each grid point (``[plan] window_px``), pixels.
DEFAULT_WINDOW_PX = 3


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


def largest_perimeter_px(intrinsics: Intrinsics, window_px: int = DEFAULT_WINDOW_PX) -> float:
    """Largest perimeter (px) whose nine points and their ``window_px`` sampling windows stay inside the image.

    The windows' pixel centres must lie within ``[0, size - 1]`` (see
    :func:`~cellcal.core.geometry.sampling.sample_points`), so each reaches ``window_px // 2``
    pixels beyond its point. Negative when not even the centre window fits.
    """
    return max_perimeter_px(intrinsics.width, intrinsics.height, intrinsics.cx, intrinsics.cy) - window_px // 2


def perimeter_problem(intrinsics: Intrinsics, perimeters_px: Sequence[float],
                      window_px: int = DEFAULT_WINDOW_PX) -> str | None:
    """Why a camera's image cannot hold the P1-P9 grid at these perimeters, in one line; None when it can.

    The text names the perimeters that do not fit, the image size, how far from the
    principal point the grid may reach and the largest whole perimeter that fits (what to
    change). ``cellcal calibrate`` (``--check``, and before the first move) and the
    conformance kit refuse a camera with it.

    Args:
        intrinsics: The camera's intrinsics (image size and principal point, pixels).
        perimeters_px: Grid half-sizes, pixels.
        window_px: Odd sampling window around each point, pixels.
    """
    reach = largest_perimeter_px(intrinsics, window_px)
    bad = [float(p) for p in perimeters_px if not float(p) <= reach]
    if not bad:
        return None
    listed = ", ".join(f"{p:g}" for p in bad)
    what = f"perimeter {listed} px puts" if len(bad) == 1 else f"perimeters {listed} px put"
    largest = math.floor(reach)
    change = (f"use perimeters_px of at most {largest} px" if largest >= 1 else
              f"no perimeter fits: leave {', '.join(GRID_METHODS)} out of the plan's methods")
    return (f"{what} the P1-P9 grid with its {window_px} px sampling windows outside the "
            f"{intrinsics.width}x{intrinsics.height} image (at most {reach:g} px from the principal point "
            f"({intrinsics.cx:g}, {intrinsics.cy:g}) px); {change}")


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
    return _pixels(intrinsics, camera_grid(intrinsics, p_px))


def camera_grid(intrinsics: Intrinsics, p_px: float) -> list[GridPoint]:
    """The nine points for perimeter ``p_px`` around a camera's principal point.

    Raises:
        CalibrationError: If the grid leaves the image.
    """
    return grid_points(p_px, width_px=intrinsics.width, height_px=intrinsics.height,
                       cx=intrinsics.cx, cy=intrinsics.cy)


def _pixels(intrinsics: Intrinsics, points: Sequence[GridPoint]) -> FloatArray:
    """``(u, v)`` of grid points: their offsets added to the principal point, shape (N, 2)."""
    return np.array([[intrinsics.cx + g.dx_px, intrinsics.cy + g.dy_px] for g in points])


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


def sample_grid(frames: Sequence[Frame], points: Sequence[GridPoint], window_px: int = 3) -> dict[str, Sample]:
    """Robust samples of the frames at grid points around the principal point, keyed by point name.

    Args:
        frames: Frames of one stream (same intrinsics); their samples are pooled.
        points: Output of :func:`camera_grid` for the frames' intrinsics.
        window_px: Odd sampling window, pixels.

    Raises:
        CalibrationError: A window leaves the image or a point has no valid pixel.
    """
    uv = _pixels(frames[0].intrinsics, points)
    return dict(zip((g.name for g in points), sample_points(frames, uv, window_px), strict=True))
