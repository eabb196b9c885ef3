"""The calibrate report's charts as plain images (ADR 0037, ADR 0051): each pose's side view and gates, the
poses' tilt and height with the consensus, the cross-pose consistency.

Drawn with :class:`~cellcal.core.report.chart.Chart` in matplotlib's layout and house style:
units in every axis label, the pose and the camera in every title; failed gates red, hatched
and labelled FAILED. Each function takes report data and returns PNG bytes.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from cellcal.core.report.arrays import decode_array
from cellcal.core.report.canvas import DASHED, DOTTED, Canvas
from cellcal.core.report.capture import CLASS_INLIER, CLASS_MIXED, CLASS_NAMES, CLASS_OUTLIER
from cellcal.core.report.chart import Chart, subplot_rects
from cellcal.core.report.style import CLASS_COLORS, DPI, FAILED, PASSED, THRESHOLD, pose_title

__all__ = ["consistency_figure", "gate_rows", "num", "pose_estimates", "pose_fit_figure", "poses_figure",
           "weighted_consensus"]

#: Gate name -> (label, scale, unit, "min"/"max").
_GATES = {"valid_fraction": ("valid pixels", 100.0, "%", "min"),
          "residual_floor": ("RMS vs sensor floor", 1.0, "x", "min"),
          "inlier_fraction": ("plane inliers", 100.0, "%", "min"),
          "residual_rms_m": ("residual RMS", 1000.0, "mm", "max"),
          "expected_plane": ("off the expected plane", 180.0 / math.pi, "deg", "max"),
          "coverage": ("image coverage", 100.0, "%", "min"),
          "flatness": ("flatness", 1000.0, "mm", "max")}
#: Colour of a passed pose's estimate.
ESTIMATE = "#2166ac"


def num(value: Any) -> float:
    """``value`` as a float; None is NaN."""
    return math.nan if value is None else float(value)


def gate_rows(gates: Mapping[str, Any]) -> list[tuple[str, float, float, str, str, bool]]:
    """(label, value, threshold, unit, "min"/"max", passed) per gate, in display units."""
    rows = []
    for name, g in gates.items():
        label, k, unit, side = _GATES.get(name, (name, 1.0, "", "max"))
        value = g.get("value")
        threshold = g.get("threshold")
        rows.append((label, math.nan if value is None else value * k, math.nan if threshold is None else threshold * k,
                     unit, side, bool(g.get("passed"))))
    return rows


# ---------------------------------------------------------------------- one pose
def pose_fit_figure(pose: Mapping[str, Any], camera: str) -> bytes:
    """Side view of the cloud with the fitted plane, and the gates as value against threshold."""
    canvas = Canvas((13.0, 4.2), DPI)
    canvas.title(pose_title(pose, camera))
    _side_view(Chart(canvas, (0.06, 0.14, 0.38, 0.7)), pose["pictures"])
    _gates(Chart(canvas, (0.66, 0.14, 0.22, 0.7)), (pose.get("full_frame") or {}).get("gates") or {})
    return canvas.png()


def _side_view(chart: Chart, pics: Mapping[str, Any]) -> None:
    """The sampled cloud seen along the plane: position along it (mm) against height above it (mm)."""
    pts = decode_array(pics["points_mm"]).astype(np.float64)
    cls = decode_array(pics["point_classes"]) & 3
    normal = np.asarray(pics["plane_cam"]["normal"], dtype=np.float64)
    offset_mm = 1000.0 * float(pics["plane_cam"]["offset_m"])
    # an in-plane axis: the camera's y axis projected onto the plane (the side the camera looks down)
    e1 = np.array([0.0, 1.0, 0.0]) - normal * normal[1]
    e1 /= max(np.linalg.norm(e1), 1e-12)
    along = pts @ e1
    height = pts @ normal + offset_mm  # signed distance to the plane, mm (+ toward the camera)
    for c in (CLASS_INLIER, CLASS_MIXED, CLASS_OUTLIER):
        sel = cls == c
        if sel.any():
            chart.scatter(along[sel], height[sel], CLASS_COLORS[c], label=CLASS_NAMES[c])
    chart.hline(0.0, THRESHOLD, 1.2, label="fitted plane")
    chart.labels = ("side view of the cloud (sample) and the fitted plane", "along the plane (mm, camera y projected)",
                    "height above the plane (mm)")
    chart.legend()
    chart.grid_axes = "both"
    chart.render()


def _gates(chart: Chart, gates: Mapping[str, Any]) -> None:
    """Each gate's value over its threshold (linear axis, 1 = the threshold); failed ones in red and hatched."""
    rows = gate_rows(gates)
    if not rows:
        x0, y0, x1, y1 = chart.box
        chart.canvas.text(((x0 + x1) / 2, (y0 + y1) / 2), "no gates (no full-frame fit)", 10.0, anchor="mm")
        return
    ratios = []
    for _, value, threshold, _, _, _ in rows:
        r = value / threshold if threshold and math.isfinite(value) and math.isfinite(threshold) else math.nan
        ratios.append(r if math.isfinite(r) and r > 0 else 0.0)
    y = list(range(len(rows)))
    failed = [not ok for *_, ok in rows]
    chart.bars(y, ratios, [FAILED if bad else PASSED for bad in failed], horizontal=True, hatched=failed)
    chart.vline(1.0, THRESHOLD, 1.2, DASHED)
    chart.limits["x"] = (0.0, 1.6 * max(ratios) if max(ratios) > 0 else 1.6)
    chart.ticks("y", y, [f"{label} ({side} {threshold:.3g} {unit})" for label, _, threshold, unit, side, _ in rows],
                8.0)
    for yi, (_, value, _, unit, _, ok), r in zip(y, rows, ratios, strict=True):
        chart.text(r, yi, f"  {value:.3g} {unit}" + ("" if ok else "  FAILED"), 8.0, "#000000" if ok else FAILED,
                   bold=not ok)
    chart.inverted = True
    chart.labels = ("quality gates: value vs threshold", "value / threshold (1 = the threshold)", "")
    chart.render()


