"""What the fit is given: the valid pixels of frames pooled as camera-frame points, and the plane meant.

The fit works on points ``p`` (3, N) in the camera frame (OpenCV: x right, y down, z along
the optical axis), metres, with the sensor at the origin, and their measured ranges ``dm``.
Each frame's flat (H*W,) mask says which of its pixels became points (in pixel order,
frame after frame), so inlier masks, samples and pixel indices go back to the image. The
region of interest chooses the pixels; :class:`ExpectedPlane`, the plane the user means (the
calibration layer builds it from ``[reference]``, ``[mount]`` and the arm pose, ADR 0027),
chooses among the planes a robust start finds.
"""

from __future__ import annotations

import functools
import math
import threading
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cellcal.core.geometry.planes import Plane
from cellcal.core.methods.fullframe.settings import MIN_POINTS, FullFrameSettings
from cellcal.devices.errors import CalibrationError, CalibrationQualityError
from cellcal.devices.measurement import UNKNOWN_MODEL, MeasurementModel
from cellcal.devices.types import Frame

BoolArray = NDArray[np.bool_]
F32 = NDArray[np.float32]

_KEPT = threading.local()

__all__ = ["DEFAULT_SEARCH_TOLERANCE_DEG", "DEFAULT_SEARCH_TOLERANCE_M", "FIXED_SEED", "KEEP_POINTS",
           "MAX_MEDIAN_RANGE_M", "SAMPLE", "CoverageCells", "ExpectedPlane", "Nearness", "Points", "Sample",
           "check_region", "cloud_points", "coverage_cells", "fixed_subsample", "frame_points", "gather",
           "image_coverage", "kept_array", "pixel_inliers", "pixels_of"]

#: A median range above this (metres) means the distances are not in metres.
MAX_MEDIAN_RANGE_M = 100.0
#: Inliers (strided) examined for a lock-on and for the quantisation floor's geometry.
SAMPLE = 4096
#: Fits of at most this many points keep their point-sized arrays between fits (:func:`kept_array`).
KEEP_POINTS = 1 << 17
#: Seed of the fixed subsample's jitter (and of the triplets when ``seed`` is None).
FIXED_SEED = 0x5EED


#: How far the fitted normal may be from the expected one by default (``[reference] search_tolerance_deg``), deg.
DEFAULT_SEARCH_TOLERANCE_DEG = 15.0
#: How far the camera's distance to the two planes may differ by default (``[reference] search_tolerance_m``), m.
DEFAULT_SEARCH_TOLERANCE_M = 0.1


@dataclass(frozen=True)
class ExpectedPlane:
    """The plane the fit should find, in the camera frame, and how far the found one may be from it.

    Attributes:
        plane: Expected plane, camera frame (OpenCV), normal toward the camera, metres.
        angle_tolerance_rad: Largest angle between the expected and the fitted normal, rad.
        offset_tolerance_m: Largest difference of the camera's distance to the two planes, metres.
    """

    plane: Plane
    angle_tolerance_rad: float
    offset_tolerance_m: float

    def __post_init__(self) -> None:
        if not (0.0 < self.angle_tolerance_rad <= math.pi / 2):
            raise CalibrationError(f"ExpectedPlane.angle_tolerance_rad must be in (0, pi/2], got "
                                   f"{self.angle_tolerance_rad!r}")
        if not (self.offset_tolerance_m > 0.0 and math.isfinite(self.offset_tolerance_m)):
            raise CalibrationError(f"ExpectedPlane.offset_tolerance_m must be > 0, got {self.offset_tolerance_m!r}")

    def departure(self, plane: Plane) -> tuple[float, float]:
        """Angle (rad) between the normals and offset difference (m) of ``plane`` from the expected one."""
        n0, n1 = np.asarray(self.plane.normal, float), np.asarray(plane.normal, float)
        sign = 1.0 if float(n0 @ n1) >= 0 else -1.0            # either orientation of the found normal
        angle = math.atan2(float(np.linalg.norm(np.cross(n0, sign * n1))), abs(float(n0 @ n1)))
        return angle, abs(abs(plane.offset_m) - abs(self.plane.offset_m))

    def accepts(self, plane: Plane) -> bool:
        """Whether ``plane`` lies within both tolerances."""
        angle, offset = self.departure(plane)
        return angle <= self.angle_tolerance_rad and offset <= self.offset_tolerance_m

    def within(self, normals: NDArray[np.float64], offsets: NDArray[np.float64]) -> Nearness:
        """How far planes (unit normals (K, 3), offsets (K,), either orientation) are; which are within tolerance.

        The candidate planes of a robust start are judged here, all at once.
        """
        n0 = np.asarray(self.plane.normal, dtype=np.float64)
        cos = np.minimum(np.abs(normals @ n0), 1.0)                    # either orientation of a normal
        angle = np.arccos(cos)                                          # rad
        doff = np.abs(np.abs(offsets) - abs(self.plane.offset_m))      # camera's distance to each plane vs expected, m
        ok = (angle <= self.angle_tolerance_rad) & (doff <= self.offset_tolerance_m)
        return Nearness(ok, np.maximum(angle / self.angle_tolerance_rad, doff / self.offset_tolerance_m), angle, doff)


