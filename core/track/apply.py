"""``cellcal track --apply``: the tracked mount and plane as a versioned calibration file, history kept.

``DIR/calibration.json`` (schema ``cellcal.track-calibration/1``) carries the mount as
``[mount] from_handeye`` reads it, the base-frame plane and their intervals. It is replaced
atomically, and only when the estimate passes every gate; the file it replaces is kept as
``DIR/history/calibration.vN.json``.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from cellcal.core.handeye.model import PARAMETERS

#: Schema of the applied file (``[mount] from_handeye`` accepts it).
CALIBRATION_SCHEMA = "cellcal.track-calibration/1"
CALIBRATION_FILENAME = "calibration.json"
HISTORY_DIR = "history"
#: The mount's six parameters, all of which must have been seen before a mount is applied.
MOUNT_PARAMETERS = PARAMETERS[:6]


def refusal(document: Mapping[str, Any]) -> str | None:
    """Why a ``track.json`` document must not be applied, or None when it may be.

    The gates: no change detected and still open; every mount parameter seen; intervals
    given (the noise is as stated or the intervals were scaled to it, not withheld).
    """
    if document.get("change_unresolved"):
        return "a change was detected and the frames after it have not shown every parameter again"
    observable = document.get("observable", {})
    unseen = [p for p in MOUNT_PARAMETERS if not observable.get(p, False)]
    if unseen:
        return f"the work has not shown {', '.join(unseen)} yet"
    intervals = document.get("intervals", {})
    if intervals.get("withheld"):
        return f"no intervals: {intervals['withheld']}"
    sigma = document.get("mount", {}).get("rpy_sigma_deg")
    if not isinstance(sigma, list) or not all(isinstance(v, (int, float)) and math.isfinite(v) for v in sigma):
        return "the mount has no intervals"
    return None


def current_version(out_dir: str | Path) -> int:
    """The version of ``DIR/calibration.json`` (0 when there is none or it cannot be read)."""
    from cellcal.devices import boundedjson

    path = Path(out_dir) / CALIBRATION_FILENAME
    try:
        version = boundedjson.loads(path.read_text(encoding="utf-8")).get("version", 0)
    except (OSError, ValueError, AttributeError):
        return 0
    return version if isinstance(version, int) and version >= 0 else 0


def apply(out_dir: str | Path, document: Mapping[str, Any]) -> tuple[Path, int] | str:
    """Write ``DIR/calibration.json`` from a ``track.json`` document when it passes the gates.

    Returns:
        ``(path, version)`` when written, else the refusal (one sentence); nothing is touched then.

    Raises:
        OutputError: If the directory cannot be written.
    """
    from cellcal.core.calibration.report import write_json_atomic

    why = refusal(document)
    if why is not None:
        return why
    out = Path(out_dir)
    path = out / CALIBRATION_FILENAME
    version = current_version(out) + 1
    if path.exists():  # the file it replaces is kept, by version
        history = out / HISTORY_DIR
        history.mkdir(parents=True, exist_ok=True)
        os.replace(path, history / f"calibration.v{version - 1}.json")
    calibration = {
        "schema": CALIBRATION_SCHEMA, "version": version,
        "meta": dict(document.get("meta", {})),
        "mount": document["mount"], "plane": document["plane"], "intervals": document["intervals"],
        "observable": document["observable"], "frames_used": document.get("frames_used"),
        "events": document.get("events", []),
    }
    write_json_atomic(path, calibration)
    return path, version


__all__ = ["CALIBRATION_FILENAME", "CALIBRATION_SCHEMA", "apply", "current_version", "refusal"]
