"""The report's pictures (matplotlib on the headless Agg backend, extra ``plots``), from report data alone.

Each function takes the JSON data of :mod:`cellcal.core.report.capture` (or a result
document) and returns PNG bytes. Units are in every axis label, the pose and the camera in
every title; maps use colour maps whose lightness orders the values (viridis) or, for the
residuals, a diverging map centred on zero; pixel classes differ in lightness as well as hue.
matplotlib is imported on first use.
"""

from __future__ import annotations

import io
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from cellcal.core.report.arrays import decode_array
from cellcal.core.report.capture import CLASS_INLIER, CLASS_INVALID, CLASS_MIXED, CLASS_NAMES, CLASS_OUTLIER, REGION_BIT
from cellcal.devices.errors import MissingDependencyError

__all__ = ["CLASS_AXES", "CLASS_COLORS", "DPI", "PANEL_AXES", "charuco_figure", "consistency_figure",
           "handeye_mount_figure", "handeye_observability_figure", "handeye_residuals_figure", "monitor_figure",
           "pose_fit_figure", "pose_image_figure", "poses_figure", "pyplot"]

#: Resolution of every PNG, dots per inch.
DPI = 80
#: Class colours (RGB hex); their lightness differs too, so the classes survive greyscale.
CLASS_COLORS = {CLASS_INVALID: "#ffffff", CLASS_INLIER: "#5aae61", CLASS_MIXED: "#fdb863", CLASS_OUTLIER: "#40004b"}
#: Size of the per-pose image figure, inches, and its three image axes (figure fractions: left,
#: bottom, width, height): depth, pixel classes, residuals. The images fill their axes exactly.
IMAGE_FIGSIZE_IN = (15.0, 4.2)
PANEL_AXES = ((0.045, 0.13, 0.2, 0.72), (0.37, 0.13, 0.19, 0.72), (0.73, 0.13, 0.17, 0.72))
#: Colour bars of the depth and residual panels (figure fractions).
_COLORBAR_AXES = ((0.25, 0.13, 0.01, 0.72), (0.91, 0.13, 0.01, 0.72))
CLASS_AXES = PANEL_AXES[1]
#: Colour of failed gates, passed gates and thresholds.
FAILED, PASSED, THRESHOLD = "#b2182b", "#4d4d4d", "#000000"


#: matplotlib.pyplot once imported (on the Agg backend).
_PYPLOT: list[Any] = []


def pyplot() -> Any:
    """matplotlib.pyplot on the headless Agg backend, imported on first use.

    Raises:
        MissingDependencyError: If matplotlib is not installed (extra ``plots``).
    """
    if not _PYPLOT:
        try:
            import matplotlib

            matplotlib.use("Agg", force=True)
            import matplotlib.pyplot as plt
        except ImportError:
            raise MissingDependencyError("matplotlib", "plots") from None
        _PYPLOT.append(plt)
    return _PYPLOT[0]


def _png(fig: Any) -> bytes:
    """The figure as PNG bytes at :data:`DPI`; the figure is closed."""
    buf = io.BytesIO()
    try:
        fig.savefig(buf, format="png", dpi=DPI)
    finally:
        pyplot().close(fig)
    return buf.getvalue()


def _pose_title(pose: Mapping[str, Any], camera: str) -> str:
    state = " - FAILED" if pose.get("failed") else ""
    return f"pose {int(pose['index']) + 1}, camera {camera}{state}"


