"""Honest both ways: a fit on one quantisation level, the quantisation floor, correlated residuals.

A residual far below what the sensor can deliver is not a good fit but a fit that sat on
one depth level of quantised data (integer-disparity stereo: levels 16 mm apart at 0.7 m);
intervals must never be narrower than quantisation and spatially correlated error allow.
Points are in the camera frame (OpenCV), metres. Rationale: docs/adr/0028-honest-full-frame-fit.md.
"""

from __future__ import annotations

import dataclasses
import math
import threading
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cellcal.core.methods.fullframe.flatness import Flatness
from cellcal.core.methods.fullframe.points import ExpectedPlane, Points, Sample
from cellcal.core.methods.fullframe.result import IntervalFactors
from cellcal.core.methods.fullframe.space import MeasurementSpace, SpaceFit
from cellcal.core.methods.fullframe.systematic import systematic_budget
from cellcal.devices.measurement import UNKNOWN_MODEL, MeasurementModel

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
F32 = NDArray[np.float32]

__all__ = ["Honest", "allow_rounding", "design_effect", "disparity_lattice", "honest_intervals", "lock_on",
           "quantisation_floor", "rounding_allowance_m"]

#: Inlier depths taking at most this many distinct values sit on quantisation levels.
MAX_LEVELS = 2
#: Share of inliers with a zero residual (|r| <= ZERO_M) that means the same.
ZERO_SHARE = 0.5
#: A residual this small (m) is zero to float precision of a depth in metres.
ZERO_M = 1e-12
#: A level holding at least this share of the valid pixels is populated.
LEVEL_SHARE = 0.005
#: ... and at least this many pixels.
MIN_LEVEL_PIXELS = 16
#: Blocks across the image's longer side for the spatial design effect.
BLOCKS_ACROSS = 32
#: The design effect is applied when it exceeds 1 by this many of its standard errors under independence.
DEFF_SIGNIFICANCE = 3.0

_BUFFERS = threading.local()


def _image_buffer(n: int) -> F32:
    """A float32 image-sized buffer reused by this thread's fits (a fresh one per fit costs page faults, ADR 0007)."""
    buf: F32 | None = getattr(_BUFFERS, "image", None)
    if buf is None or buf.size < n:
        buf = np.empty(n, dtype=np.float32)
        _BUFFERS.image = buf
    return buf[:n]


def _other_levels(levels: NDArray[np.floating[Any]], valid_depth: F32) -> bool:
    """Whether other valid pixels also share depth values (populated levels beside ``levels``: quantised data).

    A noise-free exact plane seen head-on has one depth too, but then nothing else in the
    image is a level; if everything is one level, the plane's tilt is below what the
    data resolve and zero is the right answer within the quantisation.
    """
    values, counts = np.unique(valid_depth, return_counts=True)
    populated = (counts >= max(LEVEL_SHARE * valid_depth.size, MIN_LEVEL_PIXELS)) & ~np.isin(values, levels)
    return bool(populated.any())


def _few_levels(depth: F32) -> NDArray[np.floating[Any]] | None:
    """The distinct values of ``depth`` when there are at most ``MAX_LEVELS`` (two), else None (one pass, no sort)."""
    if depth.size == 0:
        return None
    first = depth[0]
    rest = depth[depth != first]
    if rest.size == 0:
        return np.sort(np.array([first]))
    if MAX_LEVELS >= 2 and bool(np.all(rest == rest[0])):
        return np.sort(np.array([first, rest[0]]))
    return None


