"""The flatness gate: local planes over image regions must agree with the global fit.

Two kinds of region (ADR 0007, "Flatness"): the cells of a grid over the image, each
with a local plane through its inliers (a crease, a bend or a slight step inside the
fitted surface), and large connected off-plane regions that are planar themselves (the
other side of a roof, a raised half, a second table), which the robust fit rejected as
clutter. Local planes are weighted least squares of the orthogonal residual ``w`` on the
in-plane coordinates ``(u, v)`` of the global fit; a region departs by the largest
``|w|`` of its local plane at the corners of its extent (the rectangle with the region's
(weighted) mean and ``sqrt(3)`` standard deviations), beyond ``flatness_sigma`` of its own sigma.
"""

from __future__ import annotations

import functools
import itertools
import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from cellcal.core.methods.fullframe.passes import basis
from cellcal.core.methods.fullframe.points import KEEP_POINTS, Points, gather, kept_array, pixels_of
from cellcal.core.methods.fullframe.settings import FullFrameSettings
from cellcal.core.methods.fullframe.space import Model, SpaceFit
from cellcal.core.methods.fullframe.staircase import bend_of, judge, staircase_of
from cellcal.devices.measurement import MeasurementModel

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
F32 = NDArray[np.float32]

#: Inliers (strided) the flatness grid uses at most.
MAX_FLAT_POINTS = 1 << 16
#: Off-plane maps are subsampled to about this many pixels across before finding regions.
REGION_MAP_PX = 320
#: A cell needs this many points for a local plane.
MIN_CELL_POINTS = 30
#: A region counts as one surface when its robust residual scale is at most this many
#: times the noise the fit found for its pixels.
PLANAR_NOISE_FACTOR = 3.0
#: ... and when its local plane keeps at least this share of its pixels.
PLANAR_SHARE = 0.8

_K3 = np.ones((3, 3), np.uint8)
_CORNERS = np.array([[-1.0, -1.0], [-1.0, 1.0], [1.0, -1.0], [1.0, 1.0]]) * math.sqrt(3.0)


@dataclass(frozen=True)
class Flatness:
    """The worst departure of a local plane from the global fit.

    Attributes:
        excess_m: Largest departure beyond ``flatness_sigma`` of its sigma, metres (>= 0).
        where: The region it was found in, for messages ("" when none departs); what the sensor
            terms saw when they explain the departure ("a bend of 7.5 mm at the left edge ...").
        notes: Sentences for the result's notes when an allowance of the sensor was used (ADR 0060).
    """

    excess_m: float
    where: str
    notes: tuple[str, ...] = ()


@dataclass(frozen=True)
class PlaneFrame:
    """The global fit as coordinates ``(u, v)`` in the plane and ``w = n·p + offset`` across it."""

    n: FloatArray
    e1: FloatArray
    e2: FloatArray
    offset: float

    def uvw(self, p: F32, along_ray: bool = True, kept: bool = False) -> FloatArray:
        """(3, N) in-plane coordinates and orthogonal residual of points ``p`` (3, N), float64.

        With ``along_ray`` the in-plane coordinates are where the pixel's ray meets the
        plane (exact): the measured point's range noise would leak into them and bias the
        local slopes by O(noise²) (errors in variables, ADR 0007 "Model"). Without, they
        are the measured point's projection, in which another plane is linear (regions
        far off the fit, where that bias is negligible). With ``kept`` the result and its
        float64 copy of ``p`` live in this thread's kept memory (valid until its next fit).
        """
        n = p.shape[1]
        p64 = kept_array("p64", 3 * n, np.float64).reshape(3, n) if kept else np.empty((3, n))
        np.copyto(p64, p)
        out = np.matmul(np.stack([self.e1, self.e2, self.n]), p64,
                        out=kept_array("uvw", 3 * n, np.float64).reshape(3, n) if kept else None)
        w = np.add(out[2], self.offset, out=p64[0])       # orthogonal residual of the measured point
        if along_ray:
            ratio = np.divide(-self.offset, out[2], out=p64[1])
            out[:2] *= ratio                              # the ray's point on the plane: p * t / |p|
        out[2] = w
        return out


