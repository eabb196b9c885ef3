"""The ``track.json`` document (schema ``cellcal.track/1``), the per-frame ``track.jsonl`` row, atomic writing.

Values are SI (m, rad) except ``rpy_deg`` / ``*_deg``, which read as the ``[mount]`` table
does. A value the work has not shown has no sigma and no interval (``null``) and is named
in ``unseen``; ``observable`` says it per parameter.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from cellcal.core.geometry.planes import Plane
from cellcal.core.track.state import TrackState, TrackStep
from cellcal.devices.pose import Pose

if TYPE_CHECKING:
    from cellcal.core.track.estimator import Tracker

#: Schema of ``track.json``; bump on any incompatible change.
TRACK_SCHEMA = "cellcal.track/1"
#: Schema of a fixed camera's ``track-NAME.json`` (ADR 0061): its view of the plane and how it moved.
FIXED_TRACK_SCHEMA = "cellcal.track-fixed/1"
TRACK_FILENAME = "track.json"
FRAMES_FILENAME = "track.jsonl"


def track_filenames(name: str | None) -> tuple[str, str]:
    """A camera's document and rows: ``track.json`` / ``track.jsonl`` (None: the camera a one-camera cell has,
    or the first on the flange of ``[[cameras]]``), else ``track-NAME.json`` / ``track-NAME.jsonl``."""
    if name is None:
        return TRACK_FILENAME, FRAMES_FILENAME
    return f"track-{name}.json", f"track-{name}.jsonl"


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


def _facing(plane: Plane) -> Plane:
    """The plane with its normal toward the frame's origin (the camera)."""
    return plane if plane.offset_m > 0 else Plane(-plane.normal, -plane.offset_m)


def fixed_track_document(tracker: Tracker, pose: Pose, counters: Mapping[str, int], meta: Mapping[str, Any]
                         ) -> dict[str, Any]:
    """A fixed camera's document (``cellcal.track-fixed/1``): its view of the plane and how far it moved.

    One view of a plane measures its tilt and distance in the camera's frame (``view``) and nothing
    else: a moved camera and a moved plane look alike, which the cameras on the arm tell apart
    (:mod:`~cellcal.core.track.cell`). ``drift`` is the view against the configured plane seen from the
    configured pose (``expected``); ``plane`` is the view taken to the base frame through the configured
    pose (the plane in the base frame if the camera has not moved).

    Args:
        tracker: The camera's tracker (``Tracker(fixed=True)``).
        pose: Its configured ``T_base_camera``.
        counters: Frame counts by outcome.
        meta: Run facts, copied under ``meta``.
    """
    view = tracker.view_plane()
    expected = _facing(tracker.nominal_plane.transformed(pose.inv()))
    tilt = math.degrees(math.acos(min(1.0, abs(float(view.normal @ expected.normal)))))
    base = view.transformed(pose)
    return {
        "schema": FIXED_TRACK_SCHEMA,
        "meta": dict(meta),
        "counters": {str(k): int(v) for k, v in counters.items()},
        "events": [e.to_dict() for e in tracker.state.events],
        "change_unresolved": any(e.resolved_at_s is None for e in tracker.state.events),
        "pose": {"frame": "base", "configured": pose.to_dict(),
                 "note": "track does not re-estimate a fixed camera's pose (cellcal handeye --camera NAME does)"},
        "view": {"frame": "camera", **view.to_dict()},
        "expected": {"frame": "camera", **expected.to_dict()},
        "drift": {"tilt_deg": tilt, "shift_m": float(expected.offset_m - view.offset_m)},
        "plane": {"frame": "base", **base.to_dict(), "point_m": base.point_m.tolist()},
        "frames_used": tracker.frames_used,
    }


def write_track_json(out_dir: str | Path, doc: Mapping[str, Any], filename: str = TRACK_FILENAME) -> Path:
    """Write ``DIR/track.json`` (or ``filename``) atomically (temp file + rename; an earlier file stays until
    it is complete).

    Raises:
        OutputError: If the directory cannot be created or written.
    """
    from cellcal.core.calibration.report import write_json_atomic

    path: Path = write_json_atomic(Path(out_dir) / filename, doc)
    return path


__all__ = ["FIXED_TRACK_SCHEMA", "FRAMES_FILENAME", "TRACK_FILENAME", "TRACK_SCHEMA", "fixed_track_document",
           "frame_row", "track_document", "track_filenames", "write_track_json"]