class Nearness(NamedTuple):
    """Candidate planes against the expected one (:meth:`ExpectedPlane.within`), each (K,)."""

    ok: BoolArray                      # within both tolerances
    score: NDArray[np.float64]         # departure in units of the tolerances (the larger of angle and offset)
    angle_rad: NDArray[np.float64]     # angle between the normals, rad
    offset_m: NDArray[np.float64]      # difference of the camera's distance to the two planes, m


@dataclass
class Points:
    """Pooled valid points of one or more frames of the same camera (or of a raw cloud).

    Attributes:
        p: (3, N) float32 camera-frame points, metres.
        dm: (N,) float32 measured range ``|p|``, metres.
        masks: Per frame, the flat (H*W,) mask of the pixels that became points (none for a raw cloud).
        shape: ``(H, W)`` of the frames (``(0, 0)`` for a raw cloud).
        n_pixels: What the valid fraction is taken over: region pixels of all frames, or a cloud's rows.
        what: What a point is, for messages ("valid pixel", "valid pixel in the region", "usable point").
        measurement: The camera's measurement model (the frames').
        frames: The frames (none for a raw cloud).
        region: (H, W) region of interest, or None (the whole image).
    """

    p: F32
    dm: F32
    masks: list[BoolArray]
    shape: tuple[int, int]
    n_pixels: int
    what: str
    measurement: MeasurementModel = UNKNOWN_MODEL
    frames: list[Frame] = field(default_factory=list)
    region: BoolArray | None = None

    @property
    def n(self) -> int:
        """Number of points."""
        return int(self.p.shape[1])

    @property
    def pixel_index(self) -> NDArray[np.intp]:
        """(N,) flat pixel index (row-major in ``shape``) of each point within its own frame."""
        if len(self.masks) == 1:
            return np.flatnonzero(self.masks[0])
        return np.concatenate([np.flatnonzero(m) for m in self.masks])


def check_region(region: NDArray[np.bool_] | None, shape: tuple[int, int]) -> NDArray[np.bool_] | None:
    """A region of interest as an (H, W) bool mask of the frame's shape, or None for the whole image.

    Raises:
        CalibrationError: A mask of another shape or type, or an empty one.
    """
    if region is None:
        return None
    mask = np.asarray(region)
    if mask.dtype != np.bool_ or mask.shape != shape:
        raise CalibrationError(f"the region of interest must be a bool mask of shape {shape}, got "
                               f"{mask.dtype} of shape {mask.shape}")
    if not mask.any():
        raise CalibrationError("the region of interest holds no pixel")
    return mask


