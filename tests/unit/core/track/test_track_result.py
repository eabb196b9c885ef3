"""track.json and track.jsonl: the schema's keys, unseen values as null, atomic writing."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from cellcal.core.handeye.synthetic import camera_views, sim_scenario
from cellcal.core.track import TRACK_SCHEMA, Tracker, frame_row, track_document, write_track_json
from cellcal.core.track.synthetic import work
from cellcal.devices.errors import OutputError

SC = sim_scenario()


def tracked(views: tuple | None = None) -> Tracker:  # type: ignore[type-arg]
    scenario = SC if views is None else dataclasses.replace(SC, flanges=views)
    tracker = Tracker(SC.nominal_mount, SC.nominal_plane)
    for t_s, obs in work(scenario, np.random.default_rng(3), 160, dwell=10):
        tracker.update(t_s, obs)
    return tracker


def test_document_carries_the_estimate_intervals_and_what_is_observable(tmp_path: Path) -> None:
    state = tracked().state
    doc = track_document(state, {"frames": 170, "accepted": 160, "skipped: arm moving too fast": 10}, {"config": "x"})
    path = write_track_json(tmp_path, doc)
    assert path == tmp_path / "track.json"
    back = json.loads(path.read_text())
    assert back["schema"] == TRACK_SCHEMA == "cellcal.track/1"
    assert back["events"] == [] and back["change_unresolved"] is False
    assert back["mount"]["translation_m"] == pytest.approx(state.mount.translation.tolist())
    assert back["mount"]["rpy_deg"] == pytest.approx(state.mount_rpy_deg.tolist())
    lo, hi = back["intervals"]["mount_translation_m"][2]
    assert hi - lo == pytest.approx(2 * state.interval_z * state.mount_translation_sigma_m[2])
    assert all(back["observable"].values()) and back["unseen"] == []
    assert back["counters"]["skipped: arm moving too fast"] == 10 and back["frames_used"] == 160
    assert back["plane"]["frame"] == "base" and back["intervals"]["noise_model"]["verdict"] == "consistent"


def test_unseen_values_have_no_interval() -> None:
    views = camera_views(SC.true_mount, [0.3, 0.0, 0.0], 0.45, (70.0,), (0.0, 90.0, 180.0, 270.0))
    doc = json.loads(json.dumps(track_document(tracked(views).state, {}, {})))
    assert doc["intervals"]["mount_translation_m"][2] is None and doc["mount"]["translation_sigma_m"][2] is None
    assert doc["intervals"]["plane_offset_m"] is None and doc["plane"]["offset_sigma_m"] is None
    assert doc["observable"]["mount_z"] is False and "vs the plane's height" in doc["unseen"][0]
    assert doc["intervals"]["mount_translation_m"][0] is not None


def test_frame_row_is_one_json_line() -> None:
    tracker = Tracker(SC.nominal_mount, SC.nominal_plane)
    t_s, obs = next(work(SC, np.random.default_rng(1), 1))
    row = frame_row(tracker.update(t_s, obs), t_s, fit_ms=2.5)
    line = json.dumps(row, allow_nan=False)
    assert "\n" not in line
    assert row["t_s"] == 0.0 and row["accepted"] is True and row["event"] is None and row["fit_ms"] == 2.5
    assert len(row["residual"]) == 3 and row["chi2"] == pytest.approx(sum(v * v for v in row["residual"]))


def test_a_failed_write_keeps_the_earlier_file(tmp_path: Path) -> None:
    write_track_json(tmp_path, {"schema": TRACK_SCHEMA, "n": 1})
    with pytest.raises(TypeError):
        write_track_json(tmp_path, {"schema": TRACK_SCHEMA, "bad": object()})
    assert json.loads((tmp_path / "track.json").read_text())["n"] == 1
    assert [p.name for p in tmp_path.iterdir()] == ["track.json"]
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(OutputError):
        write_track_json(blocker / "sub", {"schema": TRACK_SCHEMA})