def _moments(uvw: FloatArray, wt: FloatArray, cell: NDArray[np.intp], n_cells: int) -> FloatArray:
    """Per cell: the count and the 9 weighted least-squares sums of w on (u, v, 1), shape (10, C).

    Points come in pixel order, so a cell's points form runs (a row's stretch inside the
    cell): each product column is summed over the runs with ``np.add.reduceat`` and the
    few run sums are then binned into cells. One product column at a time (a buffer
    reused), so that at most three point-sized float64 arrays are alive besides the inputs.
    """
    u, v, w = uvw
    if wt.size == 0:
        return np.zeros((10, n_cells))
    starts = np.flatnonzero(cell[1:] != cell[:-1]) + 1
    starts = np.concatenate([[0], starts])                  # first point of each run
    run_cell = cell[starts]
    out = np.empty((10, n_cells))
    out[0] = np.bincount(run_cell, weights=np.diff(np.append(starts, wt.size)), minlength=n_cells)

    def add(k: int, col: FloatArray) -> None:               # sums over the runs, then runs -> cells
        out[k] = np.bincount(run_cell, weights=np.add.reduceat(col, starts), minlength=n_cells)

    add(1, wt)
    kept = wt.size <= KEEP_POINTS                           # kept memory: no fresh pages at every fit
    buf = kept_array("mom_buf", wt.size, np.float64) if kept else np.empty_like(wt)
    wu = np.multiply(wt, u, out=kept_array("mom_wu", wt.size, np.float64) if kept else None)
    wv = np.multiply(wt, v, out=kept_array("mom_wv", wt.size, np.float64) if kept else None)
    add(2, wu)
    add(3, wv)
    for k, (base, x) in enumerate(((wu, u), (wu, v), (wv, v), (wt, w), (wu, w), (wv, w)), start=4):
        add(k, np.multiply(base, x, out=buf))               # wuu, wuv, wvv, ww (= sum wt w), wuw, wvw
    return out                                              # count, w, wu, wv, wuu, wuv, wvv, ww, wuw, wvw


def _excess(a: FloatArray, b: FloatArray, centre: FloatArray, half: FloatArray, scale: FloatArray,
            k_sigma: float) -> FloatArray:
    """Per region, the largest ``|w| - k sigma`` of the local plane ``A θ = b`` at its extent's corners.

    Args:
        a: (R, 3, 3) normal matrices; b: (R, 3) right-hand sides.
        centre, half: (R, 2) centre and half-size of each extent in (u, v).
        scale: (R,) noise scale of each region (its covariance is ``scale² A⁻¹``).
    """
    ok = np.linalg.det(a) > 1e-300
    eye = np.broadcast_to(np.eye(3), a.shape)
    cov = np.linalg.inv(np.where(ok[:, None, None], a, eye))
    theta = np.einsum("rij,rj->ri", cov, b)
    uv = centre[:, None, :] + _CORNERS[None, :, :] * half[:, None, :]          # (R, 4, 2)
    g = np.concatenate([uv, np.ones((*uv.shape[:2], 1))], axis=2)             # (R, 4, 3)
    dev = np.abs(np.einsum("rkj,rj->rk", g, theta))
    sigma = scale[:, None] * np.sqrt(np.maximum(np.einsum("rki,rij,rkj->rk", g, cov, g), 0.0))
    out: FloatArray = np.where(ok, (dev - k_sigma * sigma).max(axis=1), -np.inf)
    return out


