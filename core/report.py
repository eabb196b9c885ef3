"""Calibration results: the versioned JSON document, atomic writing, and the summary table."""

from __future__ import annotations

import json
import math
import os
import tempfile
from collections import defaultdict
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from cellcal.devices.errors import CalibrationError

#: Version of the result document; bump on any incompatible change.
RESULT_SCHEMA = "cellcal.calibration/1"
RESULT_FILENAME = "result.json"


def _clean(value: Any) -> Any:
    """JSON-safe copy: NaN/inf become None, tuples lists, numpy scalars Python numbers."""
    if isinstance(value, Mapping):
        return {str(k): _clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_clean(v) for v in value]
    if hasattr(value, "tolist"):
        return _clean(value.tolist())
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def write_json_atomic(path: str | Path, document: Mapping[str, Any]) -> Path:
    """Write JSON to ``path`` atomically: a temp file in the same directory, fsync, rename.

    An earlier file at ``path`` is replaced only once the new one is complete, and
    no temporary file is left behind on failure.

    Raises:
        CalibrationError: If the directory cannot be created or written.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        text = json.dumps(_clean(document), indent=2, allow_nan=False) + "\n"
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as exc:
        raise CalibrationError(f"cannot write {path}: {exc.strerror or exc}") from None
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException as exc:
        Path(tmp).unlink(missing_ok=True)
        if isinstance(exc, OSError):
            raise CalibrationError(f"cannot write {path}: {exc.strerror or exc}") from None
        raise
    return path


def summarize(rows: Iterable[Mapping[str, Any]]) -> dict[str, Any]:
    """Mean absolute angle error (%) and mean angle by method: overall, per pose and per perimeter.

    Args:
        rows: Flat measurement rows with keys ``method``, ``pose_index`` (0-based),
            ``perimeter_px``, ``angle_deg`` and (optionally) ``error_pct``.

    Returns:
        ``{method: {"all" | "pose N" | "P px": {n, mean_angle_deg, mean_error_pct, max_error_pct}}}``.
    """
    groups: dict[str, dict[str, list[Mapping[str, Any]]]] = defaultdict(lambda: defaultdict(list))
    for row in rows:
        m = row["method"]
        groups[m]["all"].append(row)
        groups[m][f"pose {row['pose_index'] + 1}"].append(row)
        groups[m][f"{row['perimeter_px']} px"].append(row)
    out: dict[str, Any] = {}
    for method, by in groups.items():
        out[method] = {}
        for key, items in by.items():
            errs = [r["error_pct"] for r in items if r.get("error_pct") is not None]
            angles = [r["angle_deg"] for r in items]
            out[method][key] = {
                "n": len(items),
                "mean_angle_deg": sum(angles) / len(angles),
                "mean_error_pct": sum(errs) / len(errs) if errs else None,
                "max_error_pct": max(errs) if errs else None,
            }
    return out


def format_table(rows: list[Mapping[str, Any]]) -> str:
    """A plain-text summary table: one line per pose x perimeter x method."""
    header = (f"{'pose':>4} {'height_m':>8} {'per_px':>6} {'method':<18} {'angle_deg':>9} {'expect':>7} "
              f"{'err_%':>6} {'tilt_x':>7} {'tilt_y':>7} {'rms_mm':>7}")
    lines = [header, "-" * len(header)]

    def f(v: Any, spec: str, width: int) -> str:
        return f"{v:{width}{spec}}" if isinstance(v, (int, float)) else f"{'-':>{width}}"

    for r in rows:
        rms = r.get("residual_rms_m")
        lines.append(
            f"{r['pose_index'] + 1:>4} {f(r.get('height_m'), '.4f', 8)} {r['perimeter_px']:>6} {r['method']:<18} "
            f"{f(r['angle_deg'], '.3f', 9)} {f(r.get('expected_angle_deg'), '.2f', 7)} "
            f"{f(r.get('error_pct'), '.2f', 6)} {f(r.get('tilt_x_deg'), '.2f', 7)} {f(r.get('tilt_y_deg'), '.2f', 7)} "
            f"{f(None if rms is None else rms * 1000, '.2f', 7)}"
        )
    return "\n".join(lines)
