"""The study's rows as a table: CSV text and files, row selection, headline figures, summary.

Angles in the rows are degrees and lengths metres (a human-facing table).
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cellcal.core.calibration.report import write_bytes_atomic
from cellcal.core.study.design import (
    ARTEFACT_LEVELS,
    BASE_ARTEFACTS,
    FULL_FRAME,
    METHODS,
    PAPER_HEIGHTS_M,
    PAPER_INCLINATION_DEG,
    TARGET_CLUTTER,
    TARGET_COVERAGE,
    TARGET_COVERAGE_CLUTTER,
    TARGET_ERROR_CLUTTER_DEG,
    TARGET_ERROR_DEG,
)
from cellcal.devices.errors import CalibrationError

__all__ = [
    "COLUMNS",
    "Headline",
    "headline",
    "headline_level",
    "read_csv",
    "rows_to_csv",
    "select",
    "summary_table",
    "write_csv",
    "write_text_atomic",
]

#: CSV columns, in order (one row per trial x method x perimeter; full frame has no perimeter).
COLUMNS: tuple[str, ...] = (
    "trial", "seed", "height_m", "inclination_deg", "noise_scale", "clutter_target", "artefacts", "clutter_achieved",
    "clutter_observed", "n_boxes", "method", "perimeter_px", "ok", "true_angle_deg", "est_angle_deg",
    "angle_error_deg", "true_tilt_deg", "est_tilt_deg", "tilt_error_deg", "abs_tilt_error_deg",
    "normal_error_deg", "true_height_m", "est_height_m", "height_error_m", "sigma_tilt_deg",
    "ci_lo_deg", "ci_hi_deg", "ci_contains", "height_ci_contains", "inlier_fraction", "gates_passed", "message",
)


# ---------------------------------------------------------------------- CSV
def _cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return "" if math.isnan(value) else repr(value)
    return str(value)


def rows_to_csv(rows: Iterable[Mapping[str, Any]]) -> str:
    """The rows as CSV text (columns :data:`COLUMNS`; NaN and None as empty cells)."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(COLUMNS)
    for r in rows:
        writer.writerow([_cell(r.get(c)) for c in COLUMNS])
    return buf.getvalue()


def write_text_atomic(path: str | Path, text: str) -> Path:
    """Write UTF-8 text atomically (:func:`~cellcal.core.calibration.report.write_bytes_atomic`).

    Raises:
        CalibrationError: If the file cannot be written.
    """
    return write_bytes_atomic(path, text.encode("utf-8"))


def write_csv(path: str | Path, rows: Iterable[Mapping[str, Any]]) -> Path:
    """Write the rows to ``path`` atomically; returns the path."""
    return write_text_atomic(path, rows_to_csv(rows))


_BOOL_COLUMNS = ("ci_contains", "height_ci_contains", "gates_passed")
_TEXT_COLUMNS = ("method", "message", "artefacts")


def _parse_cell(column: str, text: str) -> Any:
    if text == "":
        return None if column in _BOOL_COLUMNS else (math.nan if column not in _TEXT_COLUMNS else "")
    if column in _TEXT_COLUMNS:
        return text
    if column in _BOOL_COLUMNS or column == "ok":
        return text == "true"
    if column in ("trial", "seed", "n_boxes", "perimeter_px"):
        return int(text)
    return float(text)


def read_csv(path: str | Path) -> list[dict[str, Any]]:
    """Read a study CSV back into rows (inverse of :func:`write_csv`).

    Raises:
        CalibrationError: If the file is missing or lacks a column.
    """
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as exc:
        raise CalibrationError(f"cannot read {path}: {exc.strerror or exc}") from None
    reader = csv.DictReader(io.StringIO(text))
    missing = [c for c in COLUMNS if c not in (reader.fieldnames or [])]
    if missing:
        raise CalibrationError(f"{path}: not a study CSV (missing column(s) {', '.join(missing)})")
    rows = []
    for r in reader:
        row = {c: _parse_cell(c, r[c]) for c in COLUMNS}
        if row["perimeter_px"] is not None and isinstance(row["perimeter_px"], float):
            row["perimeter_px"] = None
        rows.append(row)
    return rows