# ---------------------------------------------------------------------- across poses
def weighted_consensus(values: Sequence[float] | np.ndarray, sigmas: Sequence[float] | np.ndarray,
                       z: float = 1.959963984540054
                       ) -> tuple[float, float] | None:
    """Inverse-variance weighted mean of ``values`` and its 95 % half-width; None without usable sigmas."""
    v = np.asarray(values, dtype=np.float64)
    s = np.asarray(sigmas, dtype=np.float64)
    ok = np.isfinite(v) & np.isfinite(s) & (s > 0)
    if not ok.any():
        return None
    w = 1.0 / s[ok] ** 2
    return float(np.sum(w * v[ok]) / np.sum(w)), float(z / math.sqrt(np.sum(w)))


#: Per-pose quantity -> (its sigma and interval keys in a full-frame document, display scale).
_QUANTITIES = {"tilt_x_deg": ("tilt_x_sigma_deg", "tilt_x_ci_deg", 1.0),
               "tilt_y_deg": ("tilt_y_sigma_deg", "tilt_y_ci_deg", 1.0),
               "height_m": ("height_sigma_m", "height_ci_m", 1000.0)}


def pose_estimates(poses: Sequence[Mapping[str, Any]]) -> dict[str, list[Any]]:
    """Per pose with a full-frame fit: label, failed, and per quantity value, interval, sigma, expected (deg, mm)."""
    out: dict[str, list[Any]] = {"label": [], "failed": []}
    for key in _QUANTITIES:
        for suffix in ("", ":ci", ":sigma", ":expected"):
            out[key + suffix] = []
    for pose in poses:
        ff = pose.get("full_frame")
        if not ff:
            continue
        out["label"].append(f"pose {int(pose['index']) + 1}")
        out["failed"].append(bool(pose.get("failed")))
        exp = pose.get("expected") or {}
        for key, (sigma_key, ci_key, k) in _QUANTITIES.items():
            ci = ff.get(ci_key) or [None, None]
            out[key].append(num(ff.get(key)) * k)
            out[key + ":ci"].append([num(ci[0]) * k, num(ci[1]) * k])
            out[key + ":sigma"].append(num(ff.get(sigma_key)) * k)
            out[key + ":expected"].append(num(exp.get(key)) * k)
    return out


