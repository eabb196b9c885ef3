"""The fixed camera's report pictures as plain images (ADR 0051): its pose with intervals, the residuals, what
the plan sees.

Drawn with :class:`~cellcal.core.report.chart.Chart` from the result document of ``cellcal handeye``
for a camera ``on = "base"`` (``DIR/handeye-NAME.json``, schema ``cellcal.handeye-fixed/1``) alone:
the camera's steps from its configured pose in the base frame (mm, degrees) with their 95 %
intervals, the plate's terms, per-pose residuals, each parameter's 1-sigma with the camera's
systematic allowance's share. Each function returns PNG bytes.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from cellcal.core.report.calibrate_charts import ESTIMATE, num
from cellcal.core.report.canvas import DASHED, Canvas
from cellcal.core.report.chart import Chart, subplot_rects
from cellcal.core.report.style import DPI, FAILED

__all__ = ["fixed_pose_figure", "fixed_residuals_figure", "fixed_sigma_figure", "parameter_unit"]

#: Colours of the plate's terms and of the systematic allowance's part.
PLATE = "#d6604d"
SYSTEMATIC = "#fdb863"


def parameter_unit(name: str) -> tuple[float, str]:
    """Display scale and unit of a fixed fit's parameter: angles (rad) in degrees, lengths (m) in mm."""
    return (180.0 / math.pi, "deg") if ("rot" in name or "tilt" in name) else (1000.0, "mm")


def fixed_pose_figure(document: Mapping[str, Any], camera: str) -> bytes:
    """Every fitted parameter's step from the configured value with its interval: the camera's turn about the base
    axes and shift along them, then the plate's tilts and offset in the flange (when estimated)."""
    names = list(document.get("parameters") or [])
    steps = list(document.get("steps") or [])
    half = document.get("half_widths") or {}
    shown = [i for i, n in enumerate(names) if n in half]
    canvas = Canvas((15.0, 3.9), DPI)
    conf = round(100 * num(document.get("confidence")))
    canvas.title(f"fixed camera {camera} in the base frame: steps from the configured pose with {conf} % "
                 "intervals; plate in the flange")
    for rect, i in zip(subplot_rects(len(shown), 0.045, 0.99, 0.16, 0.8, 0.75), shown, strict=True):
        k, unit = parameter_unit(names[i])
        value, h = k * num(steps[i]), k * num(half[names[i]])
        chart = Chart(canvas, rect)
        chart.errorbar(0.0, value, value - h, value + h, PLATE if i >= 6 else ESTIMATE)
        chart.hline(0.0, "#000000", 0.8, DASHED)
        chart.limits["x"] = (-1.0, 1.0)
        chart.ticks("x", [0.0], ["step"])
        chart.labels = (names[i], "", f"{names[i]} ({unit})")
        chart.grid_axes = "y"
        chart.title_style = (10.0, "#000000")
        chart.render()
    return canvas.png()


def fixed_residuals_figure(document: Mapping[str, Any], camera: str) -> bytes:
    """Per plate pose: the normal's residual (deg), the offset's (mm) and the whitened chi-square (3 on average)."""
    res = list(document.get("residuals") or [])
    labels = [str(int(r.get("pose", i + 1))) for i, r in enumerate(res)]
    canvas = Canvas((13.5, 3.8), DPI)
    canvas.title(f"plate residuals per pose, fixed camera {camera}")
    rects = subplot_rects(3, 0.07, 0.98, 0.17, 0.82, 0.35)
    worst = int(np.argmax([num(r.get("chi2")) for r in res])) if res else -1
    for rect, key, scale, name, unit in zip(rects, ("normal_rad", "offset_m", "chi2"), (180.0 / math.pi, 1000.0, 1.0),
                                            ("normal residual", "offset residual", "chi-square"), ("deg", "mm", "1"),
                                            strict=True):
        chart = Chart(canvas, rect)
        values = [scale * num(r.get(key)) for r in res]
        chart.bars(range(len(values)), values, [FAILED if i == worst and key == "chi2" else "#4393c3"
                                                for i in range(len(values))])
        if key == "chi2":
            chart.hline(3.0, "#000000", 1.0, DASHED, label="expected mean (3)")
            chart.legend()
        every = max(1, math.ceil(len(labels) / 13))          # at most 13 labels: they stay apart
        chart.ticks("x", list(range(0, len(labels), every)), labels[::every], size_pt=8.0)
        chart.labels = (name, "plate pose", f"{name} ({unit})")
        chart.grid_axes = "y"
        chart.render()
    return canvas.png()


def fixed_sigma_figure(document: Mapping[str, Any], camera: str) -> bytes:
    """What the plan sees: each camera parameter's 1-sigma (deg, mm), and the share of its variance that is the
    camera's systematic allowance (common to the views: no number of views lowers it)."""
    names = list(document.get("parameters") or [])[:6]
    cov = np.asarray(document.get("covariance") or np.zeros((0, 0)), dtype=np.float64)
    share = (document.get("systematic") or {}).get("variance_share") or {}
    obs = document.get("observability") or {}
    canvas = Canvas((13.0, 3.9), DPI)
    canvas.title(f"what the plan sees, fixed camera {camera}: rank {obs.get('rank', '?')} of "
                 f"{obs.get('n_parameters', '?')}, condition {num(obs.get('condition')):.3g}")
    ax_s, ax_f = (Chart(canvas, rect) for rect in subplot_rects(2, 0.08, 0.98, 0.17, 0.82, 0.3))
    sigma = np.sqrt(np.clip(np.diag(cov), 0.0, None)) if cov.size else np.zeros(len(names))
    scaled = [parameter_unit(n)[0] * s for n, s in zip(names, sigma, strict=False)]
    ticks = [f"{n} ({parameter_unit(n)[1]})" for n in names]
    ax_s.bars(range(len(scaled)), scaled, ["#4393c3"] * len(scaled))
    ax_s.ticks("x", list(range(len(ticks))), ticks, size_pt=8.0)
    ax_s.labels = ("1-sigma of the camera's pose", "parameter", "1-sigma (deg for turns, mm for shifts)")
    fractions = [100.0 * num(share.get(n, 0.0)) for n in names]
    ax_f.bars(range(len(fractions)), fractions, [SYSTEMATIC] * len(fractions))
    ax_f.limits["y"] = (0.0, 100.0)
    ax_f.ticks("x", list(range(len(names))), names, size_pt=8.0)
    ax_f.labels = ("the systematic allowance's share of the variance", "parameter", "share of the variance (%)")
    for ax in (ax_s, ax_f):
        ax.grid_axes = "y"
        ax.render()
    return canvas.png()
