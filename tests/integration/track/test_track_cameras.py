"""``cellcal track`` over every camera of ``configs/sim_multi.toml`` (issue #40): one knocked, the others not.

The variant adds sim_track.toml's work program (the arm works on its own) and, at 8 s, knocks the
fixed camera 'above' by 0.5 deg about its x axis ([[sim.events]] with ``camera = "above"``). Its
truth before: rpy (180.3, 0.2, -0.4) deg; after: (180.8, 0.2, -0.4). The cameras run at 5 Hz for
16 s of frames (81 each). Measured: 'above' detects it at 8.6 s, 0.494 deg in its view (tolerance
0.03 deg); 'wrist' and 'side45' see no change.
"""

from __future__ import annotations

import contextlib
import io
import json
import re
from pathlib import Path
from typing import Any

import pytest
from repo_paths import REPO_ROOT

from cellcal.core.cli import main

MULTI = REPO_ROOT / "configs" / "sim_multi.toml"
TRACK = REPO_ROOT / "configs" / "sim_track.toml"
KNOCK_S = 8.0


def _variant(tmp_path: Path) -> Path:
    """sim_multi.toml with a work program, the clock driven by the frames, 5 Hz cameras and 'above' knocked."""
    text = MULTI.read_text().replace("time_scale = 0.001", "time_scale = 0.0 #")
    text = text.replace('backend = "sim"\n\n#', 'backend = "sim"\nframe_rate_hz = 5.0\n\n#')  # each camera's table
    assert text.count("frame_rate_hz = 5.0") == 3
    text = text.replace("[sim]\n", "[sim]\ninitial_flange_translation_m = [0.3824, 0.0515, 0.5023]\n"
                        "initial_flange_rpy_deg = [180.0, 10.0, 7.66]\n", 1)
    track = TRACK.read_text()
    work = track[track.index("\n[sim.work]") + 1:track.index("# Halfway")]
    path = tmp_path / "multi.toml"
    path.write_text(text + "\n" + work + f"""
[[sim.events]]
at_s = {KNOCK_S}
camera = "above"
mount_translation_m = [0.304, -0.003, 1.196]
mount_rpy_deg = [180.8, 0.2, -0.4]
""")
    return path


def _run(*args: str) -> tuple[int, str]:
    buffer = io.StringIO()
    with contextlib.redirect_stdout(buffer):
        code = main(["track", *args])
    return code, buffer.getvalue()


@pytest.fixture(scope="module")
def knocked(tmp_path_factory: pytest.TempPathFactory) -> tuple[int, str, Path]:
    base = tmp_path_factory.mktemp("cameras")
    out = base / "out"
    code, printed = _run("--config", str(_variant(base)), "--duration", "16", "--quiet", "--out", str(out))
    return code, printed, out


def _doc(out: Path, name: str) -> dict[str, Any]:
    doc: dict[str, Any] = json.loads((out / name).read_text())
    return doc


def test_every_camera_is_tracked_into_its_own_files(knocked: Any) -> None:
    _code, printed, out = knocked
    wrist, above, side = _doc(out, "track.json"), _doc(out, "track-above.json"), _doc(out, "track-side45.json")
    assert wrist["schema"] == "cellcal.track/1" and wrist["meta"]["camera_name"] == "wrist"
    assert above["schema"] == side["schema"] == "cellcal.track-fixed/1"
    assert (above["meta"]["place"], side["meta"]["place"]) == ("base", "base")
    assert {d["counters"]["frames"] for d in (wrist, above, side)} == {81}
    for name in ("track.jsonl", "track-above.jsonl", "track-side45.jsonl"):
        assert len((out / name).read_text().splitlines()) == 81
    assert "camera 'wrist' (on the flange):" in printed and "camera 'side45' (fixed):" in printed


def test_a_knocked_fixed_camera_is_reported_for_that_camera_only(knocked: Any) -> None:
    code, printed, out = knocked
    assert code == 1                                                   # a fixed camera was moved
    wrist, above, side = _doc(out, "track.json"), _doc(out, "track-above.json"), _doc(out, "track-side45.json")
    assert wrist["events"] == [] and side["events"] == []
    (event,) = above["events"]
    assert event["started_at_s"] >= KNOCK_S and event["detected_at_s"] - KNOCK_S <= 1.0
    assert event["size"]["view_tilt_deg"] == pytest.approx(0.5, abs=0.03)   # measured 0.494
    assert abs(event["size"]["view_shift_m"]) < 2e-4                        # turned about its origin
    assert event["resolved_at_s"] is not None
    assert re.search(r"^\[above\] t=8\.\d s: change detected", printed, re.M)
    assert "[wrist]" not in printed and "[side45]" not in printed
    assert re.search(r"camera 'above' was moved at t=8\.\d s: the plane moved in its view by 0\.\d+ deg .* "
                     r"while the camera\(s\) on the arm \(wrist\) saw no change of the plane", printed)
    assert "calibrate again: above (cellcal handeye --camera NAME)" in printed


def test_camera_restricts_the_run_to_one_camera(tmp_path: Path) -> None:
    out = tmp_path / "one"
    code, printed = _run("--config", str(_variant(tmp_path)), "--camera", "side45", "--frames", "5", "--out", str(out))
    assert code == 0
    assert sorted(p.name for p in out.iterdir()) == ["track-side45.json", "track-side45.jsonl"]
    doc = _doc(out, "track-side45.json")
    assert doc["meta"]["camera_name"] == "side45" and doc["counters"]["frames"] == 5
    # side45 truly stands 4 mm off its configured pose: its view of the plane 643.8 mm away (configured 636.4)
    assert doc["view"]["offset_m"] == pytest.approx(0.6438, abs=0.002)
    assert "view of the plane (camera frame)" in printed
