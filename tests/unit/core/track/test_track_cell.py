"""Tracking several cameras (ADR 0061): a fixed camera's tracker, which camera moved, a camera that fails."""

from __future__ import annotations

import json
import math
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from repo_paths import REPO_ROOT

from cellcal.core.calibration.build import build_cell
from cellcal.core.calibration.config import load_config
from cellcal.core.geometry.planes import Plane
from cellcal.core.handeye.synthetic import Scenario
from cellcal.core.track import ChangeEvent, Tracker
from cellcal.core.track.cell import CameraTrack, CellTrack, attribute
from cellcal.core.track.result import fixed_track_document, track_filenames
from cellcal.core.track.run import ReadOnlyArm, TrackRun, device_clock, fixed_settings
from cellcal.core.track.state import TrackSettings
from cellcal.core.track.synthetic import work
from cellcal.devices.errors import DeviceError
from cellcal.devices.pose import Pose

#: A camera 1.2 m over the plane z = 0, looking down (as configs/sim_multi.toml's "above").
ABOVE = Pose.from_xyz_rpy(np.array([0.3, 0.0, 1.2]), np.radians([180.0, 0.0, 0.0]))
FLOOR = Plane(np.array([0.0, 0.0, 1.0]), 0.0)


def fixed_scenario(pose: Pose) -> Scenario:
    """A fixed camera as the tracker takes it: one view at the identity flange pose, ``pose`` its T_base_camera."""
    return Scenario(true_mount=pose, nominal_mount=ABOVE, true_plane=FLOOR, nominal_plane=FLOOR,
                    flanges=(Pose.identity(),), arm_translation_sigma_m=0.0)


def test_a_fixed_camera_knocked_by_half_a_degree_is_detected_and_sized_in_its_view() -> None:
    rng = np.random.default_rng(5)
    tracker = Tracker(ABOVE, FLOOR, fixed_settings(TrackSettings()), fixed=True)
    quiet = fixed_scenario(ABOVE)
    for t_s, obs in work(quiet, rng, 300):
        assert tracker.update(t_s, obs).event is None             # 10 s of frames: no false alarm
    turn = Pose.from_xyz_rpy(np.zeros(3), np.radians([0.5, 0.0, 0.0]))   # about the camera's x
    knocked = fixed_scenario(ABOVE @ turn)
    events = [(round(t * 30), s.event) for t, obs in work(knocked, rng, 60, start_frame=300)
              if (s := tracker.update(t, obs)).event is not None]
    first_frame, first = events[0]
    assert first_frame - 300 <= 3 and first.kind == "mount or plane"  # one view never tells which
    final = tracker.state.events[-1]
    # 0.5 deg in its view, along the optical axis nothing (the turn is about the camera's origin)
    assert final.size["view_tilt_deg"] == pytest.approx(0.5, abs=0.01)
    assert abs(final.size["view_shift_m"]) < 1e-4
    assert final.resolved_at_s is not None and len(tracker.state.events) == 1


def test_a_fixed_cameras_document_gives_its_view_against_the_configured_one() -> None:
    rng = np.random.default_rng(6)
    true = ABOVE @ Pose.from_xyz_rpy(np.array([0.0, 0.0, 0.002]), np.radians([0.0, 0.3, 0.0]))
    tracker = Tracker(ABOVE, FLOOR, fixed_settings(TrackSettings()), fixed=True)
    for t_s, obs in work(fixed_scenario(true), rng, 200):
        tracker.update(t_s, obs)
    doc = fixed_track_document(tracker, ABOVE, {"frames": 200}, {"camera_name": "above"})
    assert doc["schema"] == "cellcal.track-fixed/1" and doc["meta"]["camera_name"] == "above"
    # the camera 2 mm further along its axis and turned 0.3 deg: the plane 2 mm nearer, tilted 0.3 deg in its view
    assert doc["view"]["offset_m"] == pytest.approx(1.198, abs=2e-5)
    assert doc["drift"]["tilt_deg"] == pytest.approx(0.3, abs=0.005)
    assert doc["drift"]["shift_m"] == pytest.approx(0.002, abs=2e-5)
    assert doc["events"] == [] and doc["change_unresolved"] is False
    json.dumps(doc, allow_nan=False)


def _outcome(events: list[ChangeEvent], frames_used: int = 100) -> Any:
    return SimpleNamespace(state=SimpleNamespace(events=events, frames_used=frames_used))


