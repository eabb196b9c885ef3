"""Loading P1–P9 measurement tables shaped like the paper's Table 2.

CSV columns (header required, extra columns ignored): ``height`` (data-set label,
e.g. ``H1``), ``perimeter_px``, ``point`` (``P1``..``P9``), ``x_mm``, ``y_mm``,
``z_mm`` (camera-frame coordinates in millimetres, converted to metres here).
Each (height, perimeter) pair is one data set and must hold exactly the nine points.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from cellcal.core.methods.grid import GRID_NAMES
from cellcal.devices.errors import CalibrationError

__all__ = ["REQUIRED_COLUMNS", "PaperDataSet", "load_paper_table", "parse_paper_rows"]

REQUIRED_COLUMNS = ("height", "perimeter_px", "point", "x_mm", "y_mm", "z_mm")
_MM = 1e-3


@dataclass(frozen=True)
class PaperDataSet:
    """One (height, perimeter) data set of nine camera-frame points.

    Attributes:
        height: Data-set label from the ``height`` column, e.g. ``"H1"``.
        perimeter_px: Perimeter, pixels.
        points_m: ``{"P1": array([x, y, z]), ...}`` in metres (camera frame).
        first_row: Line number of the set's first row in the file (for messages).
    """

    height: str
    perimeter_px: float
    points_m: dict[str, NDArray[np.float64]] = field(default_factory=dict)
    first_row: int = 0

    @property
    def label(self) -> str:
        """``"H1 / 20 px"``."""
        return f"{self.height} / {self.perimeter_px:g} px"


def _number(text: str | None, column: str, line: int) -> float:
    try:
        value = float((text or "").strip())
    except ValueError:
        raise CalibrationError(f"row {line}: {column} is not a number: {text!r}") from None
    if not math.isfinite(value):
        raise CalibrationError(f"row {line}: {column} must be finite, got {text!r}")
    return value


def parse_paper_rows(rows: Iterable[dict[str, str | None]], *, source: str = "table",
                     first_line: int = 2) -> list[PaperDataSet]:
    """Group already-split CSV rows into validated data sets (in file order).

    Args:
        rows: Dicts keyed by column name (e.g. from :class:`csv.DictReader`).
        source: Name used in messages.
        first_line: File line number of the first row.

    Raises:
        CalibrationError: A non-numeric value, an unknown or repeated point, or an
            incomplete P1–P9 set; the message names the row or the data set.
    """
    sets: dict[tuple[str, float], PaperDataSet] = {}
    for line, row in enumerate(rows, start=first_line):
        if all(not (v or "").strip() for v in row.values() if isinstance(v, str)):
            continue  # blank line
        height = (row.get("height") or "").strip()
        if not height:
            raise CalibrationError(f"{source}: row {line}: height is empty")
        perimeter = _number(row.get("perimeter_px"), "perimeter_px", line)
        if perimeter <= 0:
            raise CalibrationError(f"{source}: row {line}: perimeter_px must be positive, "
                                   f"got {perimeter:g}")
        point = (row.get("point") or "").strip().upper()
        if point not in GRID_NAMES:
            raise CalibrationError(f"{source}: row {line}: point must be one of P1..P9, "
                                   f"got {row.get('point')!r}")
        try:
            xyz = np.array([_number(row.get(c), c, line) for c in ("x_mm", "y_mm", "z_mm")]) * _MM
        except CalibrationError as exc:
            raise CalibrationError(f"{source}: {exc}") from None
        key = (height, perimeter)
        ds = sets.get(key)
        if ds is None:
            ds = sets[key] = PaperDataSet(height, perimeter, {}, line)
        if point in ds.points_m:
            raise CalibrationError(f"{source}: row {line}: {point} repeated in data set {ds.label}")
        ds.points_m[point] = xyz
    if not sets:
        raise CalibrationError(f"{source}: no data rows")
    for ds in sets.values():
        missing = [n for n in GRID_NAMES if n not in ds.points_m]
        if missing:
            raise CalibrationError(
                f"{source}: data set {ds.label} (starting at row {ds.first_row}) is incomplete: "
                f"missing {', '.join(missing)}")
    return list(sets.values())


def load_paper_table(path: str | Path) -> list[PaperDataSet]:
    """Read a Table-2-shaped CSV file into data sets.

    Raises:
        CalibrationError: Unreadable file, missing columns, or any row problem (see
            :func:`parse_paper_rows`).
    """
    p = Path(path)
    try:
        with p.open(newline="", encoding="utf-8-sig") as fh:
            reader = csv.DictReader(fh)
            header = [h.strip() for h in (reader.fieldnames or [])]
            missing = [c for c in REQUIRED_COLUMNS if c not in header]
            if missing:
                raise CalibrationError(f"{p}: missing column(s) {', '.join(missing)} "
                                       f"(need {', '.join(REQUIRED_COLUMNS)})")
            reader.fieldnames = header
            return parse_paper_rows(reader, source=str(p))
    except OSError as exc:
        raise CalibrationError(f"cannot read {p}: {exc.strerror or exc}") from None
    except (UnicodeDecodeError, csv.Error) as exc:
        raise CalibrationError(f"{p}: not a readable CSV file ({type(exc).__name__})") from None