# ---------------------------------------------------------------------- one pose
def pose_image_figure(pose: Mapping[str, Any], camera: str) -> bytes:
    """Depth (mm), pixel classes with the region, and residuals (mm, diverging, centred on zero)."""
    plt = pyplot()
    from matplotlib.colors import ListedColormap
    from matplotlib.patches import Patch

    pics = pose["pictures"]
    depth = decode_array(pics["depth_mm"]).astype(np.float32)
    residual = decode_array(pics["residual_mm"]).astype(np.float32)
    classes = decode_array(pics["classes"])
    h, w = pics["shape_px"]
    extent = (-0.5, w - 0.5, h - 0.5, -0.5)  # in full-resolution pixel coordinates
    fig = plt.figure(figsize=IMAGE_FIGSIZE_IN)
    fig.suptitle(_pose_title(pose, camera), fontsize=11)
    ax_d, ax_c, ax_r = (fig.add_axes(rect) for rect in PANEL_AXES)
    # depth along the optical axis, viridis (lightness increases with the value)
    im = ax_d.imshow(depth, cmap="viridis", extent=extent, aspect="auto", interpolation="nearest")
    fig.colorbar(im, cax=fig.add_axes(_COLORBAR_AXES[0])).set_label("depth z (mm)")
    ax_d.set_title("depth (camera z)")
    # pixel classes: a categorical map with the region's outline
    cmap = ListedColormap([CLASS_COLORS[c] for c in (CLASS_INVALID, CLASS_INLIER, CLASS_MIXED, CLASS_OUTLIER)])
    ax_c.imshow(classes & 3, cmap=cmap, vmin=-0.5, vmax=3.5, extent=extent, aspect="auto", interpolation="nearest")
    if pics.get("region"):
        inside = (classes & REGION_BIT) > 0
        # outside the region the fit did not look: veiled in white
        veil = np.zeros((*inside.shape, 4))
        veil[~inside] = (1.0, 1.0, 1.0, 0.65)
        ax_c.imshow(veil, extent=extent, aspect="auto", interpolation="nearest")
        ys = np.linspace(0, h - 1, inside.shape[0])
        xs = np.linspace(0, w - 1, inside.shape[1])
        ax_c.contour(xs, ys, inside.astype(float), levels=[0.5], colors="#000000", linewidths=1.5,
                     linestyles="--")
    uncovered = _uncovered_cells(ax_c, pose, h, w)
    counts = pics.get("class_counts", {})
    handles: list[Any] = [Patch(facecolor=CLASS_COLORS[c], edgecolor="#000000",
                                label=f"{CLASS_NAMES[c].split(' ')[0]}: {counts.get(CLASS_NAMES[c], 0)} px")
                          for c in (CLASS_INLIER, CLASS_MIXED, CLASS_OUTLIER, CLASS_INVALID)]
    if pics.get("region"):
        from matplotlib.lines import Line2D

        handles.append(Line2D([], [], color="#000000", linestyle="--", label="region used (outside: veiled)"))
    if uncovered:
        handles.append(Patch(facecolor="none", edgecolor=FAILED, hatch="xx", linewidth=2.0,
                             label=f"too few plane pixels: {uncovered[0]} of {uncovered[1]} cells"))
    ax_c.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7, frameon=False)
    ax_c.set_title("pixels: plane, mixed, outliers" + (", region" if pics.get("region") else ""))
    # residuals: diverging, symmetric about zero, scaled to the inliers' spread
    inl = (classes & 3) == CLASS_INLIER
    finite = residual[inl & np.isfinite(residual)]
    lim = float(np.percentile(np.abs(finite), 99)) if finite.size else float(np.nanmax(np.abs(residual), initial=1.0))
    lim = lim if lim > 0 else 1.0
    im = ax_r.imshow(residual, cmap="RdBu_r", vmin=-lim, vmax=lim, extent=extent, aspect="auto",
                     interpolation="nearest")
    fig.colorbar(im, cax=fig.add_axes(_COLORBAR_AXES[1])).set_label("residual (mm, + toward the camera)")
    flat = ((pose.get("full_frame") or {}).get("gates") or {}).get("flatness")
    if flat and not flat.get("passed", True) and flat.get("value") is not None:
        # a non-flat surface: the residual pattern above is why; say by how much in the panel's title
        ax_r.set_title(f"residual: NOT FLAT, a local plane {1000.0 * float(flat['value']):.2g} mm off "
                       f"(tolerance {1000.0 * float(flat['threshold']):.2g} mm)", color=FAILED, fontsize=9)
    else:
        ax_r.set_title("residual to the fitted plane")
    for ax in (ax_d, ax_c, ax_r):
        ax.set_xlabel("u (px)")
        ax.set_ylabel("v (px)")
    return _png(fig)


def _uncovered_cells(ax: Any, pose: Mapping[str, Any], h: int, w: int) -> tuple[int, int] | None:
    """On a pose the coverage gate refused: outline and hatch the grid cells without enough plane inliers.

    Returns (uncovered, counted) cells, or None when the gate did not refuse the pose.
    """
    from matplotlib.patches import Rectangle

    coverage = pose["pictures"].get("coverage")
    gate = ((pose.get("full_frame") or {}).get("gates") or {}).get("coverage")
    if not coverage or not gate or gate.get("passed", True):
        return None
    rows = [*coverage["row_edges_px"], h]  # cell edges in full-resolution pixels
    cols = [*coverage["col_edges_px"], w]
    bad = np.asarray(coverage["uncovered"], dtype=bool)
    for r, c in zip(*np.nonzero(bad), strict=True):
        ax.add_patch(Rectangle((cols[c] - 0.5, rows[r] - 0.5), cols[c + 1] - cols[c], rows[r + 1] - rows[r],
                               fill=False, edgecolor=FAILED, hatch="xx", linewidth=2.0))
    return int(bad.sum()), int(np.asarray(coverage["counted"], dtype=bool).sum())


