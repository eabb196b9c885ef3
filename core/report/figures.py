"""The report's matplotlib pictures (hand-eye and monitor; figures on the headless Agg canvas, extra ``plots``).

Each function takes report data (or a result document) and returns PNG bytes. Units are in
every axis label, the camera in every title. matplotlib is imported on first use; no figure
goes through pyplot. The calibrate report's pictures are plain images drawn without matplotlib
(:mod:`~cellcal.core.report.poseimage`, :mod:`~cellcal.core.report.calibrate_charts`,
ADR 0051); this module names them too, for one place that lists every picture.
"""

from __future__ import annotations

import io
import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from cellcal.core.report.calibrate_charts import (
    consistency_figure,
    gate_rows,
    num,
    pose_estimates,
    pose_fit_figure,
    poses_figure,
    weighted_consensus,
)
from cellcal.core.report.fixed_charts import fixed_pose_figure, fixed_residuals_figure, fixed_sigma_figure
from cellcal.core.report.poseimage import pose_image_figure
from cellcal.core.report.style import CLASS_AXES, CLASS_COLORS, DPI, FAILED, IMAGE_FIGSIZE_IN, PANEL_AXES
from cellcal.devices.errors import MissingDependencyError

__all__ = ["CLASS_AXES", "CLASS_COLORS", "DPI", "FAILED", "IMAGE_FIGSIZE_IN", "PANEL_AXES",
           "charuco_figure", "consistency_figure", "fixed_pose_figure", "fixed_residuals_figure",
           "fixed_sigma_figure", "gate_rows", "handeye_mount_figure", "handeye_observability_figure",
           "handeye_residuals_figure", "matplotlib_figure", "monitor_figure", "pose_estimates", "pose_fit_figure",
           "pose_image_figure", "poses_figure", "weighted_consensus"]

#: matplotlib's Figure and the Agg canvas once imported.
_MATPLOTLIB: list[Any] = []


def matplotlib_figure() -> Any:
    """matplotlib's ``Figure`` class, imported on first use with the headless Agg canvas (no pyplot state).

    Raises:
        MissingDependencyError: If matplotlib is not installed (extra ``plots``).
    """
    if not _MATPLOTLIB:
        try:
            from matplotlib.backends.backend_agg import FigureCanvasAgg
            from matplotlib.figure import Figure
        except ImportError:
            raise MissingDependencyError("matplotlib", "plots") from None
        _MATPLOTLIB.extend((Figure, FigureCanvasAgg))
    return _MATPLOTLIB[0]


def _figure(figsize: tuple[float, float]) -> Any:
    """A new figure of ``figsize`` inches on its own Agg canvas."""
    fig = matplotlib_figure()(figsize=figsize)
    _MATPLOTLIB[1](fig)
    return fig


