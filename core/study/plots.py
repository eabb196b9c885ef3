"""Pictures of the accuracy study (matplotlib on the headless Agg backend; extra ``plots``).

Error against perimeter, clutter, noise and inclination (at the headline's ToF artefact
level), the full frame's error and interval coverage per artefact level, and the full-frame
plane over one cluttered frame (the paper's Figure 14 shows its nine-point plane). matplotlib is imported
inside the functions, so this module imports without it; each PNG is written atomically.
"""

from __future__ import annotations

import io
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cellcal.core.calibration.report import write_bytes_atomic
from cellcal.core.study.design import (
    ARTEFACT_LEVELS,
    FULL_FRAME,
    METHODS,
    PAPER_HEIGHTS_M,
    PAPER_INCLINATION_DEG,
    TARGET_COVERAGE,
)
from cellcal.core.study.table import headline_level, select
from cellcal.core.study.trials import StudyResult, TrialData
from cellcal.devices.errors import MissingDependencyError

Rows = Sequence[Mapping[str, Any]]

#: File names written by :func:`write_plots`.
PLOT_FILES: dict[str, str] = {
    "perimeter": "study_error_vs_perimeter.png",
    "clutter": "study_error_vs_clutter.png",
    "conditions": "study_error_vs_noise_inclination.png",
    "artefacts": "study_artefacts.png",
    "plane": "study_plane_fit.png",
}

LABELS = {"law_of_cosines": "law of cosines", "plane_fit_nominal": "nine-point, nominal FOV (paper)",
          "plane_fit": "nine-point, real intrinsics", FULL_FRAME: "full frame"}
COLORS = {"law_of_cosines": "#d95f02", "plane_fit_nominal": "#7570b3", "plane_fit": "#1b9e77",
          FULL_FRAME: "#e7298a"}
#: Errors are drawn on a log axis; exact zeros are shown at this floor, degrees.
FLOOR_DEG = 1e-4


def _pyplot() -> Any:
    """matplotlib.pyplot on the Agg backend.

    Raises:
        MissingDependencyError: If matplotlib is not installed (extra ``plots``).
    """
    try:
        import matplotlib
    except ImportError:
        raise MissingDependencyError("matplotlib", "plots") from None
    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig: Any, path: str | Path, dpi: int = 100) -> Path:
    """Render a figure to PNG and write it atomically; closes the figure."""
    plt = _pyplot()
    buf = io.BytesIO()
    try:
        fig.savefig(buf, format="png", dpi=dpi)
    finally:
        plt.close(fig)
    return write_bytes_atomic(path, buf.getvalue())


def _errors(rows: Rows) -> NDArray[np.float64]:
    vals = [max(float(r["abs_tilt_error_deg"]), FLOOR_DEG) for r in rows if r.get("ok")]
    return np.asarray(vals, dtype=np.float64)


def _boxes(ax: Any, data: Sequence[NDArray[np.float64]], positions: Sequence[float], width: float,
           color: str) -> None:
    keep = [(d, p) for d, p in zip(data, positions, strict=True) if d.size]
    if not keep:
        return
    bp = ax.boxplot([d for d, _ in keep], positions=[p for _, p in keep], widths=width, whis=(5, 95),
                    showfliers=False, patch_artist=True, manage_ticks=False)
    for patch in bp["boxes"]:
        patch.set(facecolor=color, alpha=0.55, edgecolor=color)
    for key in ("whiskers", "caps", "medians"):
        for line in bp[key]:
            line.set(color=color)
    ax.plot([p for _, p in keep], [float(np.mean(d)) for d, _ in keep], "o", color=color, ms=3)


def _paper(rows: Rows, **match: Any) -> list[Mapping[str, Any]]:
    return select(rows, inclination_deg=PAPER_INCLINATION_DEG, noise_scale=1.0, **match)


def _legend(fig: Any, methods: Sequence[str]) -> None:
    from matplotlib.patches import Patch

    handles = [Patch(facecolor=COLORS[m], alpha=0.55, edgecolor=COLORS[m], label=LABELS[m]) for m in methods]
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=8, frameon=False)