def disparity_lattice(z_m: F32 | FloatArray, *, min_share: float = 0.002, min_levels: int = 4,
                      max_rms_step: float = 0.1) -> float | None:
    """``f·B / q`` (px·m per disparity step) of a depth image quantised on a disparity lattice, or None.

    A stereo camera's depths are ``Z = f·B / (k q)`` for integers ``k``: the populated depth
    values have ``1/Z`` on a lattice of pitch ``q / (f·B)``. The pitch is first guessed from the
    smallest gap between populated levels, then refined so that ``(f·B/q) / Z`` of every level is
    closest to an integer. Depths rounded to a millimetre (the OAK's output) still resolve it.

    Args:
        z_m: Z-depths, metres (any shape; non-finite and non-positive values ignored).
        min_share: A depth value is a populated level when it holds this share of the depths.
        min_levels: Fewer populated levels than this: no lattice can be told.
        max_rms_step: The levels must sit this close (RMS, in steps) to the lattice.

    Returns:
        ``f·B/q`` in px·m, or None when the depths show no lattice (a ToF camera, subpixel
        disparity finer than the depth unit, too few levels).
    """
    z = np.asarray(z_m, dtype=np.float64).ravel()
    z = z[np.isfinite(z) & (z > 0)]
    if z.size == 0:
        return None
    values, counts = np.unique(z, return_counts=True)
    levels = values[counts >= max(min_share * z.size, 16)]     # populated depth values
    if levels.size < min_levels:
        return None
    inv = np.sort(1.0 / levels)
    gap = float(np.min(np.diff(inv)))                            # adjacent populated levels: one step, at best
    if gap <= 0:
        return None
    candidates = np.linspace(0.8, 1.2, 4001) / gap               # f·B/q around the first guess, px·m
    k = candidates[:, None] * inv[None, :]                       # each level's disparity in steps
    cost = np.mean((k - np.round(k)) ** 2, axis=1)               # squared distance to the nearest integer
    best = int(np.argmin(cost))
    if cost[best] > max_rms_step**2:
        return None
    return float(candidates[best])


def lock_on(depth_in: F32, ortho_in: FloatArray, valid_depth: F32) -> str:
    """Why the fit sat on one quantisation level, or "" when it did not.

    Args:
        depth_in: Depths of (a strided sample of) the inliers, metres: Z-depth, or the
            range for a ToF camera (what the sensor quantises).
        ortho_in: Their orthogonal residuals to the fitted plane, metres (float64).
        valid_depth: Depths of every valid pixel in the region, metres.

    Returns:
        A short reason for messages ("" when the inliers are no lock-on).
    """
    levels = _few_levels(depth_in)
    if levels is None:                                    # many depths: a lock-on only if most residuals are 0 ...
        zero = np.abs(ortho_in) <= ZERO_M
        share = float(np.count_nonzero(zero)) / max(zero.size, 1)
        levels = _few_levels(depth_in[zero]) if share > ZERO_SHARE else None
        if levels is None:                                # ... on one or two levels
            return ""
        reason = f"{share:.0%} of its inliers have a zero residual"
    else:
        where = ", ".join(f"{v * 1000:.5g} mm" for v in levels)
        reason = f"its inliers' depths take {levels.size} distinct value(s) ({where})"
    if not _other_levels(levels, valid_depth):
        return ""                                         # one depth and no other level: nothing to judge by
    reason += ", and other valid pixels sit on depth levels of their own (quantised depth)"
    fb = disparity_lattice(valid_depth)                   # a stereo camera's levels tell its f·B/q
    if fb is not None:
        reason += (f"; the depths sit on a disparity lattice of f·B/q = {fb:.4g} px·m: a stereo camera — state "
                   "its model in [camera.model] (docs/real-sensors.md)")
    return reason


