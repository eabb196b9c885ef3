"""The range space: a ToF camera's ranges along fixed rays (and raw clouds seen from the origin).

The plane ``n·p + offset = 0`` predicts the range ``t = -offset / (r·n)`` along each ray
``r``; residuals ``|p| - t`` are whitened by the noise law ``sigma ∝ t^e / sqrt|cos|`` (or
given sigmas) and cut at a band of robust sigmas. Here: the noise law, the robust start
(the best triplet plane), the mixed-pixel clean-up at depth edges and the floors (the range
step across the plane, the stated noise); the Gauss-Newton passes are ``passes.py``.
Rationale: docs/adr/0007-full-frame-fit.md ("Robustness", "Mixed pixels"),
docs/adr/0028-honest-full-frame-fit.md, docs/adr/0050-measurement-spaces.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import cv2
import numpy as np
from numpy.typing import NDArray

from cellcal.core.geometry.planes import Plane
from cellcal.core.methods.fullframe.passes import NothingLeftError, fit_from_start
from cellcal.core.methods.fullframe.points import FIXED_SEED, ExpectedPlane, Points, Sample, fixed_subsample, kept_array
from cellcal.core.methods.fullframe.settings import DEFAULT_NOISE_EXPONENT, MIN_POINTS, FullFrameSettings
from cellcal.core.methods.fullframe.space import EdgeReport, Floors, Model, SpaceFit
from cellcal.core.methods.fullframe.systematic import Response, pixel_uv
from cellcal.devices.errors import CalibrationError, CalibrationQualityError
from cellcal.devices.measurement import UNKNOWN_MODEL, MeasurementModel
from cellcal.devices.readable import quantity_pair
from cellcal.devices.types import Intrinsics

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
F32 = NDArray[np.float32]

__all__ = ["EdgeClean", "RangeSpace", "robust_start"]

#: Rings around outlier patches examined for mixed pixels, as a multiple of the floor (+ this many pixels).
RING_REACH = 16
#: Frames with at most this many valid pixels are checked for what the edge margin leaves.
SMALL_FRAME_POINTS = 4096
#: Points whose second principal variance is below this fraction of the first lie along a line.
LINE_RATIO = 1e-4
#: With an expected plane, this many times ``hypotheses`` triplets are drawn (only those within
#: its tolerances are scored: a plane holding a third of the points gives 1 in 27 triplets).
EXPECTED_DRAWS = 8
_K3 = np.ones((3, 3), np.uint8)
#: Pixels beyond every examined ring needed for their mean to be the reference.
MIN_REFERENCE = 1000
#: A band of rings matters when its residuals could move the fit by this many of its standard errors.
RELEVANT_PULL = 0.1
#: Points binned into rings per block.
CHUNK = 1 << 16


@dataclass(frozen=True)
class RangeSpace:
    """Residuals along the rays, whitened by the range-noise law (see the module docstring).

    Attributes:
        settings: The ``[full_frame]`` table.
        measurement: The camera's measurement model (its noise law, quantisation and stated noise).
        intrinsics: The camera's intrinsics: the edge margin in pixels at its focal length
            (None: no mixed-pixel clean-up, as for raw clouds).
        sigma_m: (N,) given per-point range sigmas, metres, replacing the noise law (raw clouds), or None.
    """

    settings: FullFrameSettings
    measurement: MeasurementModel = UNKNOWN_MODEL
    intrinsics: Intrinsics | None = None
    sigma_m: F32 | None = None
    name: ClassVar[str] = "range"

    @property
    def model(self) -> Model:
        """How residuals are whitened: the noise law (the config's exponent, else the camera's, else 1.5) or sigmas."""
        return Model(self.settings.weighted, noise_exponent(self.settings, self.measurement), self.sigma_m)

    @property
    def edge_floor_px(self) -> int:
        """Rings always dropped around solid patches of outliers and invalid pixels (``edge_margin_deg`` in px)."""
        if self.intrinsics is None:
            return 0
        return math.ceil(math.radians(self.settings.edge_margin_deg) * max(self.intrinsics.fx, self.intrinsics.fy)
                         - 1e-9)

    @property
    def noise_shape(self) -> Model:
        """The range-noise shape of the flatness gate's weights: the fit's own."""
        return self.model

    def fit(self, points: Points, expected: ExpectedPlane | None) -> SpaceFit:
        """Robust start, passes on a subsample, then two passes over every point (with the edge clean-up)."""
        edge = None
        model, floor_px = self.model, self.edge_floor_px
        if floor_px > 0 and points.masks:
            edge = EdgeClean(points.masks, points.shape, floor_px, RING_REACH * (floor_px + 1),
                             self.settings.mixed_ring_sigma,
                             region=None if points.region is None else points.region.reshape(-1))
            _check_margin(edge, points, self.settings.min_valid_fraction)
        try:
            n, offset = robust_start(points.p, points.dm, model, self.settings, expected)
            fit = fit_from_start(points.p, points.dm, model, self.settings, n, offset, keep=edge)
        except NothingLeftError as exc:
            raise _nothing_left(exc.n_points, exc.n_left, points, self.settings.min_valid_fraction,
                                0 if edge is None else edge.floor_px) from None
        fit.edge = None if edge is None else edge.report
        return fit

    def floors(self, fit: SpaceFit, points: Points, sample: Sample) -> Floors:
        """The range step across the plane, the stated noise law's RMS, and the whitened residuals."""
        meas, tof = self.measurement, self.measurement.kind == "tof"
        cos = np.abs(fit.plane.normal @ sample.p) / np.maximum(points.dm[sample.index].astype(np.float64), 1e-12)
        q = meas.range_step_m if tof else 0.0
        floor = q / math.sqrt(12.0) * math.sqrt(float(np.mean(cos * cos))) if cos.size else 0.0
        expected_m = math.hypot(fit.unit_rms_m * self.settings.noise_at_1m_m(meas), floor)
        stated = tof and meas.sigma_at_1m_m is not None
        ratio = fit.residual_rms_m / expected_m if expected_m > 0 else math.nan
        notes: tuple[str, ...] = ()
        if stated and ratio > 1.0:
            notes = (f"residuals {ratio:.3g} x what the sensor model expects: the intervals follow the observed "
                     "scatter (sandwich covariance)",)
        resid = fit.resid if fit.resid is not None else np.zeros(fit.inliers.size, np.float32)
        return Floors(floor, expected_m, stated, meas.multipath_m if tof else 0.0,
                      points.dm if tof else points.p[2], resid, notes)   # a ToF camera quantises the range


    def response(self, fit: SpaceFit, points: Points, sample: Sample) -> Response:
        """The range ``t = -c/(n·r)`` along each ray ``r``, fitted with the noise law's weights: its Jacobian."""
        p = sample.p
        dm = np.linalg.norm(p, axis=0)
        r = p / dm
        n, c = np.asarray(fit.plane.normal, dtype=np.float64), fit.plane.offset_m
        nr = n @ r
        t = -c / nr
        jac = np.column_stack([c * (fit.e1 @ r) / (nr * nr), c * (fit.e2 @ r) / (nr * nr), -1.0 / nr])
        model = self.model
        if model.sigma is not None:
            w = 1.0 / np.square(model.sigma[sample.index].astype(np.float64))
        elif model.weighted:                                   # sigma ∝ t^e / sqrt|cos|
            w = np.abs(nr) / np.power(np.abs(t), 2.0 * model.exponent)
        else:
            w = np.ones(t.size)
        u, v = pixel_uv(points.masks, points.shape, sample.index)
        kind = "tof" if self.measurement.kind == "tof" else "range"
        return Response(fit.plane, fit.e1, fit.e2, jac, w, t, np.ones(t.size), u, v, kind)