def plot_error_vs_perimeter(rows: Rows, path: str | Path, *, clutter: float = 0.0) -> Path:
    """|tilt error| vs perimeter for each method at each height (paper inclination, default noise).

    The full-frame method uses every pixel, so it has one box per height, at the right.
    """
    plt = _pyplot()
    sel = _paper(rows, clutter_target=clutter)
    heights = sorted({r["height_m"] for r in sel}) or list(PAPER_HEIGHTS_M)
    perims = sorted({r["perimeter_px"] for r in sel if r["perimeter_px"] is not None})
    methods = [m for m in METHODS if select(sel, method=m)]
    fig, axes = plt.subplots(1, len(heights), figsize=(4.2 * len(heights), 4.0), sharey=True, squeeze=False)
    width = 0.8 / max(len(methods), 1)
    for ax, h in zip(axes[0], heights, strict=True):
        at_h = select(sel, height_m=h)
        for j, m in enumerate(methods):
            off = (j - (len(methods) - 1) / 2) * width
            if m == FULL_FRAME:
                _boxes(ax, [_errors(select(at_h, method=m))], [len(perims)], 0.5, COLORS[m])
            else:
                data = [_errors(select(at_h, method=m, perimeter_px=p)) for p in perims]
                _boxes(ax, data, [i + off for i in range(len(perims))], width * 0.9, COLORS[m])
        ax.set_xticks(range(len(perims) + 1), [f"{p}" for p in perims] + ["all\npixels"])
        ax.set_yscale("log")
        ax.set_title(f"height {h:.2f} m", fontsize=10)
        ax.set_xlabel("perimeter, px")
        ax.grid(True, axis="y", which="both", alpha=0.3)
    axes[0][0].set_ylabel("|tilt error|, deg")
    n = len({(r["height_m"], r["trial"]) for r in sel})
    fig.suptitle(f"Tilt error vs perimeter and height ({PAPER_INCLINATION_DEG:g} deg inclination, "
                 f"{clutter * 100:.0f} % clutter, {n} frames); boxes 25-75 %, whiskers 5-95 %, dots mean",
                 fontsize=10)
    _legend(fig, methods)
    fig.tight_layout(rect=(0, 0.07, 1, 0.95))
    return save_figure(fig, path)


def plot_error_vs_clutter(rows: Rows, path: str | Path) -> Path:
    """|tilt error| vs the fraction of the plane covered by boxes (paper settings, all heights;
    the paper's methods pooled over perimeters)."""
    plt = _pyplot()
    sel = _paper(rows, height_m=tuple(sorted({r["height_m"] for r in rows})))
    levels = sorted({r["clutter_target"] for r in sel})
    methods = [m for m in METHODS if select(sel, method=m)]
    fig, ax = plt.subplots(figsize=(8.0, 4.5))
    width = 0.8 / max(len(methods), 1)
    for j, m in enumerate(methods):
        off = (j - (len(methods) - 1) / 2) * width
        data = [_errors(select(sel, method=m, clutter_target=c)) for c in levels]
        _boxes(ax, data, [i + off for i in range(len(levels))], width * 0.9, COLORS[m])
    labels = []
    for c in levels:
        ach = list({(r["height_m"], r["trial"]): r["clutter_achieved"] for r in select(sel, clutter_target=c)}.values())
        labels.append(f"{c * 100:.0f} %\n(got {np.mean(ach) * 100:.1f} %)" if ach else f"{c * 100:.0f} %")
    ax.set_xticks(range(len(levels)), labels)
    ax.set_yscale("log")
    for i, c in enumerate(levels):  # how often the full-frame result would pass its quality gates
        gates = [bool(r["gates_passed"]) for r in select(sel, method=FULL_FRAME, clutter_target=c)
                 if r["ok"] and r.get("gates_passed") is not None]
        if gates:
            ax.annotate(f"gates pass {np.mean(gates) * 100:.0f} %", (i + 0.3, 0.02), xycoords=("data", "axes fraction"),
                        ha="center", fontsize=7, color=COLORS[FULL_FRAME])
    ax.set_xlabel("plane pixels hidden by boxes (requested, achieved mean)")
    ax.set_ylabel("|tilt error|, deg")
    ax.grid(True, axis="y", which="both", alpha=0.3)
    ax.set_title("Tilt error vs clutter (heights 0.46-0.61 m, 80 deg)", fontsize=11)
    _legend(fig, methods)
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    return save_figure(fig, path)


