"""The robust full-frame fit: robust start, reweighted Gauss-Newton on the ranges, intervals, gates.

Points are in the camera frame (OpenCV: x right, y down, z along the optical axis), metres,
with the sensor at the origin; the fitted normal points toward the camera (``offset_m > 0``).
Method and rationale: docs/adr/0007-full-frame-fit.md.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from statistics import NormalDist  # not scipy.special: its 0.2 s import is off calibrate's start-up

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cellcal.core.geometry.planes import Plane
from cellcal.core.methods.fullframe.flatness import (
    Flatness,
    PlaneFrame,
    grid_cells,
    grid_flatness,
    off_plane_regions,
    region_flatness,
)
from cellcal.core.methods.fullframe.gates import gate_table, image_coverage
from cellcal.core.methods.fullframe.mixed import EdgeClean, EdgeReport
from cellcal.core.methods.fullframe.passes import (
    Cutoff,
    FinalPass,
    KeepMask,
    Model,
    Scratch,
    basis,
    final_pass,
    step_plane,
)
from cellcal.core.methods.fullframe.result import Estimate, FullFrameResult
from cellcal.core.methods.fullframe.settings import MIN_POINTS, FullFrameSettings
from cellcal.core.methods.fullframe.start import initial_scale, refine, robust_start
from cellcal.devices.errors import CalibrationError, CalibrationQualityError
from cellcal.devices.types import Frame

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
F32 = NDArray[np.float32]

__all__ = ["fit_full_frame", "fit_plane_points"]

#: A median range above this (metres) means the distances are not in metres.
MAX_MEDIAN_RANGE_M = 100.0
_DEFAULTS = FullFrameSettings()
#: Passes over every point (the second from the first one's plane).
FINAL_PASSES = 2
#: Inliers (strided) the flatness grid uses at most.
MAX_FLAT_POINTS = 1 << 16
#: Off-plane maps are subsampled to about this many pixels across before finding regions.
REGION_MAP_PX = 320
#: Frames with at most this many valid pixels are checked for what the edge margin leaves.
SMALL_FRAME_POINTS = 4096
#: Rings around outlier patches examined for mixed pixels, as a multiple of the floor (+ this many pixels).
RING_REACH = 16


# ---------------------------------------------------------------------- the fit
def _subsample(limit: int, *arrays: F32) -> list[F32]:
    """Every k-th point (last axis; contiguous copies) so that at most ``limit`` remain."""
    step = -(-arrays[0].shape[-1] // limit)
    if step <= 1:
        return list(arrays)
    return [np.ascontiguousarray(a[..., ::step]) for a in arrays]


@dataclass
class _Fit:
    plane: Plane
    cov: FloatArray           # covariance of (d_e1, d_e2, d_offset)
    e1: FloatArray
    e2: FloatArray
    inliers: BoolArray
    residual_rms_m: float
    noise_scale_m: float
    unit_rms_m: float         # inlier RMS residual the noise model predicts per unit of noise (see result)
    multipath: tuple[float, float, FloatArray]   # border bias, its sigma, the plane step it implies


def _final(p: F32, dm: F32, model: Model, n: FloatArray, offset: float, s: float, cutoff: Cutoff,
           keep: KeepMask | None, edge: EdgeClean | None) -> _Fit:
    """Passes over every point: plane, sandwich covariance, inliers, RMS, scale, multipath.

    The second pass starts from the first one's full-data plane and scale, so that the
    inliers and the edge clean-up of the answer do not depend on where the start was.
    """
    scratch = Scratch(dm.size)                                 # point-sized rows reused by both passes
    for k in range(FINAL_PASSES):
        e1, e2 = basis(n)
        if edge is not None:
            edge.scale = s
        fin: FinalPass = final_pass(p, dm, n, e1, e2, offset, cutoff.at(s), model, keep,
                                    answer=k == FINAL_PASSES - 1, scratch=scratch)
        n_fin, offset_fin = step_plane(n, e1, e2, offset, fin.step)
        s = math.sqrt(fin.z2_sum / fin.n_inliers / cutoff.kept_var)   # truncation-corrected scale
        if k < FINAL_PASSES - 1:
            n, offset = n_fin, offset_fin
    try:
        h_inv = np.linalg.inv(fin.hessian)
        h4_inv = np.linalg.inv(fin.radial[0])
    except np.linalg.LinAlgError:
        raise CalibrationError("full-frame fit is degenerate: the inliers do not span a plane") from None
    dof = max(fin.n_inliers - 3, 1)
    # sandwich H^-1 M H^-1, small-sample factor n / (n - 3), hard-rejection correction
    cov = h_inv @ fin.meat @ h_inv * (fin.n_inliers / dof) * cutoff.cov_factor
    rms = math.sqrt(fin.ortho2_sum / fin.n_inliers)
    unit = math.sqrt(cutoff.kept_var * fin.model_ortho2_sum / fin.n_inliers)
    step4 = -h4_inv @ fin.radial[1]                             # plane and radial range bias together
    beta_sigma = s * math.sqrt(max(float(h4_inv[3, 3]), 0.0) * cutoff.cov_factor)
    return _Fit(Plane(n_fin, offset_fin), cov, e1, e2, fin.inliers, rms, s, unit,
                (-float(step4[3]), beta_sigma, step4[:3] - fin.step))


def _robust_fit(p: F32, dm: F32, model: Model, settings: FullFrameSettings, keep: KeepMask | None = None,
                edge: EdgeClean | None = None) -> _Fit:
    """The stages on finite camera-frame points ``p`` (3, N) with ranges ``dm``.

    ``keep`` maps the inlier mask (N,) and the residuals of the converged plane to the
    points allowed in the last pass (image-space clean-up, see ``edge_margin_deg``).
    """
    n, offset = robust_start(p, dm, model, settings)
    if model.sigma is None:                                    # strided subsample for the passes
        ps, ds = _subsample(settings.refine_points, p, dm)
        sub = model
    else:
        ps, ds, ss = _subsample(settings.refine_points, p, dm, model.sigma)
        sub = model.subset(ss)
    s, cutoff = initial_scale(ps, ds, sub, n, offset, settings)
    n, offset, s = refine(ps, ds, sub, n, offset, s, cutoff, settings)
    return _final(p, dm, model, n, offset, s, cutoff, keep, edge)


# ---------------------------------------------------------------------- derived values
def _geometry(n: FloatArray, d: FloatArray) -> FloatArray:
    """Angle to the optical axis, tilt x, tilt y, height along the axis of planes (K, 4).

    Vectorised copies of :meth:`Plane.angle_to_optical_axis_rad`,
    :meth:`Plane.tilt_about_x_rad`, :meth:`Plane.tilt_about_y_rad` and
    :meth:`Plane.distance_along_optical_axis_m` (NaN where the axis misses the plane)
    for unit normals ``n`` (K, 3) and offsets ``d`` (K,).
    """
    nz = n[:, 2]
    f = np.where((nz > 0)[:, None], -n, n)            # the normal as seen from the camera
    out = np.empty((n.shape[0], 4))
    out[:, 0] = np.arcsin(np.minimum(1.0, np.abs(nz)))
    out[:, 1] = np.arctan2(-f[:, 1], -f[:, 2])
    out[:, 2] = np.arctan2(f[:, 0], -f[:, 2])
    with np.errstate(divide="ignore", invalid="ignore"):
        h = -d / nz
    out[:, 3] = np.where((np.abs(nz) >= 1e-12) & (h > 0), h, np.nan)
    return out


def _derived(fit: _Fit) -> tuple[list[float], list[float], FloatArray]:
    """Angle, tilt x, tilt y, height, their 1-sigma, and the (4, 3) Jacobian (central differences)."""
    n0 = fit.plane.normal
    d0 = fit.plane.offset_m
    steps = np.array([1e-6, 1e-6, 1e-6 * max(abs(d0), 1e-3)])
    dp = np.concatenate([np.zeros((1, 3)), np.diag(steps), -np.diag(steps)])   # (7, 3): 0, +steps, -steps
    nn = n0 + dp[:, :1] * fit.e1 + dp[:, 1:2] * fit.e2
    norm = np.linalg.norm(nn, axis=1)
    v = _geometry(nn / norm[:, None], (d0 + dp[:, 2]) / norm)
    jac = ((v[1:4] - v[4:7]) / (2.0 * steps[:, None])).T                      # (4, 3)
    var = np.einsum("ij,jk,ik->i", jac, fit.cov, jac)                          # diag(J C J^T)
    return v[0].tolist(), np.sqrt(np.maximum(var, 0.0)).tolist(), jac


@dataclass(frozen=True)
class _Extras:
    """What the frame path adds: image coverage, flatness and the edge clean-up."""

    coverage: float = math.nan
    flatness: Flatness | None = None
    edge: EdgeReport | None = None


def _assemble(fit: _Fit, settings: FullFrameSettings, model: Model, *, n_points: int, valid_fraction: float,
              inlier_mask: BoolArray, n_frames: int, extras: _Extras) -> FullFrameResult:
    """The result: estimates with intervals, covariances of normal and offset, gate values."""
    (angle, tx, ty, height), (s_a, s_x, s_y, s_h), jac = _derived(fit)
    if not (math.isfinite(height) and height > 0):
        raise CalibrationError("full-frame fit: the plane does not cross the optical axis in front of the "
                               "camera, so its height is undefined; is the camera looking at the plane?")
    z = NormalDist().inv_cdf(0.5 + settings.confidence / 2.0)   # two-sided normal quantile: value ± z sigma
    e = np.stack([fit.e1, fit.e2], axis=1)
    cov_n = e @ fit.cov[:2, :2] @ e.T                    # tangent steps -> unit normal (3x3)
    cov_nd = e @ fit.cov[:2, 2]
    edge = extras.edge or EdgeReport()
    n_in = int(np.count_nonzero(fit.inliers))
    inlier_fraction = (n_in + edge.n_dropped) / n_points   # on the plane: inliers and mixed pixels
    sigma_given = model.sigma is not None
    flat = extras.flatness
    gates = gate_table(settings, valid_fraction, inlier_fraction, fit.residual_rms_m, fit.unit_rms_m,
                       sigma_given, extras.coverage, math.nan if flat is None else flat.excess_m)
    beta, beta_sigma, dstep = fit.multipath
    shift = jac @ dstep                                  # change of each value with the radial bias fitted
    return FullFrameResult(
        plane=fit.plane, angle=Estimate.from_sigma(angle, s_a, z, 0.0, math.pi / 2),
        tilt_x=Estimate.from_sigma(tx, s_x, z), tilt_y=Estimate.from_sigma(ty, s_y, z),
        height=Estimate.from_sigma(height, s_h, z), confidence=settings.confidence,
        normal_covariance=cov_n, offset_variance_m2=float(fit.cov[2, 2]), normal_offset_covariance=cov_nd,
        valid_fraction=valid_fraction, inlier_fraction=inlier_fraction, residual_rms_m=fit.residual_rms_m,
        coverage=extras.coverage, noise_scale_m=fit.noise_scale_m, n_points=n_points, n_inliers=n_in,
        n_frames=n_frames, inlier_mask=inlier_mask, gates=gates,
        residual_unit_rms_m=fit.unit_rms_m, sigma_given=sigma_given,
        flatness_m=math.nan if flat is None else flat.excess_m, flatness_where="" if flat is None else flat.where,
        multipath=Estimate.from_sigma(beta, beta_sigma, z),
        multipath_shift={"angle_rad": float(shift[0]), "tilt_x_rad": float(shift[1]),
                         "tilt_y_rad": float(shift[2]), "height_m": float(shift[3])},
        mixed_margin_px=edge.margin_px, n_mixed=edge.n_dropped, settings=settings)


# ---------------------------------------------------------------------- input checks
def _check_points(p: F32, dm: F32, n_behind: int, n_pixels: int, min_valid: float, what: str) -> None:
    """Enough points in front of the camera, in metres."""
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


def _check_margin(edge: EdgeClean, n_ok: int, n_pixels: int, min_valid: float) -> None:
    """Few valid pixels: enough of them must lie farther than the edge margin from invalid patches."""
    if n_ok > SMALL_FRAME_POINTS:
        return
    left = edge.margin_keep()
    if left < MIN_POINTS:
        raise CalibrationQualityError(
            "valid_fraction", n_ok / n_pixels, min_valid,
            f"{n_ok} valid pixels, {left} left after the edge margin ({edge.floor_px} px around invalid regions, "
            f"edge_margin_deg); a full-frame fit needs {MIN_POINTS}")


def _front(p: F32, ok: BoolArray) -> tuple[BoolArray, int]:
    """``ok`` restricted to z > 0, and how many finite points were behind the camera."""
    with np.errstate(invalid="ignore"):
        behind = ok & ~(p[..., 2] > 0)
    return ok & ~behind, int(np.count_nonzero(behind))


# ---------------------------------------------------------------------- public API
def fit_plane_points(points_m: ArrayLike, sigma_m: ArrayLike | None = None,
                     settings: FullFrameSettings | None = None) -> FullFrameResult:
    """Robust full-cloud plane fit of raw camera-frame points.

    The sensor must be at the origin (ranges are measured along the rays through it).

    Args:
        points_m: Shape (N, 3), camera frame, metres; rows with NaN/inf are skipped.
        sigma_m: Optional per-point range-noise sigma, metres, shape (N,): replaces the
            noise model's weights (rows with sigma <= 0 or non-finite are skipped).
        settings: Fit settings and gates; None uses the defaults.

    Returns:
        The result; ``inlier_mask`` has shape (N,), ``coverage`` and ``flatness_m`` are
        NaN (no image) and there are no coverage and flatness gates; ``valid_fraction``
        counts finite rows in front of the camera.

    Raises:
        CalibrationError: Wrong shape or type, points behind the camera or in millimetres,
            or no plane can be defined.
        CalibrationQualityError: Fewer than 16 usable points (gate ``valid_fraction``).
    """
    cfg = settings or _DEFAULTS
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
    ok, n_behind = _front(pts, ok)
    p = np.ascontiguousarray(pts[ok].T)
    d = np.ascontiguousarray(dm[ok])
    _check_points(p, d, n_behind, n_all, cfg.min_valid_fraction, "usable point")
    model = Model(cfg.weighted, cfg.noise_distance_exponent, None if sig is None else np.ascontiguousarray(sig[ok]))
    fit = _robust_fit(p, d, model, cfg)
    mask = np.zeros(n_all, dtype=bool)
    mask[ok] = fit.inliers
    n_ok = p.shape[1]
    return _assemble(fit, cfg, model, n_points=n_ok, valid_fraction=n_ok / n_all, inlier_mask=mask,
                     n_frames=1, extras=_Extras())


@dataclass
class _FramePoints:
    """Pooled valid points of one or more frames of the same camera."""

    frames: list[Frame]
    p: F32                    # (3, N) camera frame
    dm: F32                   # (N,) measured range
    masks: list[BoolArray]    # per frame, flat (H*W,) mask of the pixels that became points
    n_behind: int             # finite valid pixels with z <= 0 (dropped)


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


def _frames_points(frames: Frame | Sequence[Frame]) -> _FramePoints:
    """Validate frames; pooled valid points in front of the camera, ranges and each frame's flat mask."""
    seq = _frame_list(frames)
    pts, dms, masks = [], [], []
    behind = 0
    for f in seq:
        dist = f.distance.reshape(-1)
        xyz = f.xyz.reshape(-1, 3)
        with np.errstate(invalid="ignore"):
            m = f.valid.reshape(-1) & (dist > 0)   # NaN compares False
        idx = np.flatnonzero(m)
        p = np.take(xyz.T, idx, axis=1)            # (3, n) structure of arrays
        d = np.take(dist, idx)
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
    if len(seq) == 1:
        return _FramePoints(seq, pts[0], dms[0], masks, behind)
    return _FramePoints(seq, np.concatenate(pts, axis=1), np.concatenate(dms), masks, behind)


