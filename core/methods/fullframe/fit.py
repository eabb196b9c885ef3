"""The robust full-frame fit: robust start, reweighted Gauss-Newton on the ranges, intervals, gates.

Points are in the camera frame (OpenCV: x right, y down, z along the optical axis), metres,
with the sensor at the origin; the fitted normal points toward the camera (``offset_m > 0``).
Method and rationale: docs/adr/0007-full-frame-fit.md; region of interest, expected plane,
the quantisation floor and the stereo seam: docs/adr/0028-honest-full-frame-fit.md.

The stereo seam. Frames whose ``measurement.triangulating`` is true are fitted in disparity
space by ``cellcal.core.methods.fullframe.disparity.fit_disparity(p, pixel_index, shape,
model, settings, expected)`` with

* ``p``: (3, N) float32 camera-frame points (metres) of the valid pixels in the region,
  pooled over the frames (each pixel of each frame one point);
* ``pixel_index``: (N,) flat index ``row * W + column`` of each point's pixel within its
  own frame (the frames share one ``shape``);
* ``shape``: ``(H, W)``; ``model``: the frames' :class:`MeasurementModel`; ``settings``:
  the :class:`FullFrameSettings`; ``expected``: the :class:`ExpectedPlane` or None;

returning an object with ``plane`` (:class:`Plane`, camera frame, normal toward the camera),
``cov`` (3x3 covariance of ``(d_e1, d_e2, d_offset)`` with ``e1, e2 = basis(plane.normal)``
of ``passes.py``, rad² and m²), ``e1``, ``e2``, ``inliers`` ((N,) bool), ``residual_rms_m``
(the inliers' RMS orthogonal residual), ``expected_rms_m`` (what the model predicts for
them), ``floor_rms_m`` (their quantisation floor, orthogonal), ``noise_scale_m`` and
``notes`` (tuple of short strings for ``interval_notes``). Coverage, flatness, the
spatial design effect, the quantisation floor of the intervals, the lock-on check and the
gates are then the range path's.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from statistics import NormalDist  # not scipy.special: its 0.2 s import is off calibrate's start-up

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cellcal.core.geometry.planes import Plane
from cellcal.core.methods.fullframe.expected import ExpectedPlane, check_region
from cellcal.core.methods.fullframe.flatness import (
    Flatness,
    PlaneFrame,
    grid_cells,
    grid_flatness,
    off_plane_regions,
    region_flatness,
)
from cellcal.core.methods.fullframe.gates import gate_table, image_coverage
from cellcal.core.methods.fullframe.honesty import (
    DEFF_SIGNIFICANCE,
    SAMPLE,
    design_effect,
    lock_on,
    quantisation_floor,
    rounding_allowance_m,
)
from cellcal.core.methods.fullframe.mixed import EdgeClean, EdgeReport
from cellcal.core.methods.fullframe.passes import (
    Cutoff,
    FinalPass,
    KeepMask,
    Model,
    NothingLeftError,
    Scratch,
    basis,
    final_pass,
    step_plane,
)
from cellcal.core.methods.fullframe.result import Estimate, FullFrameResult, IntervalFactors
from cellcal.core.methods.fullframe.settings import MIN_POINTS, FullFrameSettings
from cellcal.core.methods.fullframe.start import initial_scale, refine, robust_start
from cellcal.devices.errors import CalibrationError, CalibrationQualityError
from cellcal.devices.measurement import UNKNOWN_MODEL, MeasurementModel
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
#: Exponent of the range in the noise shape the flatness gate weights stereo points with (Z² law).
STEREO_EXPONENT = 2.0


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
    resid: F32 | None = None  # per point: whitened residual, 0 off the inliers (None: not kept)
    expected_rms_m: float = math.nan   # disparity path: what the model predicts for the inliers
    floor_rms_m: float = math.nan      # disparity path: their quantisation floor
    notes: tuple[str, ...] = ()


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
                (-float(step4[3]), beta_sigma, step4[:3] - fin.step), fin.z)


def _robust_fit(p: F32, dm: F32, model: Model, settings: FullFrameSettings, keep: KeepMask | None = None,
                edge: EdgeClean | None = None, expected: ExpectedPlane | None = None) -> _Fit:
    """The stages on finite camera-frame points ``p`` (3, N) with ranges ``dm``.

    ``keep`` maps the inlier mask (N,) and the residuals of the converged plane to the
    points allowed in the last pass (image-space clean-up, see ``edge_margin_deg``).
    ``expected`` restricts the robust start to planes within its tolerances.
    """
    n, offset = robust_start(p, dm, model, settings, expected)
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
    """What the frame path adds: image coverage, flatness, the edge clean-up and the honesty checks."""

    coverage: float = math.nan
    flatness: Flatness | None = None
    edge: EdgeReport | None = None
    honest: _Honest | None = None


@dataclass(frozen=True)
class _Honest:
    """The sensor's floor and expectation for the inliers, a lock-on, and what widened the intervals."""

    measurement: MeasurementModel = UNKNOWN_MODEL
    native_space: str = "range"
    expected_m: float = math.nan
    floor_m: float = 0.0
    sigma_stated: bool = False
    multipath_m: float = 0.0
    lock_on: str = ""
    factors: IntervalFactors = field(default_factory=IntervalFactors)
    notes: tuple[str, ...] = ()
    expected: ExpectedPlane | None = None
    region_pixels: int = 0


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
    hon = extras.honest or _Honest(expected_m=fit.unit_rms_m * (1.0 if model.sigma is not None else math.nan),
                                   sigma_stated=model.sigma is not None, region_pixels=n_points)
    n_in = int(np.count_nonzero(fit.inliers))
    inlier_fraction = (n_in + edge.n_dropped) / n_points   # on the plane: inliers and mixed pixels
    sigma_given = model.sigma is not None
    flat = extras.flatness
    beta, beta_sigma, dstep = fit.multipath
    shift = jac @ dstep                                  # change of each value with the radial bias fitted
    exp = hon.expected
    res = FullFrameResult(
        plane=fit.plane, angle=Estimate.from_sigma(angle, s_a, z, 0.0, math.pi / 2),
        tilt_x=Estimate.from_sigma(tx, s_x, z), tilt_y=Estimate.from_sigma(ty, s_y, z),
        height=Estimate.from_sigma(height, s_h, z), confidence=settings.confidence,
        normal_covariance=cov_n, offset_variance_m2=float(fit.cov[2, 2]), normal_offset_covariance=cov_nd,
        valid_fraction=valid_fraction, inlier_fraction=inlier_fraction, residual_rms_m=fit.residual_rms_m,
        coverage=extras.coverage, noise_scale_m=fit.noise_scale_m, n_points=n_points, n_inliers=n_in,
        n_frames=n_frames, inlier_mask=inlier_mask, gates={},
        residual_unit_rms_m=fit.unit_rms_m, sigma_given=sigma_given,
        flatness_m=math.nan if flat is None else flat.excess_m, flatness_where="" if flat is None else flat.where,
        multipath=Estimate.from_sigma(beta, beta_sigma, z),
        multipath_shift={"angle_rad": float(shift[0]), "tilt_x_rad": float(shift[1]),
                         "tilt_y_rad": float(shift[2]), "height_m": float(shift[3])},
        mixed_margin_px=edge.margin_px, n_mixed=edge.n_dropped, settings=settings,
        measurement=hon.measurement, native_space=hon.native_space, residual_expected_m=hon.expected_m,
        residual_floor_m=hon.floor_m, sigma_stated=hon.sigma_stated, multipath_allowance_m=hon.multipath_m,
        lock_on=hon.lock_on, expected_departure=None if exp is None else exp.departure(fit.plane),
        expected_tolerance=None if exp is None else (exp.angle_tolerance_rad, exp.offset_tolerance_m),
        region_pixels=hon.region_pixels, interval_factors=hon.factors, interval_notes=hon.notes)
    if extras.honest is None:                            # raw clouds: the expected RMS from the default noise
        res = dataclasses.replace(res, residual_expected_m=_raw_expected(res, settings))
    return dataclasses.replace(res, gates=gate_table(settings, res))