def _png(fig: Any) -> bytes:
    """The figure as PNG bytes at :data:`DPI`."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    return buf.getvalue()


# ---------------------------------------------------------------------- hand-eye
def handeye_residuals_figure(document: Mapping[str, Any], camera: str) -> bytes:
    """Per-pose residuals of the mount fit: normal (deg), offset (mm), chi-square."""
    poses = document.get("poses") or []
    labels = [f"pose {int(p['index']) + 1}" for p in poses]
    res = [p.get("residual") or {} for p in poses]
    fig = _figure((13.5, 3.8))
    axes = fig.subplots(1, 3)
    fig.suptitle(f"hand-eye per-pose residuals, camera {camera}", fontsize=11)
    for ax, key, k, unit, name in ((axes[0], "normal_deg", 1.0, "deg", "normal residual"),
                                   (axes[1], "offset_m", 1000.0, "mm", "offset residual"),
                                   (axes[2], "chi2", 1.0, "1", "chi-square")):
        ax.bar(labels, [k * num(r.get(key)) for r in res], color="#4393c3", edgecolor="#000000")
        ax.set_ylabel(f"{name} ({unit})")
        ax.set_xlabel("plan pose")
        ax.set_title(name)
        ax.tick_params(axis="x", labelrotation=45)
        ax.grid(alpha=0.3, axis="y")
    fit = document.get("fit") or {}
    if fit.get("dof"):
        axes[2].axhline(float(fit["chi2"]) / len(poses) if poses else 0.0, color="#000000", linestyle="--",
                        label=f"mean (chi2/dof {num(fit.get('chi2_per_dof')):.2f})")
        axes[2].legend(fontsize=7)
    fig.subplots_adjust(left=0.08, right=0.98, bottom=0.2, top=0.8, wspace=0.35)
    return _png(fig)


def handeye_observability_figure(document: Mapping[str, Any], camera: str) -> bytes:
    """What the plan sees: each parameter's 1-sigma and the correlations it trades with the others."""
    fit = document.get("fit") or {}
    names = list(fit.get("parameters") or [])
    cov = np.asarray(fit.get("covariance") or np.zeros((0, 0)), dtype=np.float64)
    fig = _figure((13.0, 4.8))
    ax_s = fig.add_axes((0.13, 0.15, 0.3, 0.7))
    ax_c = fig.add_axes((0.6, 0.2, 0.28, 0.65))
    obs = document.get("observability") or {}
    fig.suptitle(f"hand-eye observability, camera {camera}: rank {obs.get('rank', '?')} of "
                 f"{obs.get('n_parameters', '?')}, condition {num(obs.get('condition')):.3g}", fontsize=11)
    if cov.size:
        sigma = np.sqrt(np.clip(np.diag(cov), 0.0, None))
        # rotations in deg, lengths in mm
        angles = [_is_angle(n) for n in names]
        scaled = [s * (180.0 / math.pi if a else 1000.0) for a, s in zip(angles, sigma, strict=True)]
        units = ["deg" if a else "mm" for a in angles]
        ax_s.barh(range(len(names)), scaled, color="#4393c3", edgecolor="#000000")
        ax_s.set_yticks(range(len(names)))
        ax_s.set_yticklabels([f"{n} ({u})" for n, u in zip(names, units, strict=True)], fontsize=8)
        ax_s.set_xscale("log")
        ax_s.invert_yaxis()
        ax_s.set_xlabel("1-sigma (deg for rotations, mm for lengths; log)")
        ax_s.set_title("what the plan can see (smaller is better)")
        d = np.where(sigma > 0, sigma, 1.0)
        corr = cov / np.outer(d, d)
        im = ax_c.imshow(corr, cmap="RdBu_r", vmin=-1, vmax=1, interpolation="nearest")
        for i in range(corr.shape[0]):
            for j in range(corr.shape[1]):
                ax_c.text(j, i, f"{corr[i, j]:.1f}", ha="center", va="center", fontsize=6,
                          color="#ffffff" if abs(corr[i, j]) > 0.6 else "#000000")
        ax_c.set_xticks(range(len(names)))
        ax_c.set_xticklabels(names, rotation=60, ha="right", fontsize=7)
        ax_c.set_yticks(range(len(names)))
        ax_c.set_yticklabels(names, fontsize=7)
        fig.colorbar(im, cax=fig.add_axes((0.9, 0.2, 0.012, 0.65))).set_label("correlation (1)")
        ax_c.set_title("what it trades: parameter correlations")
    else:
        for ax in (ax_s, ax_c):
            ax.set_axis_off()
        ax_s.text(0.5, 0.5, "no covariance", ha="center", transform=ax_s.transAxes)
    return _png(fig)


def _is_angle(parameter: str) -> bool:
    """Whether a hand-eye fit parameter is an angle (rad) rather than a length (m)."""
    return "rot" in parameter or "tilt" in parameter


def handeye_mount_figure(document: Mapping[str, Any], camera: str) -> bytes:
    """The mount's six values with their intervals; with the board, OpenCV's methods against the plane's answer."""
    m = document["mount"]
    fig = _figure((14.0, 3.8))
    axes = fig.subplots(1, 6)
    fig.suptitle(f"camera mount in the flange frame ({round(100 * num(m.get('confidence')))} % intervals), "
                 f"camera {camera}", fontsize=11)
    charuco = (document.get("charuco") or {}).get("methods") or {}
    quantities = [(f"t{a}", 1000.0 * m["translation_m"][i], [1000.0 * v for v in m["translation_ci_m"][i]], "mm",
                   [1000.0 * c["translation_m"][i] for c in charuco.values()]) for i, a in enumerate("xyz")]
    quantities += [(n, m["rpy_deg"][i], list(m["rpy_ci_deg"][i]), "deg", [c["rpy_deg"][i] for c in charuco.values()])
                   for i, n in enumerate(("roll", "pitch", "yaw"))]
    for ax, (name, value, ci, unit, board) in zip(axes, quantities, strict=True):
        ax.errorbar([0], [value], yerr=[[value - ci[0]], [ci[1] - value]], fmt="o", color="#2166ac", capsize=5)
        ticks = ["plane"]
        for j, (method, v) in enumerate(zip(charuco, board, strict=True)):
            ax.plot([j + 1], [v], marker="sDv^<>"[j % 6], color="#d6604d", linestyle="none")
            ticks.append(method)
        ax.set_xticks(range(len(ticks)))
        ax.set_xticklabels(ticks, rotation=60, fontsize=7)
        ax.set_ylabel(f"{name} ({unit})")
        ax.set_title(name)
        ax.grid(alpha=0.3)
    fig.subplots_adjust(left=0.05, right=0.99, bottom=0.24, top=0.82, wspace=0.7)
    return _png(fig)


