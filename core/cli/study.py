"""``cellcal study``: Monte Carlo accuracy study on the simulated cell.

Writes ``DIR/study.csv`` (one row per trial x method x perimeter), ``DIR/headline.json``
(the issues' figures at the paper's settings) and the PNG plots, and prints a summary per
ToF artefact level (off, all-but-multipath, all: ADR 0012, ADR 0014).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from cellcal.core.cli.argtypes import integer, path_arg
from cellcal.core.cli.progress import progress_factory
from cellcal.core.study.design import (
    ARTEFACT_LEVELS,
    BASE_ARTEFACTS,
    TARGET_CLUTTER,
    TARGET_COVERAGE,
    TARGET_ERROR_CLUTTER_DEG,
    TARGET_ERROR_DEG,
    StudySettings,
    quick_settings,
)

if TYPE_CHECKING:  # the trials (numpy, the sim) are imported by run(), not by `cellcal --help`
    from cellcal.core.study.table import Headline

CSV_NAME = "study.csv"
HEADLINE_NAME = "headline.json"
DEFAULT_TRIALS = 20
DEFAULT_QUICK_TRIALS = 8
#: Largest image side ``--resolution`` accepts (the sim camera's limit), px.
MAX_SIDE_PX = 4096
#: Most worker processes ``--jobs`` accepts.
MAX_JOBS = 1024


def artefact_levels(text: str) -> tuple[str, ...]:
    """``--artefacts``: comma-separated levels out of :data:`ARTEFACT_LEVELS` (usage error otherwise)."""
    levels = tuple(dict.fromkeys(t.strip() for t in text.split(",") if t.strip()))
    bad = [t for t in levels if t not in ARTEFACT_LEVELS]
    if bad or not levels:
        raise argparse.ArgumentTypeError(f"expected some of {','.join(ARTEFACT_LEVELS)} separated by commas, "
                                         f"got {text!r}")
    return levels


def resolution(text: str) -> tuple[int, int]:
    """``--resolution``: ``WIDTHxHEIGHT`` in pixels, each 2..4096 (usage error otherwise)."""
    parts = text.lower().split("x")
    try:
        w, h = (int(v) for v in parts)
    except ValueError:
        w = h = 0
    if len(parts) != 2 or not (2 <= w <= MAX_SIDE_PX and 2 <= h <= MAX_SIDE_PX):
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT in pixels (2..{MAX_SIDE_PX} each), got {text!r}")
    return w, h


def register(sub: Any) -> None:
    """Add the ``study`` subcommand."""
    p = sub.add_parser("study", help="Monte Carlo accuracy study of every method on the simulated cell",
                       description="Run the calibration methods (law of cosines, nine-point fit with the paper's "
                       "nominal field of view and with the real intrinsics, full frame) on simulated frames over "
                       "heights, inclinations, noise levels and clutter (boxes on the plane); write study.csv, "
                       "headline.json and PNG plots, and print the headline figures at the paper's settings.")
    p.add_argument("--trials", type=integer(ge=1, le=100_000), default=None, metavar="N",
                   help=f"trials per condition (default {DEFAULT_TRIALS}, with --quick {DEFAULT_QUICK_TRIALS}); "
                   "the headline conditions run 4x as many")
    p.add_argument("--out", metavar="DIR", default="cellcal-study", type=path_arg,
                   help="output directory (default: %(default)s)")
    p.add_argument("--seed", type=integer(ge=0, le=2**32 - 1), default=0, metavar="S",
                   help="root seed (default: %(default)s)")
    p.add_argument("--quick", action="store_true",
                   help="small design: the paper's heights and inclination, no clutter and 30 %% clutter, "
                   f"ToF artefacts {BASE_ARTEFACTS} only (unless --artefacts says otherwise)")
    p.add_argument("--artefacts", type=artefact_levels, default=None, metavar="LEVELS",
                   help=f"ToF artefact levels of the clutter sweep, comma-separated out of {','.join(ARTEFACT_LEVELS)} "
                   f"(default: all three; with --quick {BASE_ARTEFACTS}); the other sweeps and the headline use "
                   f"{BASE_ARTEFACTS} if listed, else the first")
    p.add_argument("--resolution", type=resolution, default=None, metavar="WxH",
                   help="image size of the simulated camera, e.g. 1280x800 (default: 224x172, the O3R222's; "
                   "the field of view stays 60 x 45 deg)")
    p.add_argument("--jobs", type=integer(ge=1, le=MAX_JOBS), default=None, metavar="N",
                   help="worker processes for the trials (default: every core this process may use); "
                   "the results are the same for any N")
    p.add_argument("--no-plots", action="store_true", help="write the CSV and headline only")
    p.add_argument("--quiet", action="store_true", help="no progress bar or table; only the output paths")
    p.set_defaults(func=run)


def study_resolution(settings: StudySettings) -> tuple[int, int]:
    """Image size (width, height) of the study's camera, px."""
    cam = settings.camera
    return int(cam.get("width", 224)), int(cam.get("height", 172))


