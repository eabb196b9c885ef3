"""Every camera of configs/sim_multi.toml watched by ``cellcal monitor``; the sim's truths name the cell's cameras."""

from __future__ import annotations

from pathlib import Path

import pytest

from cellcal.core.cli import main

MULTI = Path(__file__).resolve().parents[3] / "configs" / "sim_multi.toml"


def test_monitor_watches_every_camera_of_the_cell(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["monitor", "--config", str(MULTI), "--frames", "40", "--out", str(tmp_path), "--quiet"]) == 0
    out = capsys.readouterr().out
    for name in ("wrist", "above", "side45"):
        line = next(x for x in out.splitlines() if x.strip().startswith(f"sim_multi.{name}:"))
        # 40 frames each, none failed, no drift on a still cell (the fixed ones see the table past the plate)
        assert "40 frames, 0 failed, 0 drift event(s)" in line, line


def test_a_sim_truth_naming_no_camera_of_the_cell_is_one_line(tmp_path: Path,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    config = tmp_path / "cell.toml"
    config.write_text(MULTI.read_text(encoding="utf-8").replace('name = "side45"\ntranslation_m',
                                                                'name = "sde45"\ntranslation_m'), encoding="utf-8")
    assert main(["calibrate", "--config", str(config), "--no-report", "--out", str(tmp_path / "out")]) in (1, 2)
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "'sde45' names no camera of the cell (its cameras: wrist, above, side45)" in err[0]


def test_calibrate_captures_every_camera_at_each_pose(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import json

    assert main(["calibrate", "--config", str(MULTI), "--no-report", "--quiet", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    driven = json.loads((tmp_path / "result.json").read_text(encoding="utf-8"))
    for name, on in (("above", "base"), ("side45", "base")):
        assert f"camera '{name}': result written to" in out
        document = json.loads((tmp_path / f"result-{name}.json").read_text(encoding="utf-8"))
        assert document["schema"] == "cellcal.camera-result/1" and document["on"] == on
        poses = document["poses"]
        # one frame per pose of the driven camera's plan, captured after it with the time said
        assert [p["index"] for p in poses] == [p["index"] for p in driven["poses"]]
        assert document["failed_poses"] == [] and all(p["after_s"] > 0 and "full_frame" in p for p in poses)
        reference = document["summary"]["plane_consistency"]["reference"]
        # through the configured pose (the truth is 0.3-0.4 deg and 4-11 mm from it): measured 0.35-0.43 deg,
        # 1-11 mm from [reference]
        assert reference["angle_deg"] < 0.8 and abs(reference["height_m"]) < 0.02
