"""The ``track.json`` document (schema ``cellcal.track/1``), the per-frame ``track.jsonl`` row, atomic writing.

Values are SI (m, rad) except ``rpy_deg`` / ``*_deg``, which read as the ``[mount]`` table
does. A value the work has not shown has no sigma and no interval (``null``) and is named
in ``unseen``; ``observable`` says it per parameter.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from cellcal.core.track.state import TrackState, TrackStep

#: Schema of ``track.json``; bump on any incompatible change.
TRACK_SCHEMA = "cellcal.track/1"
TRACK_FILENAME = "track.json"
FRAMES_FILENAME = "track.jsonl"


def _intervals(value: np.ndarray, sigma: np.ndarray, z: float) -> list[list[float] | None]:
    """``[[lo, hi] or None, ...]`` of ``value ± z sigma`` (None where sigma is NaN: not observable)."""
    return [None if not np.isfinite(sd) else [float(v - z * sd), float(v + z * sd)]
            for v, sd in zip(value, sigma, strict=True)]


def _optional(values: np.ndarray) -> list[float | None]:
    """Floats with NaN as None."""
    return [float(v) if np.isfinite(v) else None for v in np.atleast_1d(values)]


def track_document(state: TrackState, counters: Mapping[str, int], meta: Mapping[str, Any]) -> dict[str, Any]:
    """The ``track.json`` document of a tracker's state.

    Args:
        state: :attr:`Tracker.state` at the end (or at a checkpoint) of the run.
        counters: Frame counts by outcome (``frames``, ``accepted``, ``skipped: <reason>``, ...).
        meta: Run facts (config path, duration, versions): copied under ``meta``.
    """
    z = state.interval_z
    t = state.mount.translation
    rpy = state.mount_rpy_deg
    tilt_sigma = state.plane_tilt_sigma_deg
    offset_sigma = np.array([state.plane_offset_sigma_m])
    plane = state.plane
    return {
        "schema": TRACK_SCHEMA,
        "meta": dict(meta),
        "counters": {str(k): int(v) for k, v in counters.items()},
        "events": [e.to_dict() for e in state.events],
        "change_unresolved": state.change_unresolved,
        "mount": {"translation_m": t.tolist(), "rpy_deg": rpy.tolist(),
                  "translation_sigma_m": _optional(state.mount_translation_sigma_m),
                  "rpy_sigma_deg": _optional(state.mount_rpy_sigma_deg), "pose": state.mount.to_dict()},
        "plane": {"frame": "base", **plane.to_dict(), "point_m": plane.point_m.tolist(),
                  "tilt_sigma_deg": _optional(tilt_sigma), "offset_sigma_m": _optional(offset_sigma)[0]},
        "intervals": {
            "confidence": state.confidence, "z": z, "scale": state.interval_scale,
            "withheld": state.intervals_withheld or None,
            "mount_translation_m": _intervals(t, state.mount_translation_sigma_m, z),
            "mount_rpy_deg": _intervals(rpy, state.mount_rpy_sigma_deg, z),
            "plane_offset_m": _intervals(np.array([plane.offset_m]), offset_sigma, z)[0],
            "noise_model": state.noise.to_dict() if state.noise else None,
            "notes": list(state.interval_notes),
        },
        "observable": dict(state.observable),
        "unseen": list(state.unseen),
        "frames_used": state.frames_used,
    }


def frame_row(step: TrackStep, t_s: float, **extra: Any) -> dict[str, Any]:
    """One ``track.jsonl`` row: the frame's time, innovation, chi2, whether it was used, its event.

    Args:
        step: What :meth:`Tracker.update` returned (``t_s`` is repeated for skipped frames' rows,
            which the caller writes without a step: see ``extra``).
        t_s: Frame time, s.
        extra: More columns (e.g. ``pose_index``, ``fit_ms``), copied as they are.
    """
    return {"t_s": float(t_s), "residual": [float(v) for v in step.residual], "chi2": float(step.chi2),
            "accepted": bool(step.accepted), "note": step.note or None,
            "event": step.event.to_dict() if step.event else None, **extra}


def write_track_json(out_dir: str | Path, doc: Mapping[str, Any]) -> Path:
    """Write ``DIR/track.json`` atomically (temp file + rename; an earlier file stays until it is complete).

    Raises:
        OutputError: If the directory cannot be created or written.
    """
    from cellcal.core.calibration.report import write_json_atomic

    path: Path = write_json_atomic(Path(out_dir) / TRACK_FILENAME, doc)
    return path


__all__ = ["FRAMES_FILENAME", "TRACK_FILENAME", "TRACK_SCHEMA", "frame_row", "track_document", "write_track_json"]