#: Gate name -> (label, scale, unit, "min"/"max").
_GATES = {"valid_fraction": ("valid pixels", 100.0, "%", "min"),
          "residual_floor": ("RMS vs sensor floor", 1.0, "x", "min"),
          "inlier_fraction": ("plane inliers", 100.0, "%", "min"),
          "residual_rms_m": ("residual RMS", 1000.0, "mm", "max"),
          "expected_plane": ("off the expected plane", 180.0 / math.pi, "deg", "max"),
          "coverage": ("image coverage", 100.0, "%", "min"),
          "flatness": ("flatness", 1000.0, "mm", "max")}


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


def pose_fit_figure(pose: Mapping[str, Any], camera: str) -> bytes:
    """Side view of the cloud with the fitted plane, and the gates as value against threshold."""
    plt = pyplot()
    pics = pose["pictures"]
    ff = pose.get("full_frame") or {}
    fig = plt.figure(figsize=(13.0, 4.2))
    ax_s = fig.add_axes((0.06, 0.14, 0.38, 0.7))
    ax_g = fig.add_axes((0.66, 0.14, 0.22, 0.7))
    fig.suptitle(_pose_title(pose, camera), fontsize=11)
    _side_view(ax_s, pics)
    _gates(ax_g, ff.get("gates") or {})
    return _png(fig)


def _side_view(ax: Any, pics: Mapping[str, Any]) -> None:
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
            ax.scatter(along[sel], height[sel], s=4, c=CLASS_COLORS[c], label=CLASS_NAMES[c],
                       edgecolors="#000000" if c == CLASS_OUTLIER else "none", linewidths=0.2)
    ax.axhline(0.0, color=THRESHOLD, linewidth=1.2, label="fitted plane")
    ax.set_xlabel("along the plane (mm, camera y projected)")
    ax.set_ylabel("height above the plane (mm)")
    ax.set_title("side view of the cloud (sample) and the fitted plane")
    ax.legend(fontsize=7, loc="best")
    ax.grid(alpha=0.3)


def _gates(ax: Any, gates: Mapping[str, Any]) -> None:
    """Each gate's value over its threshold (log axis, 1 = the threshold); failed ones in red and hatched."""
    rows = gate_rows(gates)
    if not rows:
        ax.text(0.5, 0.5, "no gates (no full-frame fit)", ha="center", va="center", transform=ax.transAxes)
        ax.set_axis_off()
        return
    ratios = []
    for _, value, threshold, _, _, _ in rows:
        r = value / threshold if threshold and math.isfinite(value) and math.isfinite(threshold) else math.nan
        ratios.append(r if math.isfinite(r) and r > 0 else 0.0)
    y = np.arange(len(rows))
    colors = [PASSED if ok else FAILED for *_, ok in rows]
    bars = ax.barh(y, ratios, color=colors, edgecolor="#000000")
    for bar, (*_, ok) in zip(bars, rows, strict=True):
        if not ok:
            bar.set_hatch("//")
    ax.axvline(1.0, color=THRESHOLD, linestyle="--", linewidth=1.2)
    ax.set_xlim(0.0, 1.6 * max(ratios))
    ax.set_yticks(y)
    ax.set_yticklabels([f"{label} ({side} {threshold:.3g} {unit})" for label, _, threshold, unit, side, _ in rows],
                       fontsize=8)
    for yi, (_, value, _, unit, _, ok), r in zip(y, rows, ratios, strict=True):
        ax.text(r, yi, f"  {value:.3g} {unit}" + ("" if ok else "  FAILED"), va="center", fontsize=8,
                color=FAILED if not ok else "#000000", fontweight="bold" if not ok else "normal")
    ax.invert_yaxis()
    ax.set_xlabel("value / threshold (1 = the threshold)")
    ax.set_title("quality gates: value vs threshold")


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
            out[key].append(_num(ff.get(key)) * k)
            out[key + ":ci"].append([_num(ci[0]) * k, _num(ci[1]) * k])
            out[key + ":sigma"].append(_num(ff.get(sigma_key)) * k)
            out[key + ":expected"].append(_num(exp.get(key)) * k)
    return out