def _raw_expected(res: FullFrameResult, settings: FullFrameSettings) -> float:
    """A raw cloud's expected RMS: given sigmas' own, else the noise law at ``expected_noise_m`` (m)."""
    if res.sigma_given:
        return res.residual_unit_rms_m
    return res.residual_unit_rms_m * settings.noise_at_1m_m(UNKNOWN_MODEL)


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


def _nothing_left(n_ok: int, left: int, n_pixels: int, min_valid: float, what: str, floor_px: int
                  ) -> CalibrationQualityError:
    """Gate ``valid_fraction``: too few pixels left after the edge clean-up (small and large frames alike)."""
    return CalibrationQualityError(
        "valid_fraction", left / max(n_pixels, 1), min_valid,
        f"{n_ok} {what}s, {left} left after the edge clean-up ({floor_px} px around invalid and off-plane "
        f"patches, edge_margin_deg, and mixed pixels at depth edges); a full-frame fit needs {MIN_POINTS}")


def _check_margin(edge: EdgeClean, n_ok: int, n_pixels: int, min_valid: float, what: str) -> None:
    """Few valid pixels: enough of them must lie farther than the edge margin from invalid patches."""
    if n_ok > SMALL_FRAME_POINTS:
        return
    left = edge.margin_keep()
    if left < MIN_POINTS:
        raise _nothing_left(n_ok, left, n_pixels, min_valid, what, edge.floor_px)


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
    sig_ok = None if sig is None else np.ascontiguousarray(sig[ok])
    model = Model(cfg.weighted, cfg.noise_exponent(UNKNOWN_MODEL), sig_ok)
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