def charuco_figure(document: Mapping[str, Any], camera: str) -> bytes:
    """The ChArUco board views: corners found and reprojection error (px) per pose, board distance (mm)."""
    views = (document.get("charuco") or {}).get("views") or []
    labels = [f"pose {i + 1}" for i in range(len(views))]
    fig = _figure((13.5, 3.8))
    axes = fig.subplots(1, 3)
    fig.suptitle(f"ChArUco board poses, camera {camera}", fontsize=11)
    corners = [num(v.get("corners")) if v else 0.0 for v in views]
    reproj = [num(v.get("reprojection_px")) if v else math.nan for v in views]
    dist = [1000.0 * float(np.linalg.norm(v["board_in_camera"]["translation_m"])) if v and v.get("board_in_camera")
            else math.nan for v in views]
    for ax, values, name, unit in ((axes[0], corners, "corners found", "1"),
                                   (axes[1], reproj, "reprojection RMS", "px"),
                                   (axes[2], dist, "board distance from the camera", "mm")):
        ax.bar(labels, values, color="#f4a582", edgecolor="#000000")
        ax.set_ylabel(f"{name} ({unit})")
        ax.set_xlabel("plan pose")
        ax.set_title(name)
        ax.tick_params(axis="x", labelrotation=45)
        ax.grid(alpha=0.3, axis="y")
    fig.subplots_adjust(left=0.08, right=0.98, bottom=0.2, top=0.8, wspace=0.35)
    return _png(fig)


# ---------------------------------------------------------------------- monitor
def monitor_figure(label: str, series: Mapping[str, Any], camera: Mapping[str, Any]) -> bytes:
    """Tilt and height deviation from the baseline over time, the thresholds and the flagged drift."""
    t = np.asarray(series.get("t") or [], dtype=np.float64)
    drift = np.asarray(series.get("drift") or [], dtype=bool)
    fig = _figure((11.0, 5.6))
    ax_t, ax_h = fig.subplots(2, 1, sharex=True)
    fig.suptitle(f"monitor: drift of the measuring plane, camera {label}", fontsize=11)
    for ax, key, thr_key, k, name, unit in ((ax_t, "tilt_deg", "tilt_threshold_rad", 180.0 / math.pi, "tilt", "deg"),
                                            (ax_h, "height_mm", "height_threshold_m", 1000.0, "height", "mm")):
        y = np.asarray(series.get(key) or [], dtype=np.float64)
        ax.plot(t, y, color="#2166ac", linewidth=1.0, label=f"{name} from baseline")
        if drift.any():
            ax.scatter(t[drift], y[drift], s=10, color=FAILED, zorder=3, label="flagged drift")
            ax.fill_between(t, 0, 1, where=drift, color=FAILED, alpha=0.15, transform=ax.get_xaxis_transform())
        thr = camera.get(thr_key)
        if thr is not None:
            for sign in ((1,) if key == "tilt_deg" else (-1, 1)):
                ax.axhline(sign * k * float(thr), color="#000000", linestyle="--",
                           label="threshold" if sign > 0 else None)
        ax.set_ylabel(f"{name} deviation ({unit})")
        ax.legend(fontsize=7, loc="upper left")
        ax.grid(alpha=0.3)
    ax_h.set_xlabel("time since the first monitored frame (s)")
    fig.subplots_adjust(left=0.08, right=0.98, bottom=0.1, top=0.9, hspace=0.15)
    return _png(fig)