def design_effect(resid: F32, masks: list[BoolArray], shape: tuple[int, int]) -> tuple[float, float]:
    """Variance factor for residuals correlated across neighbouring pixels, and its standard error.

    The image is cut into square blocks; with independent residuals the squared sum over a
    block has the expectation of the sum of the squares, so ``sum_b (sum r)^2 / sum r^2``
    is 1, and > 1 when neighbouring residuals share an error (multipath, a warped surface).

    Args:
        resid: Per pooled point, its (whitened) residual, 0 off the inliers.
        masks: Per frame, the flat (H*W,) mask of the pixels that became points.
        shape: ``(H, W)``.

    Returns:
        ``(factor, se)``: the design effect and its standard error under independence
        (``sqrt(2 / blocks)``).
    """
    h, w = shape
    b = max(1, round(max(h, w) / BLOCKS_ACROSS))          # block side, px
    hb, wb = h // b, w // b                               # whole blocks (the last partial ones are left out)
    if hb == 0 or wb == 0:
        return 1.0, 0.0
    num = den = 0.0
    start = 0
    img = _image_buffer(h * w)
    for m in masks:                                       # per frame: scatter into the image, sum whole blocks
        k = int(np.count_nonzero(m))
        img.fill(0.0)
        img[m] = resid[start:start + k]
        start += k
        rows = img.reshape(h, w)[:hb * b].reshape(hb, b, w).sum(axis=1, dtype=np.float64)   # (hb, W) row blocks
        sums = rows[:, :wb * b].reshape(hb, wb, b).sum(axis=2)                              # (hb, wb) blocks
        num += float(np.sum(sums * sums))
        kept = img.reshape(h, w)[:hb * b, :wb * b]
        den += float(np.einsum("ij,ij->", kept, kept, dtype=np.float64))
    n_blocks = hb * wb * len(masks)
    if not den > 0:
        return 1.0, 0.0
    return num / den, math.sqrt(2.0 / n_blocks)


def quantisation_floor(cov: FloatArray, floor_m: float, uv: FloatArray, n_inliers: int) -> tuple[FloatArray, bool]:
    """The covariance of (d_e1, d_e2, d_offset) never below what the quantisation floor allows.

    The floor's covariance is that of a least-squares plane with independent orthogonal
    errors of ``floor_m`` on the inliers, ``floor² (XᵀX)⁻¹`` with ``X = [u, v, 1]`` (their
    in-plane coordinates along ``e1``, ``e2``): per tilt ``floor / (sqrt(N) L)`` with ``L``
    the RMS extent. The result is ``cov + (C_floor - cov)₊`` (the positive part), the
    smallest widening that is at least both.

    Args:
        cov: 3x3 covariance of the tangent steps and the offset (m², rad²).
        floor_m: RMS orthogonal quantisation floor per inlier, metres.
        uv: (2, n) in-plane coordinates of (a strided sample of) the inliers, metres.
        n_inliers: Number of inliers the sample stands for.

    Returns:
        The covariance and whether the floor widened it.
    """
    if not floor_m > 0 or uv.shape[1] < 3:
        return cov, False
    x = np.vstack([uv, np.ones(uv.shape[1])])             # (3, n): u, v, 1
    xtx = (x @ x.T) * (n_inliers / uv.shape[1])           # scaled to every inlier
    try:
        c_floor = floor_m * floor_m * np.linalg.inv(xtx)
    except np.linalg.LinAlgError:
        return cov, False
    vals, vecs = np.linalg.eigh(c_floor - cov)            # the part of the floor the covariance lacks ...
    plus = vals > 1e-6 * float(np.linalg.eigvalsh(c_floor).max())   # beyond rounding
    if not plus.any():
        return cov, False
    add = (vecs[:, plus] * vals[plus]) @ vecs[:, plus].T  # ... its positive part
    return cov + add, True


def rounding_allowance_m(floor_m: float, rms_m: float) -> float:
    """How far rounding alone can bend a local plane, metres: the flatness gate does not count it.

    Rounding to steps ``q`` leaves a sawtooth error; Gaussian noise of sigma ``s`` before the
    rounding (dither) damps its first harmonic, of amplitude ``q/pi``, by ``exp(-2 pi² s²/q²)``.
    Noisy ToF (3 mm on 1 mm steps) leaves nothing; integer-disparity stereo (0.1 px on 1 px
    steps) leaves nearly ``q/pi``, which bends a local plane over a few depth levels.

    Args:
        floor_m: RMS orthogonal quantisation floor ``q/sqrt(12)`` of the inliers, metres.
        rms_m: Their RMS orthogonal residual, metres (noise and rounding).
    """
    if not floor_m > 0:
        return 0.0
    q = math.sqrt(12.0) * floor_m                         # the step across the plane
    s = math.sqrt(max(rms_m * rms_m - floor_m * floor_m, 0.0))   # the noise before rounding (Sheppard)
    return q / math.pi * math.exp(-2.0 * math.pi ** 2 * (s / q) ** 2)