def noise_exponent(settings: FullFrameSettings, measurement: MeasurementModel) -> float:
    """Exponent of the range in the noise law: the config's, else a ToF camera's stated one, else 1.5."""
    if settings.noise_distance_exponent is not None:
        return settings.noise_distance_exponent
    if measurement.kind == "tof" and measurement.sigma_at_1m_m is not None:
        return measurement.distance_exponent
    return DEFAULT_NOISE_EXPONENT


# ---------------------------------------------------------------------- the robust start
def robust_start(p: F32, dm: F32, model: Model, settings: FullFrameSettings,
                 expected: ExpectedPlane | None = None) -> tuple[FloatArray, float]:
    """The start plane: the triplet plane with the smallest ``hypothesis_quantile`` of residuals.

    Residuals are orthogonal distances over ``range^e`` (weighted), over the given sigmas,
    or plain (unweighted). With ``expected``, only triplet planes within its tolerances
    compete. Returns the unit normal (toward the camera) and the offset.

    Raises:
        CalibrationQualityError: ``expected_plane``, when no triplet plane lies within the
            expected plane's tolerances (the message names the nearest one).
    """
    idx = fixed_subsample(p.shape[1], settings.sample_points)
    sub = p[:, idx].T.astype(np.float64)
    if model.sigma is not None:
        inv_norm = 1.0 / model.sigma[idx].astype(np.float64)
    elif model.weighted:
        inv_norm = dm[idx].astype(np.float64) ** -model.exponent
    else:
        inv_norm = np.ones(idx.size)
    spread = np.linalg.eigvalsh(np.cov(sub.T)) if sub.shape[0] > 3 else np.zeros(3)
    if not spread[1] > LINE_RATIO * spread[2]:
        raise CalibrationError(f"full-frame fit: the {p.shape[1]} valid points lie along a line (one image row "
                               "or column?); no plane is defined")
    if expected is None:
        nrm, off = _triplet_planes(sub, settings.hypotheses, settings.seed)
    else:                                                 # only planes near the expected one compete
        nrm, off = _triplet_planes(sub, EXPECTED_DRAWS * settings.hypotheses, settings.seed)
        ok, score = expected.within(nrm, off)[:2]
        if not ok.any():
            raise _nearest_refusal(expected, nrm, off, score)
        nrm, off = nrm[ok], off[ok]
    m = idx.size
    h = min(max(int(settings.hypothesis_quantile * m), 3), m)
    res = np.matmul(nrm.astype(np.float32), sub.T.astype(np.float32),   # kept: no fresh pages at every fit
                    out=kept_array("start_res", nrm.shape[0] * m, np.float32).reshape(nrm.shape[0], m))
    res += off.astype(np.float32)[:, None]
    np.abs(res, out=res)
    res *= inv_norm.astype(np.float32)[None, :]           # (hypotheses, points), rows contiguous
    k = _best_quantile(res, h)
    n, d = nrm[k], float(off[k])
    if d < 0 or (d == 0 and n[2] > 0):                   # normal toward the camera
        n, d = -n, -d
    return np.asarray(n, dtype=np.float64), d


