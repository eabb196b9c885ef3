"""``cellcal paper TABLE.csv``: the paper's two approaches on a Table-2-shaped file.

Prints, per data set, the law-of-cosines and plane-fit angles with their errors
against the true angle (the paper's Tables 3 and 4), then the averages by height and
by perimeter. ``--json`` prints a JSON list instead, one object per data set.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

from cellcal.core.cli.argtypes import integer, real
from cellcal.core.cli.options import check_input_file
from cellcal.devices.errors import CalibrationError

if TYPE_CHECKING:  # the methods (numpy, OpenCV) are imported when the command runs, not by `cellcal --help`
    from cellcal.core.methods.paper_data import PaperDataSet
    from cellcal.devices.geometry.camera_model import NominalFovModel

__all__ = ["evaluate", "register", "run"]

#: Largest measurement table read, bytes (the paper's Table 2 is about 6 KB).
MAX_TABLE_BYTES = 50 << 20


def register(subparsers: Any) -> None:
    """Add the ``paper`` subcommand to the dispatcher."""
    p = subparsers.add_parser(
        "paper",
        help="reproduce the paper's two tilt-measurement approaches from a P1-P9 table",
        description="Run the law-of-cosines and plane-fit approaches of Parpala et al. (2024) "
                    "on a CSV shaped like the paper's Table 2 (columns height, perimeter_px, "
                    "point, x_mm, y_mm, z_mm). Exit status 2 on a malformed file.",
    )
    p.add_argument("table", metavar="TABLE.csv", help="measurement table")
    p.add_argument("--true-angle", type=float, default=80.0, metavar="DEG",
                   help="true angle between plane and optical axis, degrees (default 80)")
    p.add_argument("--fov", type=real(gt=0, lt=180), nargs=2, default=(60.0, 45.0), metavar=("X_DEG", "Y_DEG"),
                   help="nominal field of view, degrees (default 60 45)")
    p.add_argument("--image-size", type=integer(gt=0), nargs=2, default=(224, 172),
                   metavar=("WIDTH", "HEIGHT"), help="image size, pixels (default 224 172)")
    p.add_argument("--json", action="store_true", help="print a JSON list instead of tables")
    p.set_defaults(func=run)


def evaluate(datasets: Sequence[PaperDataSet], true_angle_deg: float,
             model: NominalFovModel) -> list[dict[str, Any]]:
    """Both approaches on every data set, as JSON-ready dicts (degrees, percent)."""
    from cellcal.core.methods.paper import error_pct, paper_methods

    true_rad = math.radians(true_angle_deg)
    out: list[dict[str, Any]] = []
    for ds in datasets:
        try:
            res = paper_methods(ds.points_m, ds.perimeter_px, model)
        except CalibrationError as exc:
            raise CalibrationError(f"data set {ds.label} (row {ds.first_row}): {exc}") from None
        out.append({
            "height": ds.height,
            "perimeter_px": int(ds.perimeter_px) if ds.perimeter_px.is_integer()
            else ds.perimeter_px,
            "law_of_cosines_deg": math.degrees(res.law_of_cosines_rad),
            "plane_fit_deg": math.degrees(res.plane_fit_rad),
            "law_of_cosines_error_pct": error_pct(res.law_of_cosines_rad, true_rad),
            "plane_fit_error_pct": error_pct(res.plane_fit_rad, true_rad),
            "true_angle_deg": true_angle_deg,
            "plane_rms_m": res.fit.rms_m,
            "distance_along_optical_axis_m": _axis_distance(res.fit.plane),
        })
    return out


def _axis_distance(plane: Any) -> float | None:
    try:
        return float(plane.distance_along_optical_axis_m())
    except CalibrationError:
        return None


def _averages(rows: list[dict[str, Any]], key: str) -> list[tuple[Any, dict[str, float]]]:
    groups: dict[Any, list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault(r[key], []).append(r)
    cols = ("law_of_cosines_deg", "law_of_cosines_error_pct", "plane_fit_deg", "plane_fit_error_pct")
    return [(k, {c: sum(r[c] for r in g) / len(g) for c in cols}) for k, g in groups.items()]


def format_report(rows: list[dict[str, Any]], true_angle_deg: float) -> str:
    """Human-readable tables like the paper's Tables 3 and 4."""
    lines = [f"True angle between plane and optical axis: {true_angle_deg:g} deg", ""]
    head = (f"{'data set':<10} {'p (px)':>7}  {'law of cosines (deg)':>20} {'error (%)':>9}  "
            f"{'plane fit (deg)':>15} {'error (%)':>9}")
    lines += [head, "-" * len(head)]
    for r in rows:
        lines.append(f"{r['height']:<10} {r['perimeter_px']:>7}  {r['law_of_cosines_deg']:>20.8f} "
                     f"{r['law_of_cosines_error_pct']:>9.2f}  {r['plane_fit_deg']:>15.4f} "
                     f"{r['plane_fit_error_pct']:>9.2f}")

    def block(title: str, key: str, fmt: Callable[[Any], str]) -> None:
        lines.extend(["", title, head, "-" * len(head)])
        for k, avg in _averages(rows, key):
            lines.append(f"{fmt(k):<18}  {avg['law_of_cosines_deg']:>20.8f} "
                         f"{avg['law_of_cosines_error_pct']:>9.2f}  {avg['plane_fit_deg']:>15.4f} "
                         f"{avg['plane_fit_error_pct']:>9.2f}")

    block("Averages by height", "height", lambda k: str(k))
    block("Averages by perimeter", "perimeter_px", lambda k: f"{k} px")
    n = len(rows)
    lines += ["", f"Overall mean error: law of cosines "
              f"{sum(r['law_of_cosines_error_pct'] for r in rows) / n:.2f} %, plane fit "
              f"{sum(r['plane_fit_error_pct'] for r in rows) / n:.2f} % ({n} data sets)"]
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    """Execute ``cellcal paper``; returns the exit status."""
    true_angle = float(args.true_angle)
    if not (math.isfinite(true_angle) and 0.0 < true_angle <= 90.0):
        raise CalibrationError(f"--true-angle must be in (0, 90] degrees, got {args.true_angle:g}")
    fov_x, fov_y = (float(v) for v in args.fov)
    width, height = (int(v) for v in args.image_size)
    if width <= 0 or height <= 0:
        raise CalibrationError(f"--image-size must be positive, got {width} {height}")
    check_input_file(args.table, MAX_TABLE_BYTES)
    from cellcal.core.methods.paper_data import load_paper_table
    from cellcal.devices.geometry.camera_model import NominalFovModel

    model = NominalFovModel(width, height, math.radians(fov_x), math.radians(fov_y))
    rows = evaluate(load_paper_table(args.table), true_angle, model)
    if args.json:
        import json

        print(json.dumps(rows, indent=2))
    else:
        print(format_report(rows, true_angle))
    return 0
