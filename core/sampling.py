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
        pixel: The (u, v) pixel that was sampled (integer pixel centre).
    """

    xyz_m: NDArray[np.float64]
    distance_m: float
    n_valid: int
    pixel: tuple[int, int]


def sample_window(frames: Sequence[Frame], u: float, v: float, window_px: int = 3, *, min_valid: int = 1) -> Sample:
    """Median of valid pixels in a ``window_px`` x ``window_px`` window over all frames.

    Args:
        frames: One or more frames of the same stream (same intrinsics).
        u: Column of the point, pixels (rounded to the nearest pixel centre).
        v: Row of the point, pixels.
        window_px: Odd window size in pixels.
        min_valid: Minimum number of valid pixels required.

    Raises:
        CalibrationError: If the window lies outside the image or holds too few valid pixels.
    """
    if not frames:
        raise CalibrationError("no frames to sample")
    if window_px < 1 or window_px % 2 != 1:
        raise CalibrationError(f"window_px must be a positive odd number, got {window_px}")
    h, w = frames[0].shape
    iu, iv = math.floor(u + 0.5), math.floor(v + 0.5)
    half = window_px // 2
    if not (half <= iu < w - half and half <= iv < h - half):
        raise CalibrationError(
            f"sample window at pixel ({u:.1f}, {v:.1f}) lies outside the {w}x{h} image; use a smaller perimeter"
        )
    rows, cols = slice(iv - half, iv + half + 1), slice(iu - half, iu + half + 1)
    xyz = np.concatenate([f.xyz[rows, cols][f.valid[rows, cols]] for f in frames]).astype(np.float64)
    dist = np.concatenate([f.distance[rows, cols][f.valid[rows, cols]] for f in frames]).astype(np.float64)
    if xyz.shape[0] < min_valid:
        raise CalibrationError(
            f"only {xyz.shape[0]} valid pixels (need {min_valid}) around pixel ({iu}, {iv}) in {len(frames)} frame(s)"
        )
    return Sample(np.median(xyz, axis=0), float(np.median(dist)), int(xyz.shape[0]), (iu, iv))