# ---------------------------------------------------------------------- headline figures
def select(rows: Iterable[Mapping[str, Any]], **match: Any) -> list[Mapping[str, Any]]:
    """Rows whose columns equal the given values (floats compared to 1e-9; a tuple means any of)."""
    def ok(row: Mapping[str, Any]) -> bool:
        for k, want in match.items():
            have = row.get(k)
            options = want if isinstance(want, tuple) else (want,)
            if not any(_same(have, w) for w in options):
                return False
        return True
    return [r for r in rows if ok(r)]


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, float) and isinstance(b, (int, float)) and not isinstance(b, bool):
        return abs(a - float(b)) <= 1e-9
    return bool(a == b)


@dataclass(frozen=True)
class Headline:
    """The issues' figures at the paper's settings (heights 0.46/0.59/0.61 m, 80 deg, default
    noise) and one ToF artefact level (:data:`~cellcal.core.study.design.BASE_ARTEFACTS`).

    Errors are mean absolute tilt errors in degrees over all trials (and, for the
    paper's methods, all perimeters); a failed estimate counts as missing and is
    reported in the ``*_failures`` counts. Coverage is the fraction of full-frame
    fits whose 95 % interval holds the truth. The height figures are for the
    full frame without clutter (mean |error| in metres, interval coverage).
    ``coverage_by_clutter`` holds ``(clutter, tilt coverage, height coverage)`` of the
    full frame at each clutter level of 0-40 %. None where the run had no such trials.
    """

    n_trials: int
    n_trials_clutter: int
    full_frame_error_deg: float | None
    full_frame_error_clutter_deg: float | None
    full_frame_coverage: float | None
    full_frame_coverage_clutter: float | None
    full_frame_failures: int
    full_frame_failures_clutter: int
    nominal_error_deg: float | None
    plane_fit_error_deg: float | None
    law_of_cosines_error_deg: float | None
    nominal_error_clutter_deg: float | None
    clutter_achieved_mean: float | None
    full_frame_height_error_m: float | None = None
    full_frame_height_coverage: float | None = None
    artefacts: str = BASE_ARTEFACTS
    coverage_by_clutter: tuple[tuple[float, float | None, float | None], ...] = ()

    @property
    def meets_error(self) -> bool | None:
        """Full-frame error without clutter <= 0.05 deg."""
        e = self.full_frame_error_deg
        return None if e is None else e <= TARGET_ERROR_DEG

    @property
    def meets_error_clutter(self) -> bool | None:
        """Full-frame error with 30 % clutter <= 0.1 deg."""
        e = self.full_frame_error_clutter_deg
        return None if e is None else e <= TARGET_ERROR_CLUTTER_DEG

    @property
    def meets_coverage(self) -> bool | None:
        """95 % interval coverage (no clutter) within 93-97 %."""
        c = self.full_frame_coverage
        return None if c is None else TARGET_COVERAGE[0] <= c <= TARGET_COVERAGE[1]

    @property
    def meets_coverage_clutter(self) -> bool | None:
        """Tilt and height interval coverage within 93-97 % at every clutter level of 0-40 %."""
        vals = [v for _, tilt, height in self.coverage_by_clutter for v in (tilt, height)]
        if not vals or any(v is None for v in vals):
            return None
        return all(TARGET_COVERAGE[0] <= v <= TARGET_COVERAGE[1] for v in vals if v is not None)

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (with the target checks)."""
        out = {k: getattr(self, k) for k in self.__dataclass_fields__}
        out["coverage_by_clutter"] = [list(c) for c in self.coverage_by_clutter]
        out.update(meets_error=self.meets_error, meets_error_clutter=self.meets_error_clutter,
                   meets_coverage=self.meets_coverage, meets_coverage_clutter=self.meets_coverage_clutter)
        return out


def _mean_of(values: Sequence[float]) -> float | None:
    return float(np.mean(values)) if len(values) else None


def _mean_abs(rows: Sequence[Mapping[str, Any]]) -> float | None:
    vals = [r["abs_tilt_error_deg"] for r in rows if r.get("ok")]
    return float(np.mean(vals)) if vals else None


def _coverage(rows: Sequence[Mapping[str, Any]], column: str = "ci_contains") -> float | None:
    vals = [bool(r[column]) for r in rows if r.get("ok") and r.get(column) is not None]
    return float(np.mean(vals)) if vals else None


def headline_level(rows: Sequence[Mapping[str, Any]]) -> str:
    """The artefact level of the headline: the base level if the rows have it, else the first they have."""
    levels = [r.get("artefacts") for r in rows]
    if BASE_ARTEFACTS in levels or not levels:
        return BASE_ARTEFACTS
    return next((a for a in ARTEFACT_LEVELS if a in levels), str(levels[0]))


def _coverage_by_clutter(ff: Sequence[Mapping[str, Any]]) -> tuple[tuple[float, float | None, float | None], ...]:
    lo, hi = TARGET_COVERAGE_CLUTTER
    levels = sorted({float(r["clutter_target"]) for r in ff if lo - 1e-9 <= r["clutter_target"] <= hi + 1e-9})
    return tuple((c, _coverage(select(ff, clutter_target=c)),
                  _coverage(select(ff, clutter_target=c), "height_ci_contains")) for c in levels)


def headline(rows: Sequence[Mapping[str, Any]], artefacts: str | None = None) -> Headline:
    """The issues' headline figures from study rows (see :class:`Headline`).

    Args:
        rows: Study rows.
        artefacts: Artefact level to report; None: :func:`headline_level`.
    """
    level = artefacts or headline_level(rows)
    paper = select(rows, height_m=PAPER_HEIGHTS_M, inclination_deg=PAPER_INCLINATION_DEG, noise_scale=1.0,
                   artefacts=level)
    clean = select(paper, clutter_target=0.0)
    clut = select(paper, clutter_target=TARGET_CLUTTER)
    ff, ffc = select(clean, method=FULL_FRAME), select(clut, method=FULL_FRAME)
    trials_clean = {(r["height_m"], r["trial"]) for r in clean}
    trials_clut = {(r["height_m"], r["trial"]) for r in clut}
    achieved = list({(r["height_m"], r["trial"]): r["clutter_achieved"] for r in clut}.values())
    return Headline(
        n_trials=len(trials_clean), n_trials_clutter=len(trials_clut),
        full_frame_error_deg=_mean_abs(ff), full_frame_error_clutter_deg=_mean_abs(ffc),
        full_frame_coverage=_coverage(ff), full_frame_coverage_clutter=_coverage(ffc),
        full_frame_failures=sum(1 for r in ff if not r["ok"]),
        full_frame_failures_clutter=sum(1 for r in ffc if not r["ok"]),
        nominal_error_deg=_mean_abs(select(clean, method="plane_fit_nominal")),
        plane_fit_error_deg=_mean_abs(select(clean, method="plane_fit")),
        law_of_cosines_error_deg=_mean_abs(select(clean, method="law_of_cosines")),
        nominal_error_clutter_deg=_mean_abs(select(clut, method="plane_fit_nominal")),
        clutter_achieved_mean=float(np.mean(achieved)) if achieved else None,
        full_frame_height_error_m=_mean_of([abs(r["height_error_m"]) for r in ff if r["ok"]]),
        full_frame_height_coverage=_coverage(ff, "height_ci_contains"),
        artefacts=level, coverage_by_clutter=_coverage_by_clutter(select(paper, method=FULL_FRAME)),
    )


def summary_table(rows: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """Per artefact level, clutter level and method at the paper's settings: n, failures,
    mean/median/p95 |tilt error| (deg), mean |height error| (m), tilt and height interval
    coverage and the fraction of fits passing the quality gates (full frame)."""
    paper = select(rows, height_m=PAPER_HEIGHTS_M, inclination_deg=PAPER_INCLINATION_DEG, noise_scale=1.0)
    present = {r.get("artefacts") for r in paper}
    out = []
    for level in [a for a in ARTEFACT_LEVELS if a in present] + sorted(str(a) for a in present - set(ARTEFACT_LEVELS)):
        for clutter in sorted({r["clutter_target"] for r in paper}):
            for method in METHODS:
                sel = select(paper, method=method, clutter_target=clutter, artefacts=level)
                if sel:
                    out.append({"artefacts": level, **_summary_row(sel, method, clutter)})
    return out


def _summary_row(sel: Sequence[Mapping[str, Any]], method: str, clutter: float) -> dict[str, Any]:
    err = np.array([r["abs_tilt_error_deg"] for r in sel if r["ok"]])
    return {"method": method, "clutter": clutter, "n": len(sel), "failed": len(sel) - err.size,
            "mean_deg": float(err.mean()) if err.size else math.nan,
            "median_deg": float(np.median(err)) if err.size else math.nan,
            "p95_deg": float(np.percentile(err, 95)) if err.size else math.nan,
            "mean_height_error_m": _mean_of([abs(r["height_error_m"]) for r in sel if r["ok"]]),
            "coverage": _coverage(sel), "height_coverage": _coverage(sel, "height_ci_contains"),
            "gates_passed": _mean_of([bool(r["gates_passed"]) for r in sel
                                      if r["ok"] and r.get("gates_passed") is not None])}