@functools.lru_cache(maxsize=8)
def _blocks(grid: tuple[int, int]) -> tuple[FloatArray, list[str]]:
    """Regions made of grid cells: each cell, the image's halves and quarters. (cells, regions) 0/1, names.

    Cached per grid (read-only: callers must not modify the result).
    """
    cols, rows = grid
    c = np.arange(cols * rows) % cols
    r = np.arange(cols * rows) // cols
    masks = [np.arange(cols * rows) == k for k in range(cols * rows)]
    names = [f"image cell column {k % cols + 1}, row {k // cols + 1} of {cols}x{rows}" for k in range(cols * rows)]
    sides = []
    if cols >= 2:
        sides += [("left", c < cols // 2), ("right", c >= cols // 2)]
    if rows >= 2:
        sides += [("top", r < rows // 2), ("bottom", r >= rows // 2)]
    for name, m in sides:
        masks.append(m)
        names.append(f"the {name} half of the image")
    if cols >= 2 and rows >= 2:
        for (vn, vm), (hn, hm) in itertools.product(sides[2:], sides[:2]):
            masks.append(vm & hm)
            names.append(f"the {vn}-{hn} quarter of the image")
    out = np.stack(masks, axis=1).astype(np.float64)
    out.flags.writeable = False
    return out, names


def grid_flatness(uvw: FloatArray, wt: FloatArray, cell: NDArray[np.intp], grid: tuple[int, int],
                  scale: float, k_sigma: float) -> Flatness:
    """Local planes of the inliers of each grid cell, and of the image's halves and quarters.

    Args:
        uvw: (3, N) coordinates of inliers (:meth:`PlaneFrame.uvw`), metres.
        wt: Their weights ``1 / sigma_orth²`` up to the factor ``scale²``.
        cell: Their cell index, ``row * columns + column``.
        grid: ``(columns, rows)``.
        scale: Noise scale: ``sigma_orth = scale / sqrt(wt)``.
        k_sigma: Uncertainty multiple not counted.
    """
    cols, rows = grid
    blocks, names = _blocks(grid)
    mom = _moments(uvw, wt, cell, cols * rows) @ blocks          # sums over each region's cells
    use = np.flatnonzero(mom[0] >= MIN_CELL_POINTS)
    if use.size == 0:
        return Flatness(0.0, "")
    _, sw, swu, swv, swuu, swuv, swvv, sww, swuw, swvw = mom[:, use]
    centre = np.stack([swu, swv], axis=1) / sw[:, None]    # weighted mean and spread of the region's points
    half = np.sqrt(np.maximum(np.stack([swuu, swvv], axis=1) / sw[:, None] - centre ** 2, 0.0))
    a = np.stack([np.stack([swuu, swuv, swu], 1), np.stack([swuv, swvv, swv], 1), np.stack([swu, swv, sw], 1)], 1)
    e = _excess(a, np.stack([swuw, swvw, sww], axis=1), centre, half, np.full(use.size, scale), k_sigma)
    k = int(np.argmax(e))
    if not e[k] > 0:
        return Flatness(0.0, "")
    return Flatness(float(e[k]), names[int(use[k])])


def _robust_local_plane(uvw: FloatArray) -> tuple[FloatArray, float, BoolArray]:
    """Least squares of w on (u, v), twice trimmed at 3 robust sigmas: (θ, robust sigma, kept)."""
    u, v, w = uvw
    x = np.stack([u, v, np.ones_like(u)], axis=1)
    keep = np.ones(u.size, dtype=bool)
    theta = np.zeros(3)
    rs = math.inf
    for _ in range(3):
        theta = np.linalg.lstsq(x[keep], w[keep], rcond=None)[0]
        r = w - x @ theta
        rs = 1.4826 * float(np.median(np.abs(r[keep]))) + 1e-12
        keep = np.abs(r) < 3.0 * rs
        if np.count_nonzero(keep) < MIN_CELL_POINTS:
            break
    return theta, rs, keep


def region_flatness(frame: PlaneFrame, p: F32, noise_orth: FloatArray, labels: NDArray[np.int32],
                    sizes: NDArray[np.int64], min_pixels: int, k_sigma: float, area: int = 1,
                    n_valid: int = 0) -> Flatness:
    """Large, planar, connected off-plane regions against the global fit.

    Args:
        frame: The global fit's coordinates.
        p: (3, N) points of one frame's off-plane pixels.
        noise_orth: Their orthogonal noise sigma as fitted, metres (N,).
        labels: Their connected-region label (0: none).
        sizes: Pixels per label (of the map the labels come from).
        min_pixels: Regions smaller than this (in ``sizes`` units) are clutter.
        k_sigma: Uncertainty multiple not counted.
        area: Image pixels per pixel of the label map (it may be subsampled).
        n_valid: Valid pixels of the frame (for the message).
    """
    worst, where = 0.0, ""
    for lab in np.flatnonzero(sizes >= min_pixels):
        if lab == 0:
            continue
        sel = labels == lab
        if np.count_nonzero(sel) < MIN_CELL_POINTS:
            continue
        uvw = frame.uvw(p[:, sel], along_ray=False)
        theta, rs, keep = _robust_local_plane(uvw)
        if (rs > PLANAR_NOISE_FACTOR * float(np.median(noise_orth[sel])) or np.mean(keep) < PLANAR_SHARE
                or np.count_nonzero(keep) < MIN_CELL_POINTS):
            continue                                   # not one surface (clutter of several heights)
        k = uvw[:, keep]
        x = np.stack([k[0], k[1], np.ones(k.shape[1])])
        a = x @ x.T
        e = float(_excess(a[None], (a @ theta)[None], k[:2].mean(axis=1)[None], k[:2].std(axis=1)[None],
                          np.array([rs]), k_sigma)[0])
        if e > worst:
            pixels = int(sizes[lab]) * area
            share = f", {100.0 * pixels / n_valid:.0f} % of the valid ones" if n_valid else ""
            worst, where = e, f"a planar region of {pixels} pixels off the fitted plane{share}"
    return Flatness(worst, where)


def off_plane_regions(off_plane: NDArray[np.uint8], step: int = 1) -> tuple[NDArray[np.int32], NDArray[np.int64]]:
    """Connected (8-neighbour) regions of off-plane pixels after a 3x3 opening: labels (H, W), sizes.

    With ``step`` > 1 the map is subsampled by ``step`` first (labels are then spread back
    to every pixel; sizes count subsampled pixels).
    """
    small = np.ascontiguousarray(off_plane[::step, ::step])
    opened = cv2.morphologyEx(small, cv2.MORPH_OPEN, _K3)
    _, found, stats, _ = cv2.connectedComponentsWithStats(opened, connectivity=8)
    labels = np.asarray(found, dtype=np.int32)
    sizes = np.asarray(stats[:, cv2.CC_STAT_AREA], dtype=np.int64)
    sizes[0] = 0
    if step > 1:                                          # back to every pixel (blocks of step x step)
        h, w = off_plane.shape
        big = cv2.resize(labels, (labels.shape[1] * step, labels.shape[0] * step), interpolation=cv2.INTER_NEAREST)
        labels = np.asarray(big, dtype=np.int32)[:h, :w]
    return labels, sizes


@functools.lru_cache(maxsize=8)
def _cell_map(shape: tuple[int, int], grid: tuple[int, int]) -> NDArray[np.intp]:
    """Flat (H*W,) map of each pixel's cell ``row * columns + column`` (cached per size; read-only)."""
    h, w = shape
    cols, rows = grid
    r = np.arange(h) * rows // h                            # cell row of each image row
    c = np.arange(w) * cols // w                            # cell column of each image column
    out: NDArray[np.intp] = (r[:, None] * cols + c[None, :]).reshape(-1)
    out.flags.writeable = False
    return out


def grid_cells(pixels: NDArray[np.intp], shape: tuple[int, int], grid: tuple[int, int]) -> NDArray[np.intp]:
    """Cell ``row * columns + column`` of a ``(columns, rows)`` grid for each flat pixel index."""
    out: NDArray[np.intp] = np.take(_cell_map(shape, grid), pixels)
    return out


# ---------------------------------------------------------------------- the gate's value of a fit
def fit_flatness(fit: SpaceFit, points: Points, model: Model, cfg: FullFrameSettings) -> Flatness:
    """The flatness gate's value: local planes of grid cells and of large planar off-plane regions.

    Args:
        fit: The global fit (its inliers, plane and noise scale).
        points: The pooled points it was fitted to (frames: their masks and image shape).
        model: The range-noise shape the local planes are weighted with (the space's).
        cfg: ``flatness_grid``, ``flatness_sigma`` and ``flatness_min_region``.
    """
    h, w = points.shape
    pl = fit.plane
    e1, e2 = basis(pl.normal)
    frame = PlaneFrame(pl.normal, e1, e2, pl.offset_m)
    sel = np.flatnonzero(fit.inliers)
    sel = sel[:: max(1, -(-sel.size // MAX_FLAT_POINTS))]   # strided inliers
    grid = (min(cfg.flatness_grid[0], w), min(cfg.flatness_grid[1], h))
    cell = grid_cells(pixels_of(sel, points.masks), (h, w), grid)
    kept = sel.size <= KEEP_POINTS                          # fresh point-sized blocks cost a page fault per 4 kB
    p_in = gather(points.p, sel,
                  kept_array("p_in", 3 * sel.size, np.float32).reshape(3, -1, order="F") if kept else None)
    wt = kept_array("wt", sel.size, np.float64) if kept else np.empty(sel.size)
    np.copyto(wt, _noise_orth(p_in, points.dm[sel], frame, model))
    np.square(wt, out=wt)
    np.divide(1.0, wt, out=wt)                              # weights 1 / noise^2
    uvw = frame.uvw(p_in, kept=kept)
    best = grid_flatness(uvw, wt, cell, grid, fit.noise_scale_m, cfg.flatness_sigma)
    if best.excess_m > cfg.flatness_tolerance_m and points.measurement.known:   # in sensor terms (ADR 0060)
        best = _sensor_terms(best, frame, p_in, pixels_of(sel, points.masks), (h, w), points.measurement,
                             uvw, wt, cell, grid, fit.noise_scale_m, cfg)
    del sel, p_in, uvw, wt, cell                            # point-sized arrays go as soon as they are used
    step = max(1, round(max(h, w) / REGION_MAP_PX))
    start = 0
    for m in points.masks:
        k = int(np.count_nonzero(m))
        inl = fit.inliers[start:start + k]
        if k - int(np.count_nonzero(inl)) >= cfg.flatness_min_region * k:   # enough outliers for a region
            reg = _frame_regions(frame, points.p[:, start:start + k], points.dm[start:start + k], m, inl, (h, w),
                                 step, fit.noise_scale_m, model, cfg)
            if reg.excess_m > best.excess_m:
                best = Flatness(reg.excess_m, reg.where, best.notes)
        start += k
    return best


def _sensor_terms(best: Flatness, frame: PlaneFrame, p_in: F32, pix: NDArray[np.intp], shape: tuple[int, int],
                  model: MeasurementModel, uvw: FloatArray, wt: FloatArray, cell: NDArray[np.intp],
                  grid: tuple[int, int], scale_m: float, cfg: FullFrameSettings) -> Flatness:
    """The grid's departure judged in sensor terms: a staircase, a bend within the allowance, or local."""
    h, w = shape
    p = p_in.astype(np.float64)
    rng = np.sqrt(np.einsum("ij,ij->j", p, p))
    cos = frame.n @ p / rng                                      # n · unit ray
    along = -frame.offset / cos                                  # the plane's range along each ray
    rows, cols = np.divmod(pix, w)
    u = (cols - (w - 1) / 2.0) / (w / 2.0)
    v = (rows - (h - 1) / 2.0) / (h / 2.0)
    field_allowance = model.allowance[2]
    if model.triangulating:
        fb = model.fb_px_m
        z, z_hat = p[2], along * p[2] / rng
        d_meas, d_hat = fb / z, fb / z_hat
        resid, to_m = d_meas - d_hat, z_hat * z_hat / fb
    else:
        resid, to_m = rng - along, np.ones_like(rng)

    def local(field: FloatArray) -> float:
        """The grid's excess with ``field`` (native unit) taken out of the measurements."""
        clean = np.array(uvw)
        if model.triangulating:
            clean[2] = cos * (fb / (d_meas - field)) * rng / z + frame.offset
        else:
            clean[2] = cos * (rng - field) + frame.offset
        return grid_flatness(clean, wt, cell, grid, scale_m, cfg.flatness_sigma).excess_m

    bend = bend_of(resid, u, v, cols, rows, to_m, field_allowance)
    stair = None
    if model.triangulating:
        step = model.disparity_step_px
        sigma = model.disparity_sigma_px
        if sigma is None:                                        # the noise before rounding, bend taken out
            sigma = math.sqrt(max(float(np.var(resid - bend.field)) - step * step / 12.0, 0.0))
        stair = staircase_of(d_meas, d_hat, cell, float(np.median(z_hat)), model, sigma)
    verdict = judge(best.excess_m, best.where, cfg.flatness_tolerance_m, stair, bend, local)
    return Flatness(verdict.excess_m, verdict.where, verdict.notes)


def _frame_regions(frame: PlaneFrame, p: F32, dm: F32, m: BoolArray, inl: BoolArray, shape: tuple[int, int],
                   step: int, scale_m: float, model: Model, cfg: FullFrameSettings) -> Flatness:
    """Flatness of the large off-plane regions of one frame (points ``p`` of the pixels ``m``)."""
    h, w = shape
    k = inl.size
    off = np.zeros(h * w, dtype=np.uint8)
    off[m] = ~inl
    labels, sizes = off_plane_regions(off.reshape(h, w), step)
    min_size = math.ceil(cfg.flatness_min_region * k / step ** 2)
    big = np.flatnonzero(sizes >= min_size)
    if big.size == 0:
        return Flatness(0.0, "")
    lab = labels.reshape(-1)[m]
    pick = np.flatnonzero(np.isin(lab, big))
    pick = pick[:: max(1, -(-pick.size // MAX_FLAT_POINTS))]                # strided, at most 65536
    p_off = gather(p, pick)
    noise = scale_m * _noise_orth(p_off, dm[pick], frame, model).astype(np.float64)
    return region_flatness(frame, p_off, noise, lab[pick], sizes, min_size, cfg.flatness_sigma, step ** 2, k)


def _noise_orth(p: F32, dm: F32, frame: PlaneFrame, model: Model) -> F32:
    """Orthogonal noise shape ``sigma_range |cos|`` of points with ranges ``dm`` (up to the fitted scale).

    Evaluated at the range the plane predicts along each ray, never at the noisy one
    (weights correlated with the noise bias the local planes, as in ADR 0007, "Weighting").
    """
    pn: F32 = frame.n.astype(np.float32) @ p
    cos: F32 = np.abs(pn)
    cos /= dm
    if not model.weighted:
        return cos                                        # a shape of ones times |cos|
    t: F32 = np.multiply(np.float32(-frame.offset), dm)   # in place from here: fewer point-sized blocks
    t /= pn
    np.abs(t, out=t)                                      # predicted range along the ray
    np.log(t, out=t)                                      # t^e as exp(e log t): float32 pow is 2x slower
    t *= np.float32(model.exponent)
    np.exp(t, out=t)
    t /= np.sqrt(np.maximum(cos, np.float32(1e-6), out=pn), out=pn)   # the noise shape t^e / sqrt|cos|
    t *= cos
    return t

