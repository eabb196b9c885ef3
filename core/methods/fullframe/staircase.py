"""The flatness gate in sensor terms: a staircase of quantised depth, a bend within the camera's allowance.

A local plane that departs from the global fit is not always a surface that is not flat
(``../shared/spec/sensors.md``, systematic error; ADR 0060):

* a **staircase**: integer (or coarse subpixel) disparity on a nearly fronto-parallel plane
  leaves terraces one quantisation level ``q(Z)`` tall along iso-disparity lines; a local plane
  over a few of them departs by up to a level without any bow. Recognised when the measured
  disparities sit on the lattice of steps, the rounding is not dithered away by the noise and
  the worst cell spans few levels; up to one level is then not held against the plane;
* a **bend**: a smooth low-order field over the image (a stereo disparity offset field, a ToF
  range field), accepted up to the camera's systematic field allowance
  (``MeasurementModel.allowance[2]``: px at the image corner for stereo, metres for ToF),
  refused as a bend beyond it;
* anything else (a box, a step, a bump) stays what the local planes measured.

The judgement reruns the local planes on the residuals with the bend (whole, or clipped to the
allowance) taken out; every number it states is in metres at the plane's depth.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cellcal.devices.measurement import MeasurementModel
from cellcal.devices.systematic import field_basis

FloatArray = NDArray[np.float64]
F32 = NDArray[np.float32]

__all__ = ["BEND_ORDER", "Bend", "Staircase", "Verdict", "bend_of", "judge", "lattice_share", "staircase_of"]

#: Order of the smooth field a bend is fitted with (monomials of the normalised pixel coordinates).
BEND_ORDER = 3
#: Share of the inliers whose measured disparity must sit on the lattice of steps for a staircase.
LATTICE_SHARE = 0.8
#: A disparity sits on the lattice when within this share of a step of a multiple of it.
LATTICE_TOLERANCE = 0.05
#: Points (strided) the lattice and the bend's coefficients are read from.
SAMPLE_POINTS = 4096
#: How far (relative) the lattice's pitch may be from the stated ``f·B`` and step.
LATTICE_PITCH_SPREAD = 0.05
#: The rounding makes terraces while the noise before it is at most this share of a step (beyond it the
#: rounding is dithered: its pattern's first harmonic is damped below ``exp(-2π² 0.35²)`` = 9 %).
MAX_DITHER = 0.35
#: A cell spanning at most this many levels is "nearly fronto-parallel": its local plane rests on terraces.
MAX_LEVELS_PER_CELL = 4.0


@dataclass(frozen=True)
class Staircase:
    """Terraces of quantised depth.

    Attributes:
        recognised: The inliers' disparities sit on the lattice, undithered, few levels per cell.
        step_m: One level ``q(Z)`` at the plane's median depth, metres.
        levels_per_cell: The largest span of the predicted disparity over a cell, in steps.
        subpixel_bits: The camera's fractional bits (0: integer disparity).
    """

    recognised: bool
    step_m: float
    levels_per_cell: float
    subpixel_bits: int


@dataclass(frozen=True)
class Bend:
    """A smooth low-order field over the image, its affine part (what a plane absorbs) taken out.

    Attributes:
        field: (N,) the field at each inlier, in the camera's native unit (px or m).
        size_m: Its largest magnitude, metres of depth at that pixel's depth.
        allowance_m: The camera's field allowance at the same pixel, metres of depth.
        where: The image region of the largest magnitude ("the left edge (columns 0-80)").
    """

    field: FloatArray
    size_m: float
    allowance_m: float
    where: str

    @property
    def within(self) -> bool:
        """Whether the bend is within the camera's field allowance."""
        return self.size_m <= self.allowance_m


@dataclass(frozen=True)
class Verdict:
    """What the flatness gate says in sensor terms.

    Attributes:
        excess_m: The departure the sensor does not explain, metres (the gate's value).
        where: What and where, for the refusal's message ("" when nothing is left).
        notes: Sentences for the result's notes when an allowance was used.
        kind: ``"local"``, ``"bend"``, ``"staircase"`` or ``""`` (explained).
    """

    excess_m: float
    where: str
    notes: tuple[str, ...]
    kind: str