def poses_figure(poses: Sequence[Mapping[str, Any]], camera: str) -> bytes:
    """Tilt x, tilt y and height per pose with 95 % intervals, the expected values and the consensus.

    With expected values (a ``[reference]``) each is drawn as measured minus expected, so poses
    at different heights share one axis.
    """
    est = pose_estimates(poses)
    canvas = Canvas((13.5, 4.0), DPI)
    canvas.title(f"tilt and height per pose with 95 % intervals, camera {camera}")
    rects = subplot_rects(3, 0.07, 0.98, 0.16, 0.82, 0.35)
    for rect, key, name, unit in zip(rects, ("tilt_x_deg", "tilt_y_deg", "height_m"), ("tilt x", "tilt y", "height"),
                                     ("deg", "deg", "mm"), strict=True):
        _quantity(Chart(canvas, rect), est, key, name, unit)
    return canvas.png()


def _quantity(chart: Chart, est: Mapping[str, list[Any]], key: str, name: str, unit: str) -> None:
    """One quantity per pose: estimates with intervals (failed poses red), the consensus band, the expected zero."""
    value = np.asarray(est[key], dtype=np.float64)
    ci = np.asarray(est[key + ":ci"], dtype=np.float64).reshape(-1, 2)
    expected = np.asarray(est[key + ":expected"], dtype=np.float64)
    relative = bool(expected.size) and bool(np.all(np.isfinite(expected)))
    ref = expected if relative else np.zeros_like(value)
    y = value - ref
    for xi, (yi, lo, hi, failed) in enumerate(zip(y, ci[:, 0] - ref, ci[:, 1] - ref, est["failed"], strict=True)):
        chart.errorbar(xi, yi, lo, hi, FAILED if failed else ESTIMATE)
    cons = weighted_consensus(y, est[key + ":sigma"])
    if cons is not None:
        mean, half = cons
        chart.hspan(mean - half, mean + half, "#999999", 0.3, label="consensus 95 %")
        chart.hline(mean, "#000000", 1.0, label=f"consensus {mean:.4g} {unit}")
    if relative:
        chart.hline(0.0, "#000000", 1.0, DOTTED, label="expected")
    chart.ticks("x", list(range(len(y))), est["label"])
    chart.labels = (name, "plan pose", f"{name} {'- expected ' if relative else ''}({unit})")
    chart.legend()
    chart.grid_axes = "both"
    chart.render()


def consistency_figure(consistency: Mapping[str, Any], camera: str) -> bytes:
    """Each pose's plane against the consensus in the base frame: normal (deg) and height (mm), with tolerances."""
    normal = np.asarray(consistency.get("normal_deviation_deg") or [], dtype=np.float64)
    height = 1000.0 * np.asarray(consistency.get("height_deviation_m") or [], dtype=np.float64)
    canvas = Canvas((11.0, 3.8), DPI)
    canvas.title(f"cross-pose consistency in the base frame, camera {camera}: verdict "
                 f"{consistency.get('verdict', 'n/a')}")
    ax_n, ax_h = (Chart(canvas, rect) for rect in subplot_rects(2, 0.08, 0.98, 0.2, 0.8, 0.35))
    labels = [f"pose {i + 1}" for i in range(max(normal.size, height.size))]
    ax_n.bars(range(normal.size), normal, ["#4393c3"] * normal.size)
    if consistency.get("normal_tolerance_deg") is not None:
        ax_n.hline(float(consistency["normal_tolerance_deg"]), FAILED, 1.5, DASHED, label="accepted")
    ax_n.ticks("x", list(range(normal.size)), labels[:normal.size])
    ax_n.labels = (f"normal spread {num(consistency.get('normal_spread_deg')):.4f} deg", "plan pose",
                   "normal from the consensus (deg)")
    ax_h.bars(range(height.size), height, ["#92c5de"] * height.size)
    if consistency.get("height_tolerance_m") is not None:
        tol = 1000.0 * float(consistency["height_tolerance_m"])
        for sign in (-1, 1):
            ax_h.hline(sign * tol, FAILED, 1.5, DASHED, label="accepted" if sign > 0 else None)
    ax_h.hline(0.0, "#000000", 0.8)
    ax_h.ticks("x", list(range(height.size)), labels[:height.size])
    ax_h.labels = (f"height spread {1000 * num(consistency.get('height_spread_m')):.3f} mm", "plan pose",
                   "height from the consensus (mm)")
    for ax in (ax_n, ax_h):
        ax.legend()
        ax.grid_axes = "y"
        ax.render()
    return canvas.png()