def plot_error_vs_conditions(rows: Rows, path: str | Path) -> Path:
    """|tilt error| vs noise scale (80 deg) and vs inclination (default noise), no clutter,
    all heights; the paper's methods at every perimeter pooled."""
    plt = _pyplot()
    clean = select(rows, clutter_target=0.0)
    methods = [m for m in METHODS if select(clean, method=m)]
    fig, axes = plt.subplots(1, 2, figsize=(11.0, 4.2), sharey=True)
    panels = (("noise_scale", {"inclination_deg": PAPER_INCLINATION_DEG}, "noise scale (1 = default sim camera)"),
              ("inclination_deg", {"noise_scale": 1.0}, "inclination of the optical axis, deg"))
    width = 0.8 / max(len(methods), 1)
    for ax, (col, fixed, xlabel) in zip(axes, panels, strict=True):
        sub = select(clean, **fixed)
        levels = sorted({r[col] for r in sub})
        for j, m in enumerate(methods):
            off = (j - (len(methods) - 1) / 2) * width
            data = [_errors(select(sub, method=m, **{col: v})) for v in levels]
            _boxes(ax, data, [i + off for i in range(len(levels))], width * 0.9, COLORS[m])
        ax.set_xticks(range(len(levels)), [f"{v:g}" for v in levels])
        ax.set_xlabel(xlabel)
        ax.set_yscale("log")
        ax.grid(True, axis="y", which="both", alpha=0.3)
    axes[0].set_ylabel("|tilt error|, deg")
    fig.suptitle("Tilt error vs noise level and inclination (no clutter, heights 0.46-0.61 m)", fontsize=11)
    _legend(fig, methods)
    fig.tight_layout(rect=(0, 0.07, 1, 0.95))
    return save_figure(fig, path)


def _mean_or_nan(values: NDArray[np.float64]) -> float:
    return float(np.mean(values)) if values.size else math.nan


def plot_artefacts(rows: Rows, path: str | Path) -> Path:
    """Full frame per ToF artefact level vs clutter (paper settings, all heights): mean |tilt
    error| (left) and the 95 % intervals' coverage of the tilt and the height (right)."""
    plt = _pyplot()
    sel = _paper(rows, method=FULL_FRAME)
    levels = [a for a in ARTEFACT_LEVELS if select(sel, artefacts=a)]
    fig, (ax_e, ax_c) = plt.subplots(1, 2, figsize=(11.0, 4.2))
    for k, level in enumerate(levels):
        at = select(sel, artefacts=level)
        clutter = sorted({r["clutter_target"] for r in at})
        err = [_mean_or_nan(_errors(select(at, clutter_target=c))) for c in clutter]
        x = [c * 100 for c in clutter]
        color = f"C{k}"
        ax_e.plot(x, err, "o-", color=color, label=level)
        for col, style in (("ci_contains", "o-"), ("height_ci_contains", "s--")):
            cov = [_mean_or_nan(np.array([bool(r[col]) for r in select(at, clutter_target=c)
                                          if r["ok"] and r[col] is not None], dtype=float)) * 100 for c in clutter]
            ax_c.plot(x, cov, style, color=color, label=f"{level}, {'tilt' if col == 'ci_contains' else 'height'}")
    ax_c.axhspan(TARGET_COVERAGE[0] * 100, TARGET_COVERAGE[1] * 100, color="#2ca02c", alpha=0.15, label="target")
    ax_e.set_yscale("log")
    ax_e.set_ylabel("mean |tilt error|, deg")
    ax_c.set_ylabel("95 % interval coverage, %")
    for ax in (ax_e, ax_c):
        ax.set_xlabel("plane pixels hidden by boxes, %")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle("Full frame per ToF artefact level (heights 0.46-0.61 m, 80 deg, default noise)", fontsize=11)
    fig.tight_layout(rect=(0, 0, 1, 0.95))
    return save_figure(fig, path)


