"""Online self-calibration during normal work: pairing, the recursive estimator, change detection (ADR 0040)."""

from cellcal.core.track.estimator import Tracker
from cellcal.core.track.pairing import PoseHistory, Skip
from cellcal.core.track.result import TRACK_FILENAME, TRACK_SCHEMA, frame_row, track_document, write_track_json
from cellcal.core.track.state import ChangeEvent, TrackSettings, TrackState, TrackStep

__all__ = [
    "TRACK_FILENAME",
    "TRACK_SCHEMA",
    "ChangeEvent",
    "PoseHistory",
    "Skip",
    "TrackSettings",
    "TrackState",
    "TrackStep",
    "Tracker",
    "frame_row",
    "track_document",
    "write_track_json",
]