def frame_points(frames: Frame | Sequence[Frame], region: NDArray[np.bool_] | None, min_valid: float) -> Points:
    """The valid pixels in the region of one or more frames, in front of the camera, pooled.

    Raises:
        CalibrationError: Not frames, mixed shapes, a bad region, points behind the camera or
            in millimetres.
        CalibrationQualityError: Fewer than ``MIN_POINTS`` valid pixels (gate ``valid_fraction``).
    """
    seq = _frame_list(frames)
    h, w = seq[0].shape
    roi = check_region(region, (h, w))
    roi_flat = None if roi is None else roi.reshape(-1)
    pts, dms, masks = [], [], []
    behind = 0
    for f in seq:
        dist = f.distance.reshape(-1)
        xyz = f.xyz.reshape(-1, 3)
        with np.errstate(invalid="ignore"):
            m = f.valid.reshape(-1) & (dist > 0)   # NaN compares False
        if roi_flat is not None:
            m &= roi_flat                          # pixels outside the region of interest are ignored
        idx = np.flatnonzero(m)
        one = len(seq) == 1 and idx.size <= KEEP_POINTS   # kept memory: no fresh pages at every fit
        p = kept_array("p", 3 * idx.size, np.float32).reshape(3, -1) if one else np.empty((3, idx.size), np.float32)
        xt = xyz.T
        for k in range(3):                         # (3, n) structure of arrays, one take per coordinate (1.5x)
            np.take(xt[k], idx, out=p[k])
        d = np.take(dist, idx, out=kept_array("dm", idx.size, np.float32) if one else None)
        if not (math.isfinite(float(p.sum())) and math.isfinite(float(d.sum()))) or not bool((p[2] > 0).all()):
            with np.errstate(invalid="ignore"):
                fin = np.isfinite(p).all(axis=0) & np.isfinite(d)
                front = fin & (p[2] > 0)
            behind += int(np.count_nonzero(fin & ~front))
            m[idx[~front]] = False
            p, d = np.ascontiguousarray(p[:, front]), d[front]
        pts.append(p)
        dms.append(d)
        masks.append(m)
    n_pixels = (h * w if roi is None else int(np.count_nonzero(roi))) * len(seq)   # region pixels, all frames
    what = "valid pixel" if roi is None else "valid pixel in the region"
    p_all = pts[0] if len(seq) == 1 else np.concatenate(pts, axis=1)
    d_all = dms[0] if len(seq) == 1 else np.concatenate(dms)
    _check_points(p_all, d_all, behind, n_pixels, min_valid, what)
    return Points(p_all, d_all, masks, (h, w), n_pixels, what, seq[0].measurement, seq, roi)


def cloud_points(points_m: ArrayLike, sigma_m: ArrayLike | None, min_valid: float
                 ) -> tuple[Points, F32 | None, BoolArray]:
    """The usable rows of a raw (N, 3) cloud as points, their sigmas (or None) and which rows they are.

    Raises:
        CalibrationError: Wrong shape or type, points behind the camera or in millimetres.
        CalibrationQualityError: Fewer than ``MIN_POINTS`` usable points (gate ``valid_fraction``).
    """
    try:
        pts = np.asarray(points_m, dtype=np.float32)
    except (TypeError, ValueError):
        raise CalibrationError("points_m must be a numeric (N, 3) array") from None
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise CalibrationError(f"points_m must have shape (N, 3), got {pts.shape}")
    n_all = pts.shape[0]
    with np.errstate(invalid="ignore", over="ignore"):
        dm = np.sqrt(np.einsum("ij,ij->i", pts, pts))   # measured range |p|
        ok = np.isfinite(dm) & (dm > 0)
    sig: F32 | None = None
    if sigma_m is not None:
        try:
            sig = np.asarray(sigma_m, dtype=np.float32).reshape(-1)
        except (TypeError, ValueError):
            raise CalibrationError("sigma_m must be a numeric (N,) array") from None
        if sig.shape != (n_all,):
            raise CalibrationError(f"sigma_m must have shape ({n_all},), got {np.shape(sigma_m)}")
        with np.errstate(invalid="ignore"):
            ok &= np.isfinite(sig) & (sig > 0)
    with np.errstate(invalid="ignore"):
        behind = ok & ~(pts[..., 2] > 0)
    ok &= ~behind
    p = np.ascontiguousarray(pts[ok].T)
    d = np.ascontiguousarray(dm[ok])
    _check_points(p, d, int(np.count_nonzero(behind)), n_all, min_valid, "usable point")
    sig_ok = None if sig is None else np.ascontiguousarray(sig[ok])
    return Points(p, d, [], (0, 0), n_all, "usable point"), sig_ok, ok


