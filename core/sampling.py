"""Robust sampling of measurement points from depth frames.

A grid point of the paper is one pixel; a real ToF pixel is noisy and may be
invalid. :func:`sample_window` takes the median over a small window around the
pixel (and over several frames), skipping invalid pixels, so one flying pixel or
dropout does not move the point.
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
    """Robust sample at a sub-pixel location: median over a window and over frames.

    The window holds ``window_px`` x ``window_px`` positions spaced one pixel apart and
    centred exactly on ``(u, v)``; each position is bilinearly interpolated from its four
    neighbouring pixels (a convex combination, so a point on a plane stays on it) and
    counts only if every neighbour it uses is valid. The coordinate-wise median over
    all valid positions of all frames is returned.

    Args:
        frames: One or more frames of the same stream (same intrinsics).
        u: Column of the point, pixels (sub-pixel; pixel centres at integers).
        v: Row of the point, pixels.
        window_px: Odd window size in pixels.
        min_valid: Minimum number of valid window positions required.

    Raises:
        CalibrationError: If the window leaves the image or holds too few valid positions.
    """
    if not frames:
        raise CalibrationError("no frames to sample")
    if window_px < 1 or window_px % 2 != 1:
        raise CalibrationError(f"window_px must be a positive odd number, got {window_px}")
    if not (math.isfinite(u) and math.isfinite(v)):
        raise CalibrationError(f"sample position must be finite, got ({u}, {v})")
    h, w = frames[0].shape
    half = window_px // 2
    offsets = np.arange(-half, half + 1, dtype=np.float64)
    us = (u + offsets)[None, :].repeat(window_px, 0).ravel()
    vs = (v + offsets)[:, None].repeat(window_px, 1).ravel()
    if us.min() < 0 or vs.min() < 0 or us.max() > w - 1 or vs.max() > h - 1:
        raise CalibrationError(
            f"sample window at pixel ({u:.1f}, {v:.1f}) leaves the {w}x{h} image; use a smaller perimeter"
        )
    u0 = np.minimum(np.floor(us).astype(np.intp), w - 2)
    v0 = np.minimum(np.floor(vs).astype(np.intp), h - 2)
    fu, fv = us - u0, vs - v0
    corners = ((0, 0, (1 - fu) * (1 - fv)), (0, 1, fu * (1 - fv)), (1, 0, (1 - fu) * fv), (1, 1, fu * fv))
    xyz_all, dist_all = [], []
    for f in frames:
        xyz = np.zeros((us.size, 3))
        dist = np.zeros(us.size)
        ok = np.ones(us.size, dtype=bool)
        for dv, du, wgt in corners:
            rows, cols = v0 + dv, u0 + du
            used = wgt > 0
            ok &= ~used | f.valid[rows, cols]
            xyz += wgt[:, None] * np.nan_to_num(f.xyz[rows, cols].astype(np.float64))
            dist += wgt * np.nan_to_num(f.distance[rows, cols].astype(np.float64))
        xyz_all.append(xyz[ok])
        dist_all.append(dist[ok])
    xyz_v = np.concatenate(xyz_all)
    dist_v = np.concatenate(dist_all)
    iu, iv = math.floor(u + 0.5), math.floor(v + 0.5)
    if xyz_v.shape[0] < min_valid:
        raise CalibrationError(
            f"only {xyz_v.shape[0]} valid samples (need {min_valid}) around pixel ({u:.1f}, {v:.1f}) "
            f"in {len(frames)} frame(s)"
        )
    return Sample(np.median(xyz_v, axis=0), float(np.median(dist_v)), int(xyz_v.shape[0]), (iu, iv))
