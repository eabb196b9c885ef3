"""Robust sampling of measurement points from depth frames.

:func:`sample_window` takes the median over a small window around a pixel (and over
several frames), skipping invalid pixels, so one flying pixel or dropout does not move
the point.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cellcal.devices.errors import CalibrationError
from cellcal.devices.types import Frame


@dataclass(frozen=True)
class Sample:
    """A robust sample at one image location.

    Attributes:
        xyz_m: Median point in the camera frame, metres, shape (3,).
        distance_m: Median radial distance, metres.
        n_valid: Number of valid pixels that went into the median.
        pixel: The nearest integer pixel to the sampled location.
    """

    xyz_m: NDArray[np.float64]
    distance_m: float
    n_valid: int
    pixel: tuple[int, int]


def sample_window(frames: Sequence[Frame], u: float, v: float, window_px: int = 3, *, min_valid: int = 1) -> Sample:
    """Robust sample at one sub-pixel location (see :func:`sample_points`)."""
    return sample_points(frames, np.array([[u, v]], dtype=np.float64), window_px, min_valid=min_valid)[0]


def sample_points(frames: Sequence[Frame], uv: NDArray[np.float64], window_px: int = 3, *,
                  min_valid: int = 1) -> list[Sample]:
    """Robust samples at sub-pixel locations: median over a window and over frames.

    Each window holds ``window_px`` x ``window_px`` positions spaced one pixel apart and
    centred exactly on its ``(u, v)``; each position is bilinearly interpolated from its
    four neighbouring pixels (a convex combination, so a point on a plane stays on it)
    and counts only if every neighbour it uses is valid. The coordinate-wise median over
    all valid positions of all frames is returned. Vectorised over all locations.

    Args:
        frames: One or more frames of the same stream (same intrinsics).
        uv: Locations, shape (N, 2): column u and row v in pixels (pixel centres at integers).
        window_px: Odd window size in pixels.
        min_valid: Minimum number of valid window positions required per location.

    Raises:
        CalibrationError: If a window leaves the image or holds too few valid positions.
    """
    uv = _checked_locations(frames, uv, window_px)
    us, vs = _window_positions(uv, window_px, frames[0].shape)
    xyz, dist, ok = _interpolate(frames, us, vs)
    # pool frames: (N, frames * window positions); invalid positions become NaN
    n = len(uv)
    pooled_ok = ok.transpose(1, 0, 2).reshape(n, -1)
    pooled_xyz = np.where(pooled_ok[..., None], xyz.transpose(1, 0, 2, 3).reshape(n, -1, 3), np.nan)
    pooled_dist = np.where(pooled_ok, dist.transpose(1, 0, 2).reshape(n, -1), np.nan)
    counts = pooled_ok.sum(axis=1)
    if np.any(counts < min_valid):
        i = int(np.argmax(counts < min_valid))
        u, v = uv[i]
        raise CalibrationError(
            f"only {counts[i]} valid samples (need {min_valid}) around pixel ({u:.1f}, {v:.1f}) "
            f"in {len(frames)} frame(s)"
        )
    # coordinate-wise medians over the valid positions (NaNs ignored)
    med_xyz = np.nanmedian(pooled_xyz, axis=1)
    med_dist = np.nanmedian(pooled_dist, axis=1)
    return [Sample(med_xyz[i], float(med_dist[i]), int(counts[i]), (math.floor(u + 0.5), math.floor(v + 0.5)))
            for i, (u, v) in enumerate(uv)]


def _checked_locations(frames: Sequence[Frame], uv: NDArray[np.float64], window_px: int) -> NDArray[np.float64]:
    """The locations as a finite (N, 2) float array, after checking frames and window size.

    Raises:
        CalibrationError: No frames, an even or non-positive window, or a non-finite location.
    """
    if not frames:
        raise CalibrationError("no frames to sample")
    if window_px < 1 or window_px % 2 != 1:
        raise CalibrationError(f"window_px must be a positive odd number, got {window_px}")
    out = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    if not np.all(np.isfinite(out)):
        raise CalibrationError("sample positions must be finite")
    return out


def _window_positions(uv: NDArray[np.float64], window_px: int,
                      shape: tuple[int, int]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Sub-pixel columns and rows of every location's window, each shape (N, window_px**2).

    Raises:
        CalibrationError: If a window leaves the image (pixel centres span [0, size - 1]).
    """
    h, w = shape
    half = window_px // 2
    offsets = np.arange(-half, half + 1, dtype=np.float64)  # one-pixel steps about the centre
    # (N, window, window) grids flattened to (N, window**2): u varies along a row, v down the columns
    us = (uv[:, 0, None, None] + offsets[None, None, :]).repeat(window_px, 1).reshape(len(uv), -1)
    vs = (uv[:, 1, None, None] + offsets[None, :, None]).repeat(window_px, 2).reshape(len(uv), -1)
    outside = (us.min(1) < 0) | (vs.min(1) < 0) | (us.max(1) > w - 1) | (vs.max(1) > h - 1)
    if np.any(outside):
        u, v = uv[int(np.argmax(outside))]
        raise CalibrationError(
            f"sample window at pixel ({u:.1f}, {v:.1f}) leaves the {w}x{h} image; use a smaller perimeter"
        )
    return us, vs


def _interpolate(frames: Sequence[Frame], us: NDArray[np.float64], vs: NDArray[np.float64]
                 ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
    """Bilinear XYZ and distance of every frame at every window position.

    Returns:
        ``xyz`` (frames, N, P, 3) metres, ``distance`` (frames, N, P) metres and ``ok``
        (frames, N, P): True where every neighbour with a non-zero weight is valid.
    """
    h, w = frames[0].shape
    # top-left neighbour, clamped so that the bottom-right one stays inside the image
    u0 = np.minimum(np.floor(us).astype(np.intp), w - 2)
    v0 = np.minimum(np.floor(vs).astype(np.intp), h - 2)
    fu, fv = us - u0, vs - v0  # fractional position inside the 2x2 cell, 0..1
    # (row step, column step, weight) of the four neighbours; the weights sum to 1
    corners = ((0, 0, (1 - fu) * (1 - fv)), (0, 1, fu * (1 - fv)), (1, 0, (1 - fu) * fv), (1, 1, fu * fv))
    xyz = np.zeros((len(frames), *us.shape, 3))
    dist = np.zeros((len(frames), *us.shape))
    ok = np.ones((len(frames), *us.shape), dtype=bool)
    for i, f in enumerate(frames):
        for dv, du, wgt in corners:
            rows, cols = v0 + dv, u0 + du
            ok[i] &= (wgt <= 0) | f.valid[rows, cols]  # a zero-weight neighbour may be invalid
            xyz[i] += wgt[..., None] * f.xyz[rows, cols]
            dist[i] += wgt * f.distance[rows, cols]
    return xyz, dist, ok