def _frames_points(seq: list[Frame], region: BoolArray | None = None) -> _FramePoints:
    """Pooled valid points (in the flat (H*W,) region) in front of the camera, ranges and each frame's flat mask."""
    pts, dms, masks = [], [], []
    behind = 0
    for f in seq:
        dist = f.distance.reshape(-1)
        xyz = f.xyz.reshape(-1, 3)
        with np.errstate(invalid="ignore"):
            m = f.valid.reshape(-1) & (dist > 0)   # NaN compares False
        if region is not None:
            m &= region                            # pixels outside the region of interest are ignored
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


def _sample_inliers(inliers: BoolArray) -> NDArray[np.intp]:
    """Indices of a strided sample of the inliers (about ``SAMPLE``), without a pass over every point's index."""
    step = max(1, inliers.size // (2 * SAMPLE))
    idx = np.arange(0, inliers.size, step)
    return idx[inliers[idx]]


def _honesty(fit: _Fit, data: _FramePoints, shape: tuple[int, int], meas: MeasurementModel, cfg: FullFrameSettings,
             region_pixels: int, expected: ExpectedPlane | None) -> tuple[_Fit, _Honest]:
    """The sensor's floor and expected RMS for the inliers, a lock-on, and the widened covariance.

    Covariance (d_e1, d_e2, d_offset): times the spatial design effect when significant, then
    never below the quantisation floor spread over the inliers' extent (``honesty.py``).
    """
    n, off = fit.plane.normal, fit.plane.offset_m
    sel = _sample_inliers(fit.inliers)
    p_s = _gather(data.p, sel).astype(np.float64)          # (3, n) sampled inliers
    ortho = n @ p_s + off                                  # their orthogonal residuals, m
    disparity = meas.triangulating
    if disparity:
        floor, expected_m = fit.floor_rms_m, fit.expected_rms_m
        stated = (meas.disparity_sigma_px or 0.0) > 0
        resid = np.multiply(n.astype(np.float32) @ data.p + np.float32(off), fit.inliers, dtype=np.float32)
    else:
        cos = np.abs(n @ p_s) / np.maximum(data.dm[sel].astype(np.float64), 1e-12)   # |cos| ray-normal
        q = meas.range_step_m if meas.kind == "tof" else 0.0
        floor = q / math.sqrt(12.0) * math.sqrt(float(np.mean(cos * cos))) if cos.size else 0.0
        expected_m = math.hypot(fit.unit_rms_m * cfg.noise_at_1m_m(meas), floor)
        stated = meas.kind == "tof" and meas.sigma_at_1m_m is not None
        resid = fit.resid if fit.resid is not None else np.zeros(fit.inliers.size, np.float32)
    depth_all = data.dm if meas.kind == "tof" else data.p[2]   # what the sensor quantises
    locked = lock_on(np.take(depth_all, sel), ortho, depth_all)
    deff, se = design_effect(resid, data.masks, shape)
    # significant correlation only; the disparity path has already applied its own (in disparity units)
    spatial = deff if deff > 1.0 + DEFF_SIGNIFICANCE * se and not disparity else 1.0
    uv = np.stack([fit.e1 @ p_s, fit.e2 @ p_s])            # in-plane coordinates, m
    cov, held = quantisation_floor(fit.cov * spatial, floor, uv, int(np.count_nonzero(fit.inliers)))
    ratio = fit.residual_rms_m / expected_m if expected_m > 0 else math.nan
    notes = list(fit.notes)
    if stated and ratio > 1.0 and not disparity:
        notes.append(f"residuals {ratio:.3g} x what the sensor model expects: the intervals follow the observed "
                     "scatter (sandwich covariance)")
    if spatial > 1.0:
        notes.append(f"intervals {math.sqrt(spatial):.3g} x wider for residuals correlated across neighbouring "
                     f"pixels (design effect {spatial:.3g})")
    if held:
        notes.append(f"intervals held at the quantisation floor ({floor * 1000:.3g} mm RMS across the plane)")
    honest = _Honest(meas, "disparity" if disparity else "range", expected_m, floor, stated,
                     meas.multipath_m if meas.kind == "tof" else 0.0, locked, IntervalFactors(ratio, spatial, held),
                     tuple(notes), expected, region_pixels)
    return dataclasses.replace(fit, cov=cov, resid=None), honest   # the residuals' scratch goes before flatness


def _disparity_fit(data: _FramePoints, shape: tuple[int, int], meas: MeasurementModel, cfg: FullFrameSettings,
                   expected: ExpectedPlane | None) -> _Fit:
    """The stereo path (the seam in the module docstring): ``fit_disparity`` as a :class:`_Fit`."""
    from cellcal.core.methods.fullframe.disparity import fit_disparity  # only stereo frames need it

    pixel_index = _pixels_of(np.arange(data.p.shape[1]), data.masks)
    d = fit_disparity(data.p, pixel_index, shape, meas, cfg, expected)
    nan3 = (math.nan, math.nan, np.zeros(3))              # no radial range bias in disparity space
    return _Fit(d.plane, np.asarray(d.cov, dtype=np.float64), np.asarray(d.e1, dtype=np.float64),
                np.asarray(d.e2, dtype=np.float64), np.asarray(d.inliers, dtype=bool), float(d.residual_rms_m),
                float(d.noise_scale_m), math.nan, nan3, None, float(d.expected_rms_m), float(d.floor_rms_m),
                tuple(d.notes))


def fit_full_frame(frames: Frame | Sequence[Frame], settings: FullFrameSettings | None = None, *,
                   region: NDArray[np.bool_] | None = None, expected: ExpectedPlane | None = None
                   ) -> FullFrameResult:
    """Fit the measuring plane to every valid pixel of one or more frames of a static camera.

    Frames are pooled (each pixel of each frame is one observation). The fit does not
    raise on a failed gate: see ``result.gates`` or call :func:`check_gates`. The frames'
    measurement model (``frame.measurement``) sets the native space (stereo: disparity,
    see the module docstring), the noise law and the quantisation floor.

    Args:
        frames: One frame or several of the same camera and pose.
        settings: Fit settings and gates (the ``[full_frame]`` table); None: defaults.
        region: (H, W) bool region of interest: pixels outside it are ignored, and the
            valid fraction and coverage are taken over it. None: the whole image.
        expected: The plane the user means (camera frame): only planes within its
            tolerances start the fit, and a fit outside them fails gate ``expected_plane``.

    Returns:
        The plane (camera frame, normal toward the camera) with intervals and gates.

    Raises:
        CalibrationError: Malformed input (not frames, mixed shapes, a bad region), points
            behind the camera or in millimetres, or no plane defined.
        CalibrationQualityError: Fewer than 16 valid pixels in the region, or fewer left after
            the edge clean-up (gate ``valid_fraction``); no plane near the expected one
            (gate ``expected_plane``).
    """
    cfg = settings or _DEFAULTS
    seq = _frame_list(frames)
    h, w = seq[0].shape
    roi = check_region(region, (h, w))
    roi_flat = None if roi is None else roi.reshape(-1)
    data = _frames_points(seq, roi_flat)
    n_pixels = (h * w if roi is None else int(np.count_nonzero(roi))) * len(seq)   # region pixels, all frames
    what = "valid pixel" if roi is None else "valid pixel in the region"
    _check_points(data.p, data.dm, data.n_behind, n_pixels, cfg.min_valid_fraction, what)
    meas = seq[0].measurement
    edge = None
    if meas.triangulating:
        model = Model(cfg.weighted, STEREO_EXPONENT)       # flatness weights: depth noise grows as Z²
        fit = _disparity_fit(data, (h, w), meas, cfg, expected)
    else:
        model = Model(cfg.weighted, cfg.noise_exponent(meas))
        intr = seq[0].intrinsics
        floor_px = math.ceil(math.radians(cfg.edge_margin_deg) * max(intr.fx, intr.fy) - 1e-9)   # degrees -> px
        if floor_px > 0:
            edge = EdgeClean(data.masks, (h, w), floor_px, RING_REACH * (floor_px + 1), cfg.mixed_ring_sigma,
                             region=roi_flat)
            _check_margin(edge, data.p.shape[1], n_pixels, cfg.min_valid_fraction, what)
        try:
            fit = _robust_fit(data.p, data.dm, model, cfg, keep=edge, edge=edge, expected=expected)
        except NothingLeftError as exc:
            raise _nothing_left(exc.n_points, exc.n_left, n_pixels, cfg.min_valid_fraction, what,
                                0 if edge is None else edge.floor_px) from None
    fit, honest = _honesty(fit, data, (h, w), meas, cfg, n_pixels, expected)
    mask = _pixel_inliers(fit.inliers, data.masks, (h, w))
    flat = _flatness(fit, data, model, cfg)
    bend = rounding_allowance_m(honest.floor_m, fit.residual_rms_m)   # undithered rounding bends local planes
    if bend > 1e-5 and flat.excess_m > 0:
        left = max(flat.excess_m - bend, 0.0)
        flat = Flatness(left, flat.where if left > 0 else "")
        honest = dataclasses.replace(honest, notes=(*honest.notes, f"flatness allows {bend * 1000:.3g} mm for "
                                                    "the rounding's sawtooth (weakly dithered depth steps)"))
    extras = _Extras(image_coverage(mask, cfg, roi), flat, None if edge is None else edge.report, honest)
    return _assemble(fit, cfg, model, n_points=data.p.shape[1], valid_fraction=data.p.shape[1] / n_pixels,
                     inlier_mask=mask, n_frames=len(data.frames), extras=extras)