def _fmt(value: float | None, spec: str = ".4f", unit: str = "") -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "n/a"
    return f"{value:{spec}}{unit}"


def _scaled(value: float | None, factor: float, spec: str, unit: str) -> str:
    return _fmt(None if value is None else value * factor, spec, unit)


def _verdict(ok: bool | None) -> str:
    return "n/a" if ok is None else ("met" if ok else "MISSED")


def _pct(value: float | None) -> str:
    return _fmt(None if value is None else value * 100, ".1f", " %")


def format_headline(h: Headline) -> str:
    """The headline figures and the issues' targets, as text."""
    cov = h.full_frame_coverage
    cov_c = h.full_frame_coverage_clutter
    by_clutter = ", ".join(f"{c * 100:.0f} %: {_pct(t)} / {_pct(z)}" for c, t, z in h.coverage_by_clutter)
    lines = [
        f"Paper settings (heights 0.46/0.59/0.61 m, 80 deg, default noise, ToF artefacts {h.artefacts}): "
        f"{h.n_trials} frames clean, "
        f"{h.n_trials_clutter} with {TARGET_CLUTTER * 100:.0f} % clutter "
        f"(achieved {_fmt(None if h.clutter_achieved_mean is None else h.clutter_achieved_mean * 100, '.1f', ' %')})",
        f"  full frame, mean |tilt error|        {_fmt(h.full_frame_error_deg)} deg   "
        f"(target <= {TARGET_ERROR_DEG} deg: {_verdict(h.meets_error)})",
        f"  full frame, 30 % clutter             {_fmt(h.full_frame_error_clutter_deg)} deg   "
        f"(target <= {TARGET_ERROR_CLUTTER_DEG} deg: {_verdict(h.meets_error_clutter)})",
        f"  full frame, 95 % interval coverage   {_fmt(None if cov is None else cov * 100, '.1f', ' %')}    "
        f"(target {TARGET_COVERAGE[0] * 100:.0f}-{TARGET_COVERAGE[1] * 100:.0f} %: {_verdict(h.meets_coverage)}); "
        f"with clutter {_fmt(None if cov_c is None else cov_c * 100, '.1f', ' %')}",
        f"  full frame, height                   mean |error| "
        f"{_scaled(h.full_frame_height_error_m, 1000, '.3f', ' mm')}, "
        f"95 % interval coverage {_scaled(h.full_frame_height_coverage, 100, '.1f', ' %')}",
        f"  full frame, coverage tilt / height by clutter: {by_clutter or 'n/a'} "
        f"(target {TARGET_COVERAGE[0] * 100:.0f}-{TARGET_COVERAGE[1] * 100:.0f} % at 0-40 %: "
        f"{_verdict(h.meets_coverage_clutter)})",
        f"  full-frame fits that raised: {h.full_frame_failures} clean, {h.full_frame_failures_clutter} cluttered",
        f"  nine-point, nominal FOV (paper)      {_fmt(h.nominal_error_deg)} deg   "
        f"(30 % clutter: {_fmt(h.nominal_error_clutter_deg)} deg)",
        f"  nine-point, real intrinsics          {_fmt(h.plane_fit_error_deg)} deg",
        f"  law of cosines                       {_fmt(h.law_of_cosines_error_deg)} deg",
    ]
    return "\n".join(lines)