def _triplet_planes(sub: FloatArray, count: int, seed: int | None) -> tuple[FloatArray, FloatArray]:
    """Unit normals (K, 3) and offsets (K,) of planes through random triplets of ``sub`` (m, 3)."""
    rng = np.random.default_rng(FIXED_SEED if seed is None else seed)
    idx = rng.integers(0, sub.shape[0], size=(3, count))
    a = sub[idx[0]]
    u = sub[idx[1]] - a
    v = sub[idx[2]] - a
    nrm = np.cross(u, v)
    length = np.sqrt(np.einsum("ij,ij->i", nrm, nrm))
    ok = length > 1e-9 * np.einsum("ij,ij->i", u, u)    # drop (nearly) collinear triplets
    if not ok.any():
        raise CalibrationError("full-frame fit: the points are collinear or coincident; no plane is defined")
    nrm = nrm[ok] / length[ok, None]
    return nrm, -np.einsum("ij,ij->i", nrm, a[ok])


def _nearest_refusal(expected: ExpectedPlane, nrm: FloatArray, off: FloatArray, score: FloatArray
                     ) -> CalibrationQualityError:
    """``expected_plane`` failed before the fit: no hypothesis within the tolerances; say what was nearest."""
    k = int(np.argmin(score))
    near = Plane(nrm[k], float(off[k])).oriented_toward_origin()
    angle, doff = expected.departure(near)
    a, tol_a = quantity_pair(angle, expected.angle_tolerance_rad, "rad")
    o, tol_o = quantity_pair(doff, expected.offset_tolerance_m, "m", digits=4)
    return CalibrationQualityError(
        "expected_plane", angle, expected.angle_tolerance_rad,
        f"no plane within {tol_a} and {tol_o} of the expected one among {nrm.shape[0]} candidate planes; "
        f"the nearest is {a} and {o} from it (tilt x "
        f"{math.degrees(near.tilt_about_x_rad()):.3g} deg, tilt y {math.degrees(near.tilt_about_y_rad()):.3g} deg, "
        f"{near.offset_m * 1000:.4g} mm from the camera)", unit="rad")


