"""What a camera's systematic depth error does to a full-frame fit: the allowance in the intervals, the budget.

A real depth camera errs systematically (issue #39): a stereo camera's ``f·B`` is off by a
percent, its disparities carry an offset and a smooth field over the image; a ToF camera's
ranges carry a scale, an offset and a field. No number of pixels averages such an error out.
The frame's :class:`~cellcal.devices.measurement.MeasurementModel` states how large it may be
(``allowance``: scale, offset, field at the image corner, 1-sigma); until ``cellcal depthcal``
has calibrated it, the intervals must carry it.

Each term is a per-point perturbation ``δm`` of what the camera measures (disparity, px, or
range, m). The fit is a (weighted) least-squares fit of the plane in that space, so its answer
moves by ``δθ = (JᵀWJ)⁻¹ JᵀW δm`` (``θ``: the plane's steps ``(d_e1, d_e2, d_offset)``, ``J``
the model's Jacobian at the fitted plane over the inliers, ``W`` the fit's weights) — exact to
first order and cheap on a strided sample of the inliers. The covariance gains
``Σ_terms δθ δθᵀ`` at each term's 1-sigma allowance. The field's shape is unknown before
``depthcal``: its prior is the sum of ``K = 6`` smooth shapes, each 1 at the image corner (a
radial bow, ``u²``, ``v²``, ``uv``, ``u``, ``v``), with independent coefficients of variance
``field² / K`` (so the field at the corner has the stated 1-sigma); each shape is its own term
``field:<shape>`` at ``field / sqrt(K)``. The sum is positive semi-definite by construction and
the same for every derived value (both tilts widen by the linear shapes) — ADR 0059, "Amended".

The same responses give the error budget: what a 1 % depth scale and a 1 mm depth offset do to
the plane's tilt and height. Points in the camera frame (OpenCV), metres. Rationale:
docs/adr/0059-systematic-allowance-and-error-budget.md.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cellcal.core.geometry.planes import Plane

FloatArray = NDArray[np.float64]

__all__ = ["FIELD_SHAPES", "FIELD_SHAPE_DEGREES", "ErrorBudget", "PlaneShift", "Response", "field_shapes", "pixel_uv",
           "systematic_budget"]

#: The smooth field shapes (each 1 at the image corner ``u = v = 1``); the field's prior is their sum with
#: independent coefficients of variance ``field² / K`` (``K`` shapes), each shape its own term ``field:<shape>``.
FIELD_SHAPES: tuple[str, ...] = ("radial bow", "u^2", "v^2", "uv", "u", "v")
#: The polynomial degree of each of :data:`FIELD_SHAPES` (a field of that order or higher spans it).
FIELD_SHAPE_DEGREES: tuple[int, ...] = (2, 2, 2, 2, 1, 1)
#: Depth scale of the budget (relative) and depth offset (m).
BUDGET_SCALE = 0.01
BUDGET_OFFSET_M = 0.001


def field_shapes(u: FloatArray, v: FloatArray) -> FloatArray:
    """(n, 6) the :data:`FIELD_SHAPES` at normalised pixel coordinates ``u``, ``v`` (1 at the corner)."""
    return np.stack([(u * u + v * v) / 2.0, u * u, v * v, u * v, u, v], axis=1)


def pixel_uv(masks: list[NDArray[np.bool_]], shape: tuple[int, int], index: NDArray[np.intp]
             ) -> tuple[FloatArray | None, FloatArray | None]:
    """Normalised pixel coordinates ``u = (col - cx) / (W/2)``, ``v = (row - cy) / (H/2)`` of pooled points.

    ``index``: the points' indices among the pooled points of the frames' ``masks``; the image
    centre stands for the principal point. ``(None, None)`` without an image (a raw cloud).
    """
    h, w = shape
    if not masks or h == 0 or w == 0:
        return None, None
    flat = np.flatnonzero(masks[0]) if len(masks) == 1 else np.concatenate([np.flatnonzero(m) for m in masks])
    pix = flat[index]
    rows, cols = np.divmod(pix, w)
    return (cols - (w - 1) / 2.0) / (w / 2.0), (rows - (h - 1) / 2.0) / (h / 2.0)


@dataclass(frozen=True)
class Response:
    """How the fitted plane answers a per-point perturbation of what the camera measures.

    Attributes:
        plane: The fitted plane (camera frame).
        e1, e2: The tangent basis of the steps (the fit's covariance basis).
        jac: (n, 3) d(measured)/d(step) at the fitted plane for a sample of the inliers.
        weights: (n,) the fit's weights (1 / sigma², or 1).
        measured: (n,) what the plane predicts there: disparity (px) or range (m).
        depth_offset: (n,) change of the measured value for +1 m of Z-depth (stereo) or range (ToF), per metre.
        u, v: (n,) normalised pixel coordinates (``(col - cx) / (W/2)``, image centre), or None (no image).
        kind: ``"stereo"`` (disparity) or ``"tof"`` / ``"range"`` (range along the rays).
    """

    plane: Plane
    e1: FloatArray
    e2: FloatArray
    jac: FloatArray
    weights: FloatArray
    measured: FloatArray
    depth_offset: FloatArray
    u: FloatArray | None
    v: FloatArray | None
    kind: str

    def shift(self, delta: FloatArray) -> FloatArray:
        """(k, 3) steps the fit takes for ``delta`` (n, k) per-point perturbations: ``(JᵀWJ)⁻¹ JᵀW δ``."""
        jw = self.jac * self.weights[:, None]
        h = jw.T @ self.jac
        try:
            out = np.asarray(np.linalg.solve(h, jw.T @ delta).T, dtype=np.float64)
        except np.linalg.LinAlgError:
            out = np.zeros((delta.shape[1], 3))
        return out


@dataclass(frozen=True)
class PlaneShift:
    """How far a systematic error moves the fitted plane (camera frame).

    Attributes:
        step: ``(d_e1, d_e2, d_offset)`` in the fit's basis (rad, rad, m).
        normal: Change of the unit normal (3,).
        offset_m: Change of the plane's offset, m.
        tilt_rad: Rotation of the normal, rad.
        tilt_x_rad, tilt_y_rad, height_m, angle_rad: Changes of the derived values.
    """

    step: FloatArray
    normal: FloatArray
    offset_m: float
    tilt_rad: float
    tilt_x_rad: float
    tilt_y_rad: float
    height_m: float
    angle_rad: float

    def to_dict(self) -> dict[str, Any]:
        """JSON form (radians and metres, the normal's change in the camera frame)."""
        return {"tilt_rad": self.tilt_rad, "tilt_x_rad": self.tilt_x_rad, "tilt_y_rad": self.tilt_y_rad,
                "height_m": _num(self.height_m), "angle_rad": self.angle_rad, "offset_m": self.offset_m,
                "normal_cam": [float(x) for x in self.normal]}


def _num(v: float) -> float | None:
    return v if math.isfinite(v) else None


_DERIVED: tuple[Callable[[Plane], float], ...] = (
    Plane.angle_to_optical_axis_rad, Plane.tilt_about_x_rad, Plane.tilt_about_y_rad,
    Plane.distance_along_optical_axis_m)


def _step_plane(n: FloatArray, e1: FloatArray, e2: FloatArray, offset: float, step: FloatArray
                ) -> tuple[FloatArray, float]:
    """``passes.step_plane`` (not imported: passes -> space -> this module would close a circle)."""
    n_new = n + step[0] * e1 + step[1] * e2
    return n_new / np.linalg.norm(n_new), offset + float(step[2])


def derived_jacobian(plane: Plane, e1: FloatArray, e2: FloatArray) -> FloatArray:
    """(4, 3) d(angle, tilt_x, tilt_y, height)/d(step) by central differences."""
    n0 = np.asarray(plane.normal, dtype=np.float64)
    h = np.array([1e-6, 1e-6, 1e-6 * max(abs(plane.offset_m), 1e-3)])
    out = np.zeros((4, 3))
    for k in range(3):
        vals = []
        for sgn in (1.0, -1.0):
            step = np.zeros(3)
            step[k] = sgn * h[k]
            n, c = _step_plane(n0, e1, e2, plane.offset_m, step)
            p = Plane(n, c)
            vals.append(np.array([f(p) for f in _DERIVED]))
        out[:, k] = (vals[0] - vals[1]) / (2.0 * h[k])
    return out


def _plane_shift(step: FloatArray, resp: Response, geo: FloatArray) -> PlaneShift:
    d = geo @ step
    normal = step[0] * resp.e1 + step[1] * resp.e2
    return PlaneShift(np.asarray(step, dtype=np.float64), normal, float(step[2]), float(np.linalg.norm(step[:2])),
                      float(d[1]), float(d[2]), float(d[3]), float(d[0]))


@dataclass(frozen=True)
class ErrorBudget:
    """What systematic depth errors do to one full-frame fit, and what its allowance added to the intervals.

    Attributes:
        kind: The measurement the perturbations are in (``stereo``: disparity; ``tof``/``range``: range).
        depth_scale: The plane's shift for depths 1 % long.
        depth_offset: The plane's shift for depths 1 mm long (stereo: Z-depth; ToF: range).
        allowance: The camera's systematic allowance ``(scale, offset, field)`` (relative; px or m; px or m).
        allowance_shifts: Per allowance term (``scale``, ``offset``, ``field:<shape>`` for each of
            :data:`FIELD_SHAPES`), its 1-sigma shift.
        field_shape: The field shape that moves the plane most in the fit's own sigmas (for reports;
            every shape is in the covariance), "" without an image.
        sigma_before: 1-sigma of (angle, tilt_x, tilt_y, height) without the allowance (rad, m).
        sigma_after: ... with it.
    """

    kind: str
    depth_scale: PlaneShift
    depth_offset: PlaneShift
    allowance: tuple[float, float, float] = (0.0, 0.0, 0.0)
    allowance_shifts: dict[str, PlaneShift] = field(default_factory=dict)
    field_shape: str = ""
    sigma_before: tuple[float, float, float, float] = (math.nan,) * 4
    sigma_after: tuple[float, float, float, float] = (math.nan,) * 4
    wiggle: tuple[float, float] = (0.0, 0.0)

    @property
    def covariance(self) -> FloatArray:
        """3x3 covariance of the steps the allowance adds (sum of the terms' outer products)."""
        out = np.zeros((3, 3))
        for s in self.allowance_shifts.values():
            out += np.outer(s.step, s.step)
        return out

    @property
    def widened(self) -> bool:
        """Whether the allowance added anything to the intervals."""
        return bool(self.allowance_shifts) and (any(a > 0 for a in self.allowance) or self.wiggle[0] > 0)

    def note(self) -> str:
        """One sentence for ``interval_notes``: the allowance and how much it widened tilt and height."""
        scale, offset, fld = self.allowance
        stereo = self.kind == "stereo"
        unit, k = ("px", 1.0) if stereo else ("mm", 1000.0)
        what = (f"f·B scale {scale * 100:.3g} %, disparity offset {offset:.3g} px" if stereo
                else f"range scale {scale * 100:.3g} %, offset {offset * 1000:.3g} mm")
        if fld > 0 and self.field_shape:
            what += (f", field {fld * k:.3g} {unit} at the image corner as {len(FIELD_SHAPES)} independent smooth "
                     f"shapes, largest here: {self.field_shape}")
        if self.wiggle[0] > 0:
            what += f", wiggle {self.wiggle[0] * 1000:.3g} mm with a {self.wiggle[1]:.3g} m period"
        b, a = self.sigma_before, self.sigma_after

        def ratio(i: int) -> str:
            return f"x{a[i] / b[i]:.3g}" if b[i] > 0 else "from 0"

        return (f"intervals carry the camera's uncorrected systematic allowance ({what}; 1-sigma, "
                f"until cellcal depthcal): tilt x {ratio(1)}, tilt y {ratio(2)}, height {ratio(3)} wider "
                f"(height 1-sigma {b[3] * 1000:.3g} -> {a[3] * 1000:.3g} mm, tilt "
                f"{math.degrees(max(b[1], b[2])):.3g} -> {math.degrees(max(a[1], a[2])):.3g} deg)")

    def to_dict(self) -> dict[str, Any]:
        """JSON form: radians and metres (the report shows mm and degrees)."""
        return {
            "kind": self.kind,
            "depth_scale_1pct": self.depth_scale.to_dict(),
            "depth_offset_1mm": self.depth_offset.to_dict(),
            "allowance": {"scale": self.allowance[0], "offset": self.allowance[1], "field": self.allowance[2],
                          "offset_unit": "px" if self.kind == "stereo" else "m",
                          "field_shape": self.field_shape or None,
                          "wiggle_m": self.wiggle[0], "wiggle_period_m": self.wiggle[1]},
            "allowance_shifts": {k: s.to_dict() for k, s in self.allowance_shifts.items()},
            "sigma_without_allowance": dict(zip(("angle_rad", "tilt_x_rad", "tilt_y_rad", "height_m"),
                                                map(_num, self.sigma_before), strict=True)),
            "sigma_with_allowance": dict(zip(("angle_rad", "tilt_x_rad", "tilt_y_rad", "height_m"),
                                             map(_num, self.sigma_after), strict=True)),
        }


def _sigmas(geo: FloatArray, cov: FloatArray) -> tuple[float, float, float, float]:
    var = np.einsum("ij,jk,ik->i", geo, cov, geo)
    s = np.sqrt(np.maximum(var, 0.0))
    return float(s[0]), float(s[1]), float(s[2]), float(s[3])


def systematic_budget(resp: Response, cov: FloatArray, allowance: tuple[float, float, float],
                      wiggle: tuple[float, float] = (0.0, 0.0)) -> ErrorBudget:
    """The budget of a fit (1 % depth scale, 1 mm depth offset) and its allowance's shifts.

    Args:
        resp: The fit's response (:class:`Response`).
        cov: The fit's covariance of the steps before the allowance (the field shape named is
            the one largest in its sigmas).
        allowance: ``(scale, offset, field)`` 1-sigma (relative; px or m; px or m at the corner).
        wiggle: ToF: ``(amplitude_m, period_m)`` of the wiggling allowance, taken as independent cos and
            sin terms of ``amplitude / sqrt(2)`` each (RMS amplitude ``amplitude``); ``(0, 0)``: none.
    """
    geo = derived_jacobian(resp.plane, resp.e1, resp.e2)
    stereo = resp.kind == "stereo"
    m = resp.measured
    # depths 1 % long: disparity d/1.01 (stereo) or range 1.01 t (ToF); 1 mm long: through depth_offset
    scale_delta = (1.0 / (1.0 + BUDGET_SCALE) - 1.0) * m if stereo else BUDGET_SCALE * m
    cols = [scale_delta, BUDGET_OFFSET_M * resp.depth_offset]
    s_all, o_all, f_all = allowance
    cols += [s_all * m, np.full_like(m, o_all)]
    shapes = None
    if f_all > 0 and resp.u is not None and resp.v is not None:
        shapes = field_shapes(resp.u, resp.v) * f_all
        cols += list(shapes.T)
    amp, period = wiggle
    wiggled = not stereo and amp > 0 and period > 0
    if wiggled:                               # range-periodic: cos and sin of 2π r / P (r: the range, m)
        phase = 2.0 * math.pi * m / period
        cols += [amp / math.sqrt(2.0) * np.cos(phase), amp / math.sqrt(2.0) * np.sin(phase)]
    steps = resp.shift(np.stack(cols, axis=1))
    shifts = {"scale": _plane_shift(steps[2], resp, geo), "offset": _plane_shift(steps[3], resp, geo)}
    if wiggled:
        shifts["wiggle:cos"] = _plane_shift(steps[-2], resp, geo)
        shifts["wiggle:sin"] = _plane_shift(steps[-1], resp, geo)
    worst = ""
    if shapes is not None:                    # the field: K independent shapes at field / sqrt(K) each
        fsteps = steps[4:4 + len(FIELD_SHAPES)] / math.sqrt(len(FIELD_SHAPES))
        try:
            whiten = np.linalg.pinv(cov)
        except np.linalg.LinAlgError:
            whiten = np.eye(3)
        size = np.einsum("ki,ij,kj->k", fsteps, whiten, fsteps)
        worst = FIELD_SHAPES[int(np.argmax(size))]
        for name, fstep in zip(FIELD_SHAPES, fsteps, strict=True):
            shifts[f"field:{name}"] = _plane_shift(fstep, resp, geo)
    shifts = {k: s for k, s in shifts.items() if np.any(s.step != 0.0)}
    add = np.zeros((3, 3))
    for s in shifts.values():
        add += np.outer(s.step, s.step)
    return ErrorBudget(resp.kind, _plane_shift(steps[0], resp, geo), _plane_shift(steps[1], resp, geo),
                       (float(s_all), float(o_all), float(f_all)), shifts, worst,
                       _sigmas(geo, cov), _sigmas(geo, cov + add),
                       (float(amp), float(period)) if wiggled else (0.0, 0.0))