def inlier_image(trial: TrialData) -> NDArray[np.bool_] | None:
    """The full-frame inlier mask of a trial as an (H, W) image, or None."""
    res = trial.full_frame
    if res is None:
        return None
    h, w = trial.frame.valid.shape
    for name in ("inlier_mask", "inliers"):
        mask = getattr(res, name, None)
        if mask is None:
            continue
        mask = np.asarray(mask, dtype=bool)
        if mask.shape == (h, w):
            return mask
        if mask.ndim == 1 and mask.size == int(np.count_nonzero(trial.frame.valid)):
            img = np.zeros((h, w), dtype=bool)
            img[trial.frame.valid] = mask
            return img
    return None


def plot_plane_fit(trial: TrialData, path: str | Path, *, max_points: int = 6000, seed: int = 0) -> Path:
    """The full-frame plane over one frame's point cloud: inliers, outliers (boxes), the plane.

    Left: the camera-frame cloud (subsampled to ``max_points``, seeded) with the fitted plane;
    right: the image, inliers vs outliers, with the true box outlines.
    """
    plt = _pyplot()
    inl = inlier_image(trial)
    if inl is None:  # no full-frame result: colour by the truth instead
        inl = trial.frame.valid & ~trial.occluded_mask
        fit_label = "plane (truth; full frame unavailable)"
        plane = trial.truth.plane_cam
    else:
        fit_label = "full-frame plane"
        plane = trial.full_frame.plane
    fig = plt.figure(figsize=(11.5, 5.4))
    _draw_cloud(fig.add_subplot(1, 2, 1, projection="3d"), trial, inl, plane, fit_label,
                np.random.default_rng(seed), max_points)
    _draw_image(fig.add_subplot(1, 2, 2), trial, inl)
    fig.subplots_adjust(left=0.0, right=0.97, top=0.9, bottom=0.2, wspace=0.12)
    return save_figure(fig, path)


def _draw_cloud(ax: Any, trial: TrialData, inl: NDArray[np.bool_], plane: Any, fit_label: str,
                rng: np.random.Generator, max_points: int) -> None:
    """The camera-frame cloud (random subsample), inliers vs outliers, and the plane as a wireframe."""
    valid = trial.frame.valid
    pts = trial.frame.xyz[valid].astype(np.float64)
    is_in = inl[valid]
    idx = rng.permutation(pts.shape[0])[:max_points]
    p, flag = pts[idx], is_in[idx]
    # drawn as (x, -y, -z): image right, image up, toward the camera (boxes stand up)
    ax.scatter(p[flag, 0], -p[flag, 1], -p[flag, 2], s=0.6, c="#4c72b0", alpha=0.5, label="inliers",
               depthshade=False)
    ax.scatter(p[~flag, 0], -p[~flag, 1], -p[~flag, 2], s=0.8, c="#dd3322", alpha=0.8, label="outliers",
               depthshade=False)
    # the plane over the cloud's x/y extent (1st-99th percentiles), on a 12 x 12 grid
    x0, x1 = float(np.percentile(pts[:, 0], 1)), float(np.percentile(pts[:, 0], 99))
    y0, y1 = float(np.percentile(pts[:, 1], 1)), float(np.percentile(pts[:, 1], 99))
    gx, gy = np.meshgrid(np.linspace(x0, x1, 12), np.linspace(y0, y1, 12))
    n, d = plane.normal, plane.offset_m
    if abs(n[2]) > 1e-9:  # solve n . (x, y, z) + d = 0 for z (skip a plane containing the optical axis)
        gz = -(n[0] * gx + n[1] * gy + d) / n[2]
        ax.plot_wireframe(gx, -gy, -gz, color="k", linewidth=0.5, alpha=0.7, label=fit_label)
    ax.set_xlabel("x, m")
    ax.set_ylabel("-y, m")
    ax.set_zlabel("-z (depth), m")
    ax.view_init(elev=28, azim=-58)
    ax.set_box_aspect((1.5, 1.0, 0.7))
    ax.legend(loc="upper left", fontsize=8, markerscale=8)
    c = trial.condition
    ax.set_title(f"camera-frame cloud: height {c.height_m:.2f} m, {c.inclination_deg:g} deg,\n"
                 f"{trial.clutter_achieved * 100:.0f} % of the plane hidden by boxes", fontsize=9)