def _num(value: Any) -> float:
    return math.nan if value is None else float(value)


def poses_figure(poses: Sequence[Mapping[str, Any]], camera: str) -> bytes:
    """Tilt x, tilt y and height per pose with 95 % intervals, the expected values and the consensus.

    With expected values (a ``[reference]``) each is drawn as measured minus expected, so poses
    at different heights share one axis.
    """
    plt = pyplot()
    est = pose_estimates(poses)
    fig, axes = plt.subplots(1, 3, figsize=(13.5, 4.0))
    fig.suptitle(f"tilt and height per pose with 95 % intervals, camera {camera}", fontsize=11)
    x = np.arange(len(est["label"]))
    for ax, key, name, unit in zip(axes, ("tilt_x_deg", "tilt_y_deg", "height_m"), ("tilt x", "tilt y", "height"),
                                   ("deg", "deg", "mm"), strict=True):
        value = np.asarray(est[key], dtype=np.float64)
        ci = np.asarray(est[key + ":ci"], dtype=np.float64).reshape(-1, 2)
        expected = np.asarray(est[key + ":expected"], dtype=np.float64)
        relative = bool(expected.size) and bool(np.all(np.isfinite(expected)))
        ref = expected if relative else np.zeros_like(value)
        y = value - ref
        err = np.vstack([y - (ci[:, 0] - ref), (ci[:, 1] - ref) - y]) if ci.size else None
        colors = [FAILED if f else "#2166ac" for f in est["failed"]]
        for xi, yi, e0, e1, c in zip(x, y, *(err if err is not None else ([], [])), colors, strict=False):
            ax.errorbar([xi], [yi], yerr=[[e0], [e1]], fmt="o", color=c, capsize=4)
        cons = weighted_consensus(y, est[key + ":sigma"])
        if cons is not None:
            mean, half = cons
            ax.axhspan(mean - half, mean + half, color="#999999", alpha=0.3, label="consensus 95 %")
            ax.axhline(mean, color="#000000", linewidth=1.0, label=f"consensus {mean:.4g} {unit}")
        if relative:
            ax.axhline(0.0, color="#000000", linestyle=":", linewidth=1.0, label="expected")
        ax.set_xticks(x)
        ax.set_xticklabels(est["label"])
        ax.set_xlabel("plan pose")
        ax.set_ylabel(f"{name} {'- expected ' if relative else ''}({unit})")
        ax.set_title(name)
        ax.legend(fontsize=7)
        ax.grid(alpha=0.3)
    fig.subplots_adjust(left=0.07, right=0.98, bottom=0.16, top=0.82, wspace=0.35)
    return _png(fig)


def consistency_figure(consistency: Mapping[str, Any], camera: str) -> bytes:
    """Each pose's plane against the consensus in the base frame: normal (deg) and height (mm), with tolerances."""
    plt = pyplot()
    normal = np.asarray(consistency.get("normal_deviation_deg") or [], dtype=np.float64)
    height = 1000.0 * np.asarray(consistency.get("height_deviation_m") or [], dtype=np.float64)
    fig, (ax_n, ax_h) = plt.subplots(1, 2, figsize=(11.0, 3.8))
    fig.suptitle(f"cross-pose consistency in the base frame, camera {camera}: verdict "
                 f"{consistency.get('verdict', 'n/a')}", fontsize=11)
    labels = [f"pose {i + 1}" for i in range(max(normal.size, height.size))]
    ax_n.bar(labels[:normal.size], normal, color="#4393c3", edgecolor="#000000")
    if consistency.get("normal_tolerance_deg") is not None:
        ax_n.axhline(float(consistency["normal_tolerance_deg"]), color=FAILED, linestyle="--", label="accepted")
    ax_n.set_ylabel("normal from the consensus (deg)")
    ax_n.set_xlabel("plan pose")
    ax_n.set_title(f"normal spread {_num(consistency.get('normal_spread_deg')):.4f} deg")
    ax_h.bar(labels[:height.size], height, color="#92c5de", edgecolor="#000000")
    if consistency.get("height_tolerance_m") is not None:
        tol = 1000.0 * float(consistency["height_tolerance_m"])
        for sign in (-1, 1):
            ax_h.axhline(sign * tol, color=FAILED, linestyle="--", label="accepted" if sign > 0 else None)
    ax_h.axhline(0.0, color="#000000", linewidth=0.8)
    ax_h.set_ylabel("height from the consensus (mm)")
    ax_h.set_xlabel("plan pose")
    ax_h.set_title(f"height spread {1000 * _num(consistency.get('height_spread_m')):.3f} mm")
    for ax in (ax_n, ax_h):
        ax.legend(fontsize=7)
        ax.grid(alpha=0.3, axis="y")
    fig.subplots_adjust(left=0.08, right=0.98, bottom=0.2, top=0.8, wspace=0.35)
    return _png(fig)