def _event(start: float, kind: str = "mount or plane", **size: float) -> ChangeEvent:
    return ChangeEvent(start + 0.2, kind, dict(size), start + 1.0, start)


def test_a_fixed_cameras_change_is_its_own_unless_a_camera_on_the_arm_saw_the_plane_move() -> None:
    places = {"wrist": "flange", "above": "base"}
    knock = _event(10.0, view_tilt_deg=0.5, view_shift_m=0.0)
    (own,) = attribute({"wrist": _outcome([]), "above": _outcome([knock])}, places)
    assert own.cause == "camera moved" and own.camera == "above" and own.started_at_s == 10.0
    assert "camera 'above' was moved at t=10.0 s" in own.text and "(wrist) saw no change" in own.text
    assert "by 0.500 deg" in own.text
    table = {"wrist": _outcome([_event(11.0, "plane")]), "above": _outcome([knock])}
    assert attribute(table, places)[0].cause == "plane moved"                       # 1 s apart: one change
    late = {"wrist": _outcome([_event(16.0, "plane")]), "above": _outcome([knock])}
    assert attribute(late, places)[0].cause == "camera moved"                       # 6 s apart: another
    mounted = {"wrist": _outcome([_event(10.0, "mount")]), "above": _outcome([knock])}
    assert attribute(mounted, places)[0].cause == "camera moved"                    # the wrist's own knock
    blind = {"wrist": _outcome([], frames_used=0), "above": _outcome([knock])}
    assert attribute(blind, places)[0].cause == "undecided"                         # no witness on the arm
    failed = attribute({"wrist": _outcome([]), "above": _outcome([knock])}, places, {"wrist": 12.0})
    assert failed[0].cause == "undecided"                                           # stopped before it could see
    assert attribute({"wrist": _outcome([knock])}, {"wrist": "flange"}) == []       # only fixed cameras' changes


def test_each_camera_has_its_files_and_the_first_on_the_flange_keeps_track_json() -> None:
    assert track_filenames(None) == ("track.json", "track.jsonl")
    assert track_filenames("above") == ("track-above.json", "track-above.jsonl")


def test_a_camera_that_fails_is_left_out_and_the_others_go_on(tmp_path: Path) -> None:
    path = str(REPO_ROOT / "configs" / "sim_multi.toml")
    config = load_config(path)
    cameras, arm = build_cell(config)

    def fail_third(event: str, n: int) -> None:
        if event == "capture" and n == 3:
            raise DeviceError("side45: no frame (test)")

    cameras["side45"].fault_hook = fail_third  # type: ignore[attr-defined]
    reader = ReadOnlyArm(arm)
    tracks = []
    with reader:
        for entry in config.cameras:
            camera = cameras[entry.name].connect()
            own = load_config(path, entry.name, allow_fixed=True)
            run = TrackRun(own, camera, reader, out_dir=tmp_path, now=device_clock(camera), name=entry.name,
                           filenames=track_filenames(None if entry.name == "wrist" else entry.name),
                           fixed_pose=entry.pose_base if entry.on == "base" else None, decimation=4)
            tracks.append(CameraTrack(entry.name, entry.on, run))
        said: list[str] = []
        outcome = CellTrack(tracks, on_failure=lambda f: said.append(f.name)).run(max_frames=6)
        for camera in cameras.values():
            camera.close()
    assert said == ["side45"] and [f.name for f in outcome.failures] == ["side45"]
    assert outcome.failures[0].message == "side45: no frame (test)"
    counts = {name: o.document["counters"]["frames"] for name, o in outcome.outcomes.items()}
    assert counts == {"wrist": 6, "above": 6, "side45": 2}
    side = json.loads((tmp_path / "track-side45.json").read_text())
    assert side["meta"]["failed"] == "side45: no frame (test)" and side["meta"]["place"] == "base"
    assert len((tmp_path / "track-side45.jsonl").read_text().splitlines()) == 2
    wrist = json.loads((tmp_path / "track.json").read_text())
    assert wrist["meta"]["camera_name"] == "wrist" and wrist["meta"]["failed"] is None
    # one time line: every camera's first frame counts from the run's first frame (the sim's shared clock)
    firsts = [json.loads((tmp_path / f).read_text().splitlines()[0])["t_s"]
              for f in ("track.jsonl", "track-above.jsonl", "track-side45.jsonl")]
    assert firsts[0] == 0.0 and all(0.0 <= t < 0.5 for t in firsts)
    assert math.isclose(outcome.outcomes["above"].document["view"]["offset_m"], 1.2, abs_tol=0.01)