def _draw_image(ax: Any, trial: TrialData, inl: NDArray[np.bool_]) -> None:
    """The image coloured by inlier, outlier and invalid, with the true box outlines and the errors."""
    valid = trial.frame.valid
    img = np.full((*valid.shape, 3), 0.85)  # grey: invalid
    img[valid & inl] = (0.30, 0.45, 0.69)
    img[valid & ~inl] = (0.87, 0.20, 0.13)
    ax.imshow(img, interpolation="nearest")
    if trial.occluded_mask.any():
        ax.contour(trial.occluded_mask.astype(float), levels=[0.5], colors="k", linewidths=0.8)
    ax.set_title("image: inliers (blue), outliers (red), invalid (grey);\nblack: true box outlines", fontsize=9)
    ax.set_xlabel("u, px")
    ax.set_ylabel("v, px")
    text = _trial_errors(trial)
    if text:
        ax.text(0.0, -0.12, text, transform=ax.transAxes, fontsize=8, va="top", family="monospace")


def _trial_errors(trial: TrialData) -> str:
    res = trial.full_frame
    true_tilt = 90.0 - math.degrees(trial.truth.angle_rad)
    if res is None:
        return f"true tilt {true_tilt:.3f} deg"
    tilt = 90.0 - math.degrees(float(res.angle_rad))
    lo, hi = (90.0 - math.degrees(float(v)) for v in reversed(res.angle_ci_rad))
    return (f"true tilt {true_tilt:.4f} deg, full frame {tilt:.4f} deg (error {tilt - true_tilt:+.4f} deg)\n"
            f"95 % interval {lo:.4f}..{hi:.4f} deg; {res.inlier_fraction * 100:.1f} % of the valid pixels are inliers")


def write_plots(result: StudyResult, out_dir: str | Path, jobs: int = 1) -> dict[str, Path]:
    """Write every picture of a study run into ``out_dir``; returns name -> path.

    Args:
        result: The study's rows and example trial.
        out_dir: Folder for the PNG files.
        jobs: Worker processes drawing the pictures side by side (1: in this process).

    Raises:
        MissingDependencyError: If matplotlib is not installed (extra ``plots``).
    """
    from cellcal.core.study.pool import run_calls

    _pyplot()  # imported once here: forked workers inherit it (and a missing matplotlib is said here)
    out = Path(out_dir)
    all_rows = result.rows
    rows = select(all_rows, artefacts=headline_level(all_rows))  # one artefact level in the other plots
    calls: dict[str, tuple[Any, tuple[Any, ...]]] = {
        "perimeter": (plot_error_vs_perimeter, (rows, out / PLOT_FILES["perimeter"]))}
    if len({r["clutter_target"] for r in rows}) > 1:
        calls["clutter"] = (plot_error_vs_clutter, (rows, out / PLOT_FILES["clutter"]))
    if len({r["noise_scale"] for r in rows}) > 1 or len({r["inclination_deg"] for r in rows}) > 1:
        calls["conditions"] = (plot_error_vs_conditions, (rows, out / PLOT_FILES["conditions"]))
    if len({r.get("artefacts") for r in all_rows}) > 1:
        calls["artefacts"] = (plot_artefacts, (all_rows, out / PLOT_FILES["artefacts"]))
    if result.example is not None:
        calls["plane"] = (plot_plane_fit, (result.example, out / PLOT_FILES["plane"]))
    # the perimeter picture, the slowest, is first: it starts at once
    return dict(zip(calls, run_calls(list(calls.values()), jobs), strict=True))


__all__ = ["PLOT_FILES", "inlier_image", "plot_artefacts", "plot_error_vs_clutter", "plot_error_vs_conditions",
           "plot_error_vs_perimeter", "plot_plane_fit", "save_figure", "write_plots"]