def format_summary(rows: list[dict[str, Any]]) -> str:
    """Per artefact level, method and clutter level: n, failures, mean/median/p95 |tilt error| (deg),
    mean |height error| (mm), tilt and height interval coverage, gates passed."""
    from cellcal.core.study.table import summary_table

    head = (f"{'artefacts':<17} {'method':<18} {'clutter':>7} {'n':>5} {'fail':>5} {'mean':>9} {'median':>9} "
            f"{'p95':>9} {'|dh| mm':>8} {'cover':>6} {'h cov':>6} {'gates':>6}")
    out = [head, "-" * len(head)]
    for r in summary_table(rows):
        cov = "" if r["coverage"] is None else f"{r['coverage'] * 100:.1f}%"
        hcov = "" if r["height_coverage"] is None else f"{r['height_coverage'] * 100:.1f}%"
        gates = "" if r["gates_passed"] is None else f"{r['gates_passed'] * 100:.0f}%"
        dh = "" if r["mean_height_error_m"] is None else f"{r['mean_height_error_m'] * 1000:.3f}"
        out.append(f"{r['artefacts']:<17} {r['method']:<18} {r['clutter'] * 100:>6.0f}% {r['n']:>5} {r['failed']:>5} "
                   f"{r['mean_deg']:>9.4f} {r['median_deg']:>9.4f} {r['p95_deg']:>9.4f} {dh:>8} {cov:>6} {hcov:>6} "
                   f"{gates:>6}")
    return "\n".join(out)


def _settings(args: argparse.Namespace) -> StudySettings:
    """The study design the options ask for."""
    levels = args.artefacts
    extra: dict[str, Any] = {}
    if levels is not None:
        extra["artefact_levels"] = levels
        extra["base_artefacts"] = BASE_ARTEFACTS if BASE_ARTEFACTS in levels else levels[0]
    if args.resolution is not None:
        extra["camera"] = {"width": args.resolution[0], "height": args.resolution[1]}
    if args.quick:
        base = quick_settings(trials=args.trials or DEFAULT_QUICK_TRIALS, seed=args.seed)
    else:
        base = StudySettings(trials=args.trials or DEFAULT_TRIALS, seed=args.seed)
    return dataclasses.replace(base, **extra)


def run(args: argparse.Namespace) -> int:
    """Run ``cellcal study``; returns the exit status.

    The output directory is locked first (one run at a time; a path that cannot be
    written fails before the trials, not after).
    """
    from cellcal.core.calibration.outlock import OutputLock

    settings = _settings(args)
    out = Path(args.out)
    with OutputLock.for_directory(out):
        return _run(args, settings, out)


def _run(args: argparse.Namespace, settings: StudySettings, out: Path) -> int:
    from cellcal.core.calibration.report import write_json_atomic
    from cellcal.core.study.pool import default_jobs
    from cellcal.core.study.table import headline, write_csv
    from cellcal.core.study.trials import run_study

    progress = progress_factory("trials", "trial", args.quiet)
    jobs = args.jobs if args.jobs is not None else default_jobs()
    started = time.perf_counter()
    result = run_study(settings, progress=progress, jobs=jobs)
    elapsed = time.perf_counter() - started
    csv_path = write_csv(out / CSV_NAME, result.rows)
    head = headline(result.rows)
    n_trials = len({(r["height_m"], r["inclination_deg"], r["noise_scale"], r["clutter_target"], r["artefacts"],
                     r["trial"]) for r in result.rows})
    write_json_atomic(out / HEADLINE_NAME, {**head.to_dict(), "trials_total": n_trials,
                                            "trials_per_condition": settings.trials, "seed": settings.seed,
                                            "quick": bool(args.quick), "elapsed_s": elapsed, "jobs": jobs,
                                            "artefact_levels": list(settings.artefact_levels),
                                            "resolution_px": [int(v) for v in study_resolution(settings)],
                                            "full_frame_available": result.full_frame_available})
    paths: dict[str, Path] = {}
    if not args.no_plots:
        from cellcal.core.study.plots import write_plots

        paths = write_plots(result, out, jobs)
    if not args.quiet:
        print(format_summary(result.rows))
        print()
        print(format_headline(head))
        if not result.full_frame_available:
            print("  (cellcal.core.methods.fullframe not found: full frame not run)")
        print(f"{n_trials} trials in {elapsed:.1f} s ({jobs} process{'es' if jobs > 1 else ''})")
    print(f"study written to {csv_path}" + (f" (+ {HEADLINE_NAME}, {len(paths)} plots)" if paths else
                                            f" (+ {HEADLINE_NAME})"))
    return 0