def _pixel_inliers(inliers: BoolArray, masks: list[BoolArray], shape: tuple[int, int]) -> BoolArray:
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


def _noise_orth(p: F32, dm: F32, frame: PlaneFrame, model: Model) -> F32:
    """Orthogonal noise shape ``sigma_range |cos|`` of points with ranges ``dm`` (up to the fitted scale).

    Evaluated at the range the plane predicts along each ray, never at the noisy one
    (weights correlated with the noise bias the local planes, as in ADR 0007, "Weighting").
    """
    pn = frame.n.astype(np.float32) @ p
    cos = np.abs(pn) / dm
    if model.weighted:
        t = np.abs(np.float32(-frame.offset) * dm / pn)   # predicted range along the ray
        shape = t ** np.float32(model.exponent) / np.sqrt(np.maximum(cos, np.float32(1e-6)))
    else:
        shape = np.ones_like(dm)
    out: F32 = shape * cos
    return out


def _flatness(fit: _Fit, data: _FramePoints, model: Model, cfg: FullFrameSettings) -> Flatness:
    """The flatness gate's value: local planes of grid cells and of large planar off-plane regions."""
    h, w = data.frames[0].shape
    pl = fit.plane
    e1, e2 = basis(pl.normal)
    frame = PlaneFrame(pl.normal, e1, e2, pl.offset_m)
    sel = np.flatnonzero(fit.inliers)
    sel = sel[:: max(1, -(-sel.size // MAX_FLAT_POINTS))]   # strided inliers
    grid = (min(cfg.flatness_grid[0], w), min(cfg.flatness_grid[1], h))
    cell = grid_cells(_pixels_of(sel, data.masks), (h, w), grid)
    p_in = _gather(data.p, sel)
    wt = _noise_orth(p_in, data.dm[sel], frame, model).astype(np.float64)
    del sel                                                 # point-sized arrays go as soon as they are used
    np.square(wt, out=wt)
    np.divide(1.0, wt, out=wt)                              # weights 1 / noise^2
    uvw = frame.uvw(p_in)
    del p_in
    best = grid_flatness(uvw, wt, cell, grid, fit.noise_scale_m, cfg.flatness_sigma)
    del uvw, wt, cell
    step = max(1, round(max(h, w) / REGION_MAP_PX))
    start = 0
    for m in data.masks:
        k = int(np.count_nonzero(m))
        inl = fit.inliers[start:start + k]
        if k - int(np.count_nonzero(inl)) >= cfg.flatness_min_region * k:   # enough outliers for a region
            reg = _region_flatness(frame, data.p[:, start:start + k], data.dm[start:start + k], m, inl, (h, w),
                                   step, fit, model, cfg)
            if reg.excess_m > best.excess_m:
                best = reg
        start += k
    return best


def _region_flatness(frame: PlaneFrame, p: F32, dm: F32, m: BoolArray, inl: BoolArray, shape: tuple[int, int],
                     step: int, fit: _Fit, model: Model, cfg: FullFrameSettings) -> Flatness:
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
    p_off = _gather(p, pick)
    noise = fit.noise_scale_m * _noise_orth(p_off, dm[pick], frame, model).astype(np.float64)
    return region_flatness(frame, p_off, noise, lab[pick], sizes, min_size, cfg.flatness_sigma, step ** 2,
                           k)


def _gather(p: F32, sel: NDArray[np.intp]) -> F32:
    """``p[:, sel]`` of points ``p`` (3, N), 2.5x faster: one ``take`` per coordinate.

    Laid out as ``p[:, sel]`` is (column-major), so that the float32 products downstream
    round exactly as they did.
    """
    out = np.empty((3, sel.size), dtype=np.float32, order="F")
    for k in range(3):
        np.take(p[k], sel, out=out[k])
    return out


def _pixels_of(sel: NDArray[np.intp], masks: list[BoolArray]) -> NDArray[np.intp]:
    """Flat pixel index (within its frame) of the pooled points ``sel`` (sorted)."""
    if len(masks) == 1:
        out: NDArray[np.intp] = np.flatnonzero(masks[0])[sel]
        return out
    return np.concatenate([np.flatnonzero(m) for m in masks])[sel]


def fit_full_frame(frames: Frame | Sequence[Frame], settings: FullFrameSettings | None = None) -> FullFrameResult:
    """Fit the measuring plane to every valid pixel of one or more frames of a static camera.

    Frames are pooled (each pixel of each frame is one observation). The fit does not
    raise on a failed gate: see ``result.gates`` or call :func:`check_gates`.

    Args:
        frames: One frame or several of the same camera and pose.
        settings: Fit settings and gates (the ``[full_frame]`` table); None: defaults.

    Returns:
        The plane (camera frame, normal toward the camera) with intervals and gates.

    Raises:
        CalibrationError: Malformed input (not frames, mixed shapes), points behind the
            camera or in millimetres, or no plane defined.
        CalibrationQualityError: Fewer than 16 valid pixels (gate ``valid_fraction``).
    """
    cfg = settings or _DEFAULTS
    data = _frames_points(frames)
    h, w = data.frames[0].shape
    n_pixels = h * w * len(data.frames)
    _check_points(data.p, data.dm, data.n_behind, n_pixels, cfg.min_valid_fraction, "valid pixel")
    intr = data.frames[0].intrinsics
    floor_px = math.ceil(math.radians(cfg.edge_margin_deg) * max(intr.fx, intr.fy) - 1e-9)   # degrees -> px
    edge = None
    if floor_px > 0:
        edge = EdgeClean(data.masks, (h, w), floor_px, RING_REACH * (floor_px + 1), cfg.mixed_ring_sigma)
        _check_margin(edge, data.p.shape[1], n_pixels, cfg.min_valid_fraction)
    model = Model(cfg.weighted, cfg.noise_distance_exponent)
    fit = _robust_fit(data.p, data.dm, model, cfg, keep=edge, edge=edge)
    mask = _pixel_inliers(fit.inliers, data.masks, (h, w))
    extras = _Extras(image_coverage(mask, cfg), _flatness(fit, data, model, cfg), None if edge is None else edge.report)
    return _assemble(fit, cfg, model, n_points=data.p.shape[1], valid_fraction=data.p.shape[1] / n_pixels,
                     inlier_mask=mask, n_frames=len(data.frames), extras=extras)