def _best_quantile(res: F32, h: int) -> int:
    """Index of the row of ``res`` with the smallest ``h``-th smallest value (first on ties).

    The same answer as partitioning every row, with far fewer rows ordered: a row whose
    ``h``-th value could be at most that of a good row has at least ``h`` values ``<=`` it;
    only those rows are ordered (exactly). The good row is the best by the same quantile
    on every 8th column (a cheap guess; any row keeps the answer exact). Rows are sorted,
    not partitioned: a noise-free plane gives rows of many equal residuals (zeros), where
    numpy's introselect degrades (2.9 ms instead of 0.5 ms for 96 x 1024). When the guess's
    quantile is 0, the least a row of absolute residuals can have, every such row ties at 0 and
    the first wins, unsorted (a noise-free plane: 73 of 96 rows, 0.7 ms of sorting).
    """
    guess_cols = res[:, ::8]
    g = min(max(h // 8, 1), guess_cols.shape[1]) - 1
    guess = int(np.argmin(np.sort(guess_cols, axis=1)[:, g]))
    q0 = np.sort(res[guess])[h - 1]                       # the guess's exact quantile
    cand = np.flatnonzero(np.count_nonzero(res <= q0, axis=1) >= h)   # rows whose quantile is <= q0
    if q0 == 0:                                           # residuals are >= 0: these all tie at 0
        return int(cand[0])
    score = np.full(res.shape[0], np.inf, dtype=np.float32)
    score[cand] = np.sort(res[cand], axis=1)[:, h - 1]
    return int(np.argmin(score))                          # rows left out have a larger quantile


# ---------------------------------------------------------------------- mixed pixels at depth edges
def _open(mask: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """3x3 opening: solid patches stay, isolated pixels and thin lines go."""
    return np.asarray(cv2.morphologyEx(mask, cv2.MORPH_OPEN, _K3), dtype=np.uint8)


def _near(patches: NDArray[np.uint8], reach: int) -> NDArray[np.uint8]:
    """1 where a patch pixel lies within ``reach`` pixels (chessboard distance), else 0.

    The same as ``_distance(patches) <= reach``, by a dilation with a square (separable,
    several times faster than the distance transform).
    """
    kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * reach + 1, 2 * reach + 1))
    return np.asarray(cv2.dilate(patches, kernel), dtype=np.uint8)


def _distance(patches: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """Chessboard distance (pixels, saturating at 255) of every pixel to the nearest patch pixel."""
    if not patches.any():
        return np.full(patches.shape, 255, np.uint8)
    out = cv2.distanceTransform(np.uint8(1) - patches, cv2.DIST_C, 3, dstType=cv2.CV_8U)
    return np.asarray(out, dtype=np.uint8)


def _ring_sums(ring: NDArray[np.uint8], inliers: BoolArray, z: F32, n_bins: int
               ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Sum of ``z`` and count of the inliers in each ring (bin 0: every other point).

    In blocks of ``CHUNK`` points: the bin index array ``bincount`` wants (intp: other
    index types are cast on every call, 3x slower with weights) and its float64 copy of
    the weights then stay block-sized (16 B per point less at the peak of the fit) and in cache.
    """
    sums = np.zeros(n_bins)
    counts = np.zeros(n_bins)
    for s in range(0, ring.size, CHUNK):
        k = min(CHUNK, ring.size - s)                            # kept blocks: no fresh pages at every fit
        bins = kept_array("ring_bins", k, np.intp)
        bins[...] = np.multiply(ring[s:s + CHUNK], inliers[s:s + CHUNK], dtype=np.uint8)   # 2x a mixed-type ufunc
        weights = kept_array("ring_z", k, np.float64)             # bincount's float64 copy of the weights
        np.copyto(weights, z[s:s + CHUNK])
        sums += np.bincount(bins, weights=weights, minlength=n_bins)
        counts += np.bincount(bins, minlength=n_bins)
    return sums, counts


class EdgeClean:
    """``(inliers, z) -> keep``: drops inliers near solid patches of outliers or invalid pixels.

    Per frame (pooled order of points), outliers and invalid pixels are opened with a
    3x3 square (isolated ones go: noise tails and random flying pixels do not mark an
    edge). Every inlier within ``floor_px`` of a patch is dropped. Around the outlier
    patches, bands of ``floor_px`` rings beyond the floor (pooled over the frames) are
    dropped while the sum of their normalised residuals exceeds ``ring_sigma`` standard
    errors: the data say how far the mixing reaches, which scales with the resolution
    (the optics' spill is an angle) and with the height of the jump over the noise.

    Args:
        masks: Per frame, the flat (H*W,) mask of the pixels that became points.
        shape: ``(H, W)``.
        floor_px: Rings always dropped.
        max_px: Farthest ring examined.
        ring_sigma: Significance of a biased ring, standard errors.
        scale: Robust scale of the normalised residuals (z / scale is standard normal).
        region: Flat (H*W,) region of interest; pixels outside it are neither invalid nor
            outliers (its border is not a depth edge). None: the whole image.
    """

    def __init__(self, masks: list[BoolArray], shape: tuple[int, int], floor_px: int, max_px: int,
                 ring_sigma: float, scale: float = 1.0, region: BoolArray | None = None) -> None:
        self.masks = masks
        self.shape = shape
        self.floor_px = floor_px
        self.max_px = min(max(max_px, floor_px), 250)
        self.ring_sigma = ring_sigma
        self.scale = scale
        self.report = EdgeReport(floor_px=floor_px)
        self.invalid = [(~m if region is None else region & ~m).astype(np.uint8) for m in masks]

    def margin_keep(self) -> int:
        """How many points lie farther than ``floor_px`` from the solid patches of invalid pixels."""
        h, w = self.shape
        return sum(int(np.count_nonzero(_near(_open(inv.reshape(h, w)), self.floor_px).reshape(-1)[m] == 0))
                   for m, inv in zip(self.masks, self.invalid, strict=True))

    def __call__(self, inliers: BoolArray, z: F32) -> BoolArray:
        h, w = self.shape
        cap = self.max_px + 1                      # rings beyond max_px: the reference bin
        ring = np.empty(inliers.size, dtype=np.uint8)
        start = 0
        for m, invalid in zip(self.masks, self.invalid, strict=True):   # per frame, in image space
            k = int(np.count_nonzero(m))
            flat = np.zeros(h * w, dtype=np.uint8)
            flat[m] = ~inliers[start:start + k]    # boolean scatter: 4x faster than by index at 98 % valid
            outlier = flat.reshape(h, w)
            # ring = distance to the outlier patches (capped), 0 within the floor of any patch:
            # outliers and invalid pixels together there (a wall seen at grazing incidence is both)
            code = np.minimum(_distance(_open(outlier)), np.uint8(cap))
            far = np.subtract(np.uint8(1), _near(_open(outlier | invalid.reshape(h, w)), self.floor_px))
            code *= far                             # 0 within the floor (multiply: no boolean-mask pass)
            ring[start:start + k] = code.reshape(-1)[m]
            start += k
        sums, counts = _ring_sums(ring, inliers, z, cap + 1)
        sums[0] = counts[0] = 0.0
        margin = self._margin(sums, counts, float(np.count_nonzero(inliers)))
        keep: BoolArray = ring > margin
        self.report = EdgeReport(margin, self.floor_px, int(np.count_nonzero(inliers & ~keep)))
        return keep

    def _margin(self, sums: NDArray[np.float64], counts: NDArray[np.float64], n_total: float) -> int:
        """The outer edge of an unbroken run of biased bands of rings beyond the floor.

        Bands are ``floor_px`` rings wide (the mixing reaches farther in pixels at a higher
        resolution; a band holds enough pixels to show it). A band is biased when the sum
        of its residuals is significant (``ring_sigma`` standard errors) and large enough
        to move the fit by ``RELEVANT_PULL`` of its own standard error, both measured
        against the mean residual of the pixels beyond every band (contamination pulls the
        fit itself, which shifts every residual).
        """
        width = max(self.floor_px, 1)
        margin = self.floor_px
        n_ref, s_ref = float(counts[-1]), float(sums[-1])
        if n_ref < MIN_REFERENCE:                  # few pixels far from every patch: all of them
            n_ref, s_ref = float(counts.sum()), float(sums.sum())
        mean_ref = s_ref / max(n_ref, 1.0)         # residual level of the clean plane (the fit may be pulled)
        while margin + width <= self.max_px:
            band = slice(margin + 1, margin + width + 1)
            n = float(counts[band].sum())
            excess = abs(float(sums[band].sum()) - n * mean_ref)
            noise = math.sqrt(n * (1.0 + n / max(n_ref, 1.0)))
            if n < 1 or excess <= self.scale * max(self.ring_sigma * noise, RELEVANT_PULL * math.sqrt(n_total)):
                break
            margin += width
        return margin


# ---------------------------------------------------------------------- too few pixels left
def _nothing_left(n_ok: int, left: int, points: Points, min_valid: float, floor_px: int) -> CalibrationQualityError:
    """Gate ``valid_fraction``: too few pixels left after the edge clean-up (small and large frames alike)."""
    return CalibrationQualityError(
        "valid_fraction", left / max(points.n_pixels, 1), min_valid,
        f"{n_ok} {points.what}s, {left} left after the edge clean-up ({floor_px} px around invalid and off-plane "
        f"patches, edge_margin_deg, and mixed pixels at depth edges); a full-frame fit needs {MIN_POINTS}")


def _check_margin(edge: EdgeClean, points: Points, min_valid: float) -> None:
    """Few valid pixels: enough of them must lie farther than the edge margin from invalid patches."""
    if points.n > SMALL_FRAME_POINTS:
        return
    left = edge.margin_keep()
    if left < MIN_POINTS:
        raise _nothing_left(points.n, left, points, min_valid, edge.floor_px)