def _frame_list(frames: Frame | Sequence[Frame]) -> list[Frame]:
    if isinstance(frames, Frame):
        return [frames]
    try:
        seq = list(frames)
    except TypeError:
        raise CalibrationError(f"expected a Frame or a sequence of frames, got {type(frames).__name__}") from None
    if not seq:
        raise CalibrationError("fit_full_frame needs at least one frame")
    for i, f in enumerate(seq):
        if not isinstance(f, Frame):
            raise CalibrationError(f"frame {i} is a {type(f).__name__}, not a Frame")
        if f.shape != seq[0].shape:
            raise CalibrationError(f"frame {i} has shape {f.shape}, frame 0 has {seq[0].shape}")
    return seq


def _check_points(p: F32, dm: F32, n_behind: int, n_pixels: int, min_valid: float, what: str) -> None:
    """Points in front of the camera, enough of them, in metres."""
    n_ok = p.shape[1]
    if n_behind > n_ok:
        raise CalibrationError(f"{n_behind} of {n_behind + n_ok} {what}s lie behind the camera (z <= 0): "
                               "the points must be in the camera frame (OpenCV: z along the optical axis)")
    if n_ok < MIN_POINTS:
        extra = f" ({n_behind} behind the camera)" if n_behind else ""
        raise CalibrationQualityError("valid_fraction", n_ok / max(n_pixels, 1), min_valid,
                                      f"only {n_ok} {what}(s){extra}; a full-frame fit needs {MIN_POINTS}")
    sample = dm[:: max(1, dm.size // 4096)]
    median = float(np.median(sample))
    if median > MAX_MEDIAN_RANGE_M:
        raise CalibrationError(f"the median range of the {what}s is {median:.4g}: the distances look like "
                               "millimetres; the full-frame fit takes metres")


# ---------------------------------------------------------------------- back to the image
def pixel_inliers(inliers: BoolArray, masks: list[BoolArray], shape: tuple[int, int]) -> BoolArray:
    """(H, W) mask of the pixels that are inliers in at least half of the frames where they are valid."""
    h, w = shape
    if len(masks) == 1:
        flat = np.zeros(h * w, dtype=bool)
        flat[masks[0]] = inliers
        return flat.reshape(h, w)
    inl_count = np.zeros(h * w, dtype=np.int32)
    val_count = np.zeros(h * w, dtype=np.int32)
    start = 0
    for m in masks:
        k = int(np.count_nonzero(m))
        inl_count[m] += inliers[start:start + k]
        val_count += m
        start += k
    return ((val_count > 0) & (2 * inl_count >= val_count)).reshape(h, w)


def pixels_of(sel: NDArray[np.intp], masks: list[BoolArray]) -> NDArray[np.intp]:
    """Flat pixel index (within its frame) of the pooled points ``sel`` (sorted)."""
    if len(masks) == 1:
        out: NDArray[np.intp] = np.flatnonzero(masks[0])[sel]
        return out
    return np.concatenate([np.flatnonzero(m) for m in masks])[sel]


def kept_array(name: str, size: int, dtype: type[np.generic]) -> NDArray[Any]:
    """The first ``size`` elements of a 1-D array that this thread keeps between fits (grown when too small).

    A fresh point-sized block costs a page fault per 4 kB at every fit (2-3 us each on a
    virtual machine; 606 a fit at 224x172 were a fifth of its time); a kept one is touched
    once. What it holds is valid until the thread's next fit: only a fit's own arrays live
    here, never anything it returns.
    """
    buf: NDArray[Any] | None = getattr(_KEPT, name, None)
    if buf is None or buf.size < size or buf.dtype != dtype:
        buf = np.empty(size, dtype=dtype)
        setattr(_KEPT, name, buf)
    return buf[:size]


def gather(p: F32, sel: NDArray[np.intp], out: F32 | None = None) -> F32:
    """``p[:, sel]`` of points ``p`` (3, N), 2.5x faster: one ``take`` per coordinate (into ``out``, (3, n)).

    Laid out as ``p[:, sel]`` is (column-major), so that the float32 products downstream
    round exactly as they did.
    """
    if out is None:
        out = np.empty((3, sel.size), dtype=np.float32, order="F")
    for k in range(3):
        np.take(p[k], sel, out=out[k])
    return out


@dataclass(frozen=True)
class Sample:
    """A strided sample of the inliers (about ``SAMPLE``): the honesty checks' view of the plane's extent.

    Attributes:
        index: Their indices among the pooled points.
        p: (3, n) float64 their camera-frame points, metres.
    """

    index: NDArray[np.intp]
    p: NDArray[np.float64]

    @classmethod
    def of(cls, points: Points, inliers: BoolArray) -> Sample:
        """Every k-th point that is an inlier, without a pass over every point's index."""
        step = max(1, inliers.size // (2 * SAMPLE))
        idx = np.arange(0, inliers.size, step)
        sel = idx[inliers[idx]]
        return cls(sel, gather(points.p, sel).astype(np.float64))


@functools.lru_cache(maxsize=16)
def fixed_subsample(n_points: int, limit: int) -> NDArray[np.intp]:
    """Indices of at most ``limit`` points, one at a fixed random place in each of ``limit`` equal strata.

    Cached per size (read-only: callers must not modify the result).
    """
    if n_points <= limit:
        out = np.arange(n_points)
    else:
        start = (np.arange(limit) * n_points) // limit
        width = np.diff(np.append(start, n_points))
        jitter = np.random.default_rng(FIXED_SEED).random(limit)
        out = start + (jitter * width).astype(np.intp)
    out.flags.writeable = False
    return out


# ---------------------------------------------------------------------- image coverage
def image_coverage(mask: NDArray[np.bool_], settings: FullFrameSettings,
                   region: NDArray[np.bool_] | None = None) -> float:
    """Fraction of the ``coverage_grid`` cells with at least ``min_cell_inlier_fraction`` inliers.

    Args:
        mask: (H, W) inlier mask of the image.
        settings: Grid and per-cell threshold.
        region: (H, W) region of interest: a cell's share is taken over its region pixels,
            and cells holding none are not counted. None: the whole image.
    """
    cells = coverage_cells(mask, settings, region)
    seen = cells.area > 0
    return float(np.mean(cells.counts[seen] >= settings.min_cell_inlier_fraction * cells.area[seen]))


class CoverageCells(NamedTuple):
    """The coverage grid of one image: inliers and counted pixels per cell, and the cells' first rows / columns."""

    counts: NDArray[np.integer]  # (rows, cols) inliers per cell
    area: NDArray[np.integer]    # (rows, cols) pixels counted per cell (region pixels with a region)
    row_edges: NDArray[np.int_]  # (rows,) first image row of each cell
    col_edges: NDArray[np.int_]  # (cols,) first image column of each cell


def coverage_cells(mask: NDArray[np.bool_], settings: FullFrameSettings,
                   region: NDArray[np.bool_] | None = None) -> CoverageCells:
    """Inliers and counted pixels in each ``coverage_grid`` cell (the numbers :func:`image_coverage` judges)."""
    h, w = mask.shape
    cols, rows = settings.coverage_grid
    rows, cols = min(rows, h), min(cols, w)              # no more cells than pixels
    r_edges = (np.arange(rows) * h) // rows              # first row / column of each cell
    c_edges = (np.arange(cols) * w) // cols
    per_row = np.add.reduceat(mask.view(np.uint8), r_edges, axis=0, dtype=np.int32)
    counts = np.add.reduceat(per_row, c_edges, axis=1)   # inliers per cell
    if region is None:
        r_size = np.diff(np.append(r_edges, h))
        c_size = np.diff(np.append(c_edges, w))
        area = np.outer(r_size, c_size)                  # pixels per cell
    else:                                                # region pixels per cell
        area = np.add.reduceat(np.add.reduceat(region.view(np.uint8), r_edges, axis=0, dtype=np.int32),
                               c_edges, axis=1)
    return CoverageCells(counts, area, r_edges, c_edges)