def _mm(x: float) -> str:
    return f"{x * 1000:.3g} mm"


def staircase_of(d_meas: FloatArray, d_hat: FloatArray, cell: NDArray[np.intp], z_m: float,
                 model: MeasurementModel, sigma_px: float) -> Staircase:
    """Whether measured disparities ``d_meas`` (px) form terraces around the plane's ``d_hat`` (px).

    Args:
        d_meas, d_hat: Measured and predicted disparity of each inlier, px.
        cell: Each inlier's flatness cell.
        z_m: The plane's median depth, metres.
        model: A stereo or structured-light model.
        sigma_px: The disparity noise before rounding (stated, or estimated), px.
    """
    step = model.disparity_step_px
    step_m = float(model.depth_step_m(z_m))
    on = lattice_share(d_meas / step)
    span = 0.0
    if cell.size:
        order = np.argsort(cell, kind="stable")
        c, dh = cell[order], d_hat[order]
        starts = np.flatnonzero(np.r_[True, c[1:] != c[:-1]])
        span = float(np.max(np.maximum.reduceat(dh, starts) - np.minimum.reduceat(dh, starts))) / step
    ok = on >= LATTICE_SHARE and sigma_px <= MAX_DITHER * step and span <= MAX_LEVELS_PER_CELL
    return Staircase(ok, step_m, span, model.subpixel_bits)