# ---------------------------------------------------------------------- the checks on a fit
@dataclass(frozen=True)
class Honest:
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
    noise_cov: FloatArray | None = None   # the steps' covariance before the systematic allowance (None: = total)


def honest_intervals(fit: SpaceFit, space: MeasurementSpace, points: Points, expected: ExpectedPlane | None
                     ) -> tuple[SpaceFit, Honest]:
    """The space's floors for the inliers, a lock-on, and the covariance widened where they say so.

    Covariance (d_e1, d_e2, d_offset): times the spatial design effect when significant (unless
    the space allowed for it in its own units), then never below the quantisation floor spread
    over the inliers' extent.
    """
    sample = Sample.of(points, fit.inliers)
    floors = space.floors(fit, points, sample)
    ortho = fit.plane.normal @ sample.p + fit.plane.offset_m   # orthogonal residuals of the sample, m
    locked = lock_on(np.take(floors.depth, sample.index), ortho, floors.depth)
    spatial = 1.0
    if floors.resid is not None:                               # significant correlation only
        deff, se = design_effect(floors.resid, points.masks, points.shape)
        spatial = deff if deff > 1.0 + DEFF_SIGNIFICANCE * se else 1.0
    uv = np.stack([fit.e1 @ sample.p, fit.e2 @ sample.p])     # in-plane coordinates, m
    cov, held = quantisation_floor(fit.cov * spatial, floors.floor_m, uv, int(np.count_nonzero(fit.inliers)))
    budget = systematic_budget(space.response(fit, points, sample), cov, points.measurement.allowance,
                               points.measurement.wiggle)
    noise_cov = cov
    if budget.widened:                                         # the camera's uncorrected systematic error (ADR 0059)
        cov = cov + budget.covariance
    ratio = fit.residual_rms_m / floors.expected_m if floors.expected_m > 0 else math.nan
    notes = [*fit.notes, *floors.notes]
    if spatial > 1.0:
        notes.append(f"intervals {math.sqrt(spatial):.3g} x wider for residuals correlated across neighbouring "
                     f"pixels (design effect {spatial:.3g})")
    if held:
        notes.append(f"intervals held at the quantisation floor ({floors.floor_m * 1000:.3g} mm RMS across the plane)")
    if budget.widened:
        notes.append(budget.note())
    honest = Honest(points.measurement, space.name, floors.expected_m, floors.floor_m, floors.stated,
                    floors.multipath_m, locked, IntervalFactors(ratio, spatial, held, budget), tuple(notes), expected,
                    points.n_pixels, noise_cov)
    return dataclasses.replace(fit, cov=cov, resid=None), honest   # the residuals' scratch goes before flatness


def allow_rounding(flat: Flatness, honest: Honest, rms_m: float) -> tuple[Flatness, Honest]:
    """The flatness value less what undithered rounding bends local planes by, and a note when it did."""
    bend = rounding_allowance_m(honest.floor_m, rms_m)
    if not (bend > 1e-5 and flat.excess_m > 0):
        return flat, honest
    left = max(flat.excess_m - bend, 0.0)
    note = f"flatness allows {bend * 1000:.3g} mm for the rounding's sawtooth (weakly dithered depth steps)"
    return Flatness(left, flat.where if left > 0 else ""), dataclasses.replace(honest, notes=(*honest.notes, note))