# ---------------------------------------------------------------------- hand-eye
def handeye_residuals_figure(document: Mapping[str, Any], camera: str) -> bytes:
    """Per-pose residuals of the mount fit: normal (deg), offset (mm), chi-square."""
    plt = pyplot()
    poses = document.get("poses") or []
    labels = [f"pose {int(p['index']) + 1}" for p in poses]
    res = [p.get("residual") or {} for p in poses]
    fig, axes = plt.subplots(1, 3, figsize=(13.5, 3.8))
    fig.suptitle(f"hand-eye per-pose residuals, camera {camera}", fontsize=11)
    for ax, key, k, unit, name in ((axes[0], "normal_deg", 1.0, "deg", "normal residual"),
                                   (axes[1], "offset_m", 1000.0, "mm", "offset residual"),
                                   (axes[2], "chi2", 1.0, "1", "chi-square")):
        ax.bar(labels, [k * _num(r.get(key)) for r in res], color="#4393c3", edgecolor="#000000")
        ax.set_ylabel(f"{name} ({unit})")
        ax.set_xlabel("plan pose")
        ax.set_title(name)
        ax.tick_params(axis="x", labelrotation=45)
        ax.grid(alpha=0.3, axis="y")
    fit = document.get("fit") or {}
    if fit.get("dof"):
        axes[2].axhline(float(fit["chi2"]) / len(poses) if poses else 0.0, color="#000000", linestyle="--",
                        label=f"mean (chi2/dof {_num(fit.get('chi2_per_dof')):.2f})")
        axes[2].legend(fontsize=7)
    fig.subplots_adjust(left=0.08, right=0.98, bottom=0.2, top=0.8, wspace=0.35)
    return _png(fig)


def handeye_observability_figure(document: Mapping[str, Any], camera: str) -> bytes:
    """What the plan sees: each parameter's 1-sigma and the correlations it trades with the others."""
    plt = pyplot()
    fit = document.get("fit") or {}
    names = list(fit.get("parameters") or [])
    cov = np.asarray(fit.get("covariance") or np.zeros((0, 0)), dtype=np.float64)
    fig = plt.figure(figsize=(13.0, 4.8))
    ax_s = fig.add_axes((0.13, 0.15, 0.3, 0.7))
    ax_c = fig.add_axes((0.6, 0.2, 0.28, 0.65))
    obs = document.get("observability") or {}
    fig.suptitle(f"hand-eye observability, camera {camera}: rank {obs.get('rank', '?')} of "
                 f"{obs.get('n_parameters', '?')}, condition {_num(obs.get('condition')):.3g}", fontsize=11)
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
    plt = pyplot()
    m = document["mount"]
    fig, axes = plt.subplots(1, 6, figsize=(14.0, 3.8))
    fig.suptitle(f"camera mount in the flange frame ({round(100 * _num(m.get('confidence')))} % intervals), "
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
    plt = pyplot()
    views = (document.get("charuco") or {}).get("views") or []
    labels = [f"pose {i + 1}" for i in range(len(views))]
    fig, axes = plt.subplots(1, 3, figsize=(13.5, 3.8))
    fig.suptitle(f"ChArUco board poses, camera {camera}", fontsize=11)
    corners = [_num(v.get("corners")) if v else 0.0 for v in views]
    reproj = [_num(v.get("reprojection_px")) if v else math.nan for v in views]
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
    plt = pyplot()
    t = np.asarray(series.get("t") or [], dtype=np.float64)
    drift = np.asarray(series.get("drift") or [], dtype=bool)
    fig, (ax_t, ax_h) = plt.subplots(2, 1, figsize=(11.0, 5.6), sharex=True)
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