def lattice_share(k: FloatArray, spread: float = LATTICE_PITCH_SPREAD) -> float:
    """The largest share of values ``k`` (in nominal steps) on a lattice of pitch within ``1 ± spread`` of one step.

    A camera's stated ``f·B`` is known to a per cent or two (the real OAK frames' lattices read
    29.7-30.3 px·m against a nominal 30): the pitch is searched for, on a strided sample.
    """
    if k.size == 0:
        return 0.0
    sample = k[:: max(1, 2 * k.size // SAMPLE_POINTS)]
    x = np.linspace(1.0 - spread, 1.0 + spread, 201)[:, None] * sample[None, :]   # (pitches, points)
    x -= np.round(x)
    on = np.count_nonzero(np.abs(x) <= LATTICE_TOLERANCE, axis=1)
    return float(on.max()) / sample.size


def _region(u: FloatArray, v: FloatArray, cols: NDArray[np.intp], rows: NDArray[np.intp], field: FloatArray,
            k: int) -> str:
    """The image region around the largest ``|field|`` (at point ``k``), with its columns or rows."""
    uk, vk = float(u[k]), float(v[k])
    sign = math.copysign(1.0, float(field[k]))
    near = sign * field >= 0.5 * abs(float(field[k]))          # where the bend is at least half its worst ...
    if abs(uk) >= 0.5:
        near &= np.sign(u) == math.copysign(1.0, uk)            # ... on the same side of the image
    if abs(vk) >= 0.5:
        near &= np.sign(v) == math.copysign(1.0, vk)
    horiz = "left" if uk < 0 else "right"
    vert = "top" if vk < 0 else "bottom"
    if abs(uk) >= 0.5 and abs(vk) >= 0.5:
        return (f"the {vert}-{horiz} corner (columns {int(cols[near].min())}-{int(cols[near].max())}, "
                f"rows {int(rows[near].min())}-{int(rows[near].max())})")
    if abs(uk) >= 0.5 and abs(uk) >= abs(vk):
        return f"the {horiz} edge (columns {int(cols[near].min())}-{int(cols[near].max())})"
    if abs(vk) >= 0.5:
        return f"the {vert} edge (rows {int(rows[near].min())}-{int(rows[near].max())})"
    return (f"the image centre (columns {int(cols[near].min())}-{int(cols[near].max())}, "
            f"rows {int(rows[near].min())}-{int(rows[near].max())})")


def bend_of(resid: FloatArray, u: FloatArray, v: FloatArray, cols: NDArray[np.intp], rows: NDArray[np.intp],
            to_m: FloatArray, allowance: float) -> Bend:
    """The smooth field of order :data:`BEND_ORDER` in the native residuals ``resid``, less its affine part.

    Args:
        resid: (N,) native residuals of the inliers (disparity px, or range m).
        u, v: Their normalised pixel coordinates (``devices.systematic.normalised_pixels``).
        cols, rows: Their pixel columns and rows (for the message).
        to_m: (N,) metres of depth per native unit at each inlier (``Z²/(f·B)``, or 1).
        allowance: The camera's field allowance at the image corner, native unit.
    """
    s = slice(None, None, max(1, u.size // SAMPLE_POINTS))     # coefficients from a strided sample
    xs = np.column_stack([np.ones(u[s].size), field_basis(u[s], v[s], BEND_ORDER)])
    coef = _solve(xs, resid[s])
    high_s = xs[:, 3:] @ coef[3:]                               # the terms a plane does not absorb ...
    aff = _solve(xs[:, :3], high_s)                             # ... less their affine part
    coef[:3] = -aff
    field = np.full(u.size, coef[0])                            # at every point: the monomials by products
    field += coef[1] * u + coef[2] * v
    k = 3
    for deg in range(2, BEND_ORDER + 1):
        for j in range(deg + 1):
            field += coef[k] * (u ** (deg - j)) * (v ** j)
            k += 1
    k = int(np.argmax(np.abs(field) * to_m))
    return Bend(field, float(abs(field[k]) * to_m[k]), float(allowance * to_m[k]),
                _region(u[s], v[s], cols[s], rows[s], field[s], int(np.argmax(np.abs(field[s]) * to_m[s]))))


def _solve(x: FloatArray, y: FloatArray) -> FloatArray:
    """Least squares by the normal equations (a few columns, well scaled: |u|, |v| <= 1)."""
    out: FloatArray = np.asarray(np.linalg.solve(x.T @ x, x.T @ y), dtype=np.float64)
    return out


def judge(excess_m: float, where: str, tolerance_m: float, stair: Staircase | None, bend: Bend | None,
          local: Callable[[FloatArray], float]) -> Verdict:
    """The gate's verdict on a departure ``excess_m`` (the local planes' own) in sensor terms.

    Args:
        excess_m, where: What the local planes measured, and where (as the gate says today).
        tolerance_m: ``flatness_tolerance_m``.
        stair: The staircase (None: a camera without disparity levels).
        bend: The bend (None: not judged).
        local: The local planes' excess with a native field (N,) taken out of the residuals, metres.
    """
    if bend is None or excess_m <= tolerance_m:
        return Verdict(excess_m, where, (), "local" if excess_m > 0 else "")
    terraces = stair is not None and stair.recognised
    level = stair.step_m if (terraces and stair is not None) else 0.0
    full = max(local(bend.field) - level, 0.0)                  # all of the bend and a level taken out
    if full > tolerance_m:
        return Verdict(excess_m, where, (), "local")            # a box, a step, a bump: as today
    clip = min(1.0, bend.allowance_m / bend.size_m) if bend.size_m > 0 else 1.0
    allowed = max(local(bend.field * clip) - level, 0.0)        # the bend up to the allowance taken out
    bend_text = (f"a bend of {_mm(bend.size_m)} at {bend.where}, "
                 f"{'within' if bend.within else 'beyond'} the camera's {_mm(bend.allowance_m)} field allowance")
    if allowed > tolerance_m and not bend.within:
        return Verdict(allowed, bend_text, (), "bend")
    if terraces and stair is not None:
        disparity = "integer disparity" if stair.subpixel_bits == 0 else f"{stair.subpixel_bits}-bit subpixel disparity"
        what = (f"a staircase of {_mm(stair.step_m)} terraces (one disparity level) — {disparity} on a nearly "
                f"fronto-parallel plane")
        if stair.step_m > tolerance_m:                          # a level the tolerance cannot see through
            advice = "enable subpixel" if stair.subpixel_bits == 0 else "more subpixel bits"
            extra = f"; besides, {bend_text}" if not bend.within else ""
            return Verdict(excess_m, f"{what}: {advice}, or a flatness tolerance of at least one level{extra}",
                           (), "staircase")
        notes = [f"flatness: {what} recognised; up to one level not held against the plane"]
    else:
        notes = []
    if bend.size_m > 0 and local(bend.field * 0.0) - level > tolerance_m:   # the bend was needed
        notes.append(f"flatness accepted {bend_text}")
    return Verdict(allowed, "", tuple(notes), "")
