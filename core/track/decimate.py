"""Every k-th pixel of a frame (``cellcal track --decimate K``): fewer points for large images at high rates.

The kept pixels are the same measurements at the same 3D points: the camera-frame points,
the validity and the measurement model (per-point noise) are unchanged; the intrinsics are
those of the coarser pixel grid (``u' = u / k``: focal lengths and principal point divided by
``k``; distortion acts on normalised coordinates and is kept). What it costs in accuracy
(k² fewer points, coarser edge and mixed-pixel handling) is measured by
``benchmarks/track_cell.py``.
"""

from __future__ import annotations

import dataclasses
import math

from cellcal.devices.types import Frame

#: Most pixels a fit gets with ``--decimate auto``: a disparity-space fit (stereo, structured light) and a
#: range fit (ToF). Both keep a 30 fps camera within one core's 33 ms (benchmarks/track_cell.py): about
#: 16 ms at 640x400 stereo with k = 2, 27 ms at 1280x800 with k = 3, 20 ms at 640x400 ToF with k = 1.
AUTO_PIXELS = {"disparity": 115_000, "range": 300_000}


def auto_decimation(frame: Frame) -> int:
    """The smallest k that leaves at most :data:`AUTO_PIXELS` pixels of ``frame`` for its kind of fit."""
    budget = AUTO_PIXELS["disparity" if frame.measurement.triangulating else "range"]
    pixels = frame.valid.shape[0] * frame.valid.shape[1]
    return max(1, math.ceil(math.sqrt(pixels / budget)))


def decimated(frame: Frame, k: int) -> Frame:
    """``frame`` with every ``k``-th pixel in each direction (``k == 1``: the frame itself).

    Raises:
        ValueError: If ``k`` is not a positive integer.
    """
    if not isinstance(k, int) or k < 1:
        raise ValueError(f"decimation must be a positive integer, got {k!r}")
    if k == 1:
        return frame
    intr = frame.intrinsics
    sliced = frame.valid[::k, ::k]
    height, width = sliced.shape
    coarse = dataclasses.replace(intr, width=width, height=height, fx=intr.fx / k, fy=intr.fy / k,
                                 cx=intr.cx / k, cy=intr.cy / k)           # pixel u' = u / k
    return dataclasses.replace(
        frame, distance=frame.distance[::k, ::k].copy(), xyz=frame.xyz[::k, ::k].copy(),
        amplitude=frame.amplitude[::k, ::k].copy(), valid=sliced.copy(), intrinsics=coarse,
        confidence=None if frame.confidence is None else frame.confidence[::k, ::k].copy())


__all__ = ["AUTO_PIXELS", "auto_decimation", "decimated"]
