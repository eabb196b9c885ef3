"""End-to-end calibration on the simulated cell, through the CLI and in-process."""

from __future__ import annotations

import json
import math
import statistics
import subprocess
import sys
import tomllib
from importlib import resources
from pathlib import Path
from typing import Any

import pytest
from toml_files import write_toml

from cellcal.core.calibration.calibrator import Calibrator, build_devices
from cellcal.core.calibration.config import parse_config
from cellcal.core.calibration.report import RESULT_SCHEMA
from cellcal.core.cli import main

SIM_TOML = resources.files("cellcal.configs").joinpath("sim.toml").read_text()


def sim_document(**overrides: dict[str, Any]) -> dict[str, Any]:
    """The packaged sim.toml as a dict, with tables updated from ``overrides``."""
    doc = tomllib.loads(SIM_TOML)
    for table, values in overrides.items():
        doc.setdefault(table, {}).update(values)
    return doc


def run_doc(doc: dict[str, Any]) -> dict[str, Any]:
    config = parse_config(doc, "<test>")
    camera, arm = build_devices(config)
    return Calibrator(config, camera, arm).run()


def rows(result: dict[str, Any], method: str | None = None) -> list[dict[str, Any]]:
    return [m for p in result["poses"] for m in p["measurements"] if method is None or m["method"] == method]


def test_default_cli_run_writes_a_complete_result(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["calibrate", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "plane_fit" in out and "result written to" in out
    result = json.loads((tmp_path / "result.json").read_text())
    assert result["schema"] == RESULT_SCHEMA
    assert len(result["poses"]) == 3
    assert len(rows(result)) == 3 * 4 * 3 + 3  # three grid methods x four perimeters, plus full_frame per pose
    for m in rows(result):
        assert set(m) >= {"angle_deg", "error_pct", "tilt_x_deg", "tilt_y_deg", "height_m", "residual_rms_m"}
    assert result["config"]["plan"]["heights_m"] == [0.46, 0.59, 0.61]
    assert result["timings_s"]["total"] > 0
    # heights measured by the nine-point fit are the planned ones within a few mm
    for pose, h in zip(result["poses"], (0.46, 0.59, 0.61), strict=True):
        fits = [m for m in pose["measurements"] if m["method"] == "plane_fit"]
        assert all(abs(m["height_m"] - h) < 0.01 for m in fits)
    assert not list(tmp_path.glob(".result.json.*"))


def test_noise_free_accuracy_and_nominal_model_bias() -> None:
    # an ideal camera and arm: noise-free, without systematic error (ADR 0054) or kinematic error (ADR 0055)
    result = run_doc(sim_document(camera={"noise": False, "quantisation_m": 0.0}, arm={"repeatability_m": 0.0},
                                  sim={"systematic": {"enabled": False}, "arm_errors": {"enabled": False}}))
    for m in rows(result, "plane_fit"):
        assert abs(m["angle_deg"] - 80.0) < 0.01, m
        assert abs(m["tilt_x_deg"] - 10.0) < 0.01 and abs(m["tilt_y_deg"]) < 0.01
    for m in rows(result, "law_of_cosines"):
        assert abs(m["angle_deg"] - 80.0) < 0.05, m
    nominal = rows(result, "plane_fit_nominal")
    # the paper's constant-angle-per-pixel model is biased on a real lens; the result says so
    worst = max(abs(m["angle_deg"] - 80.0) for m in nominal)
    assert worst > 0.05
    assert all(m["error_pct"] == pytest.approx(abs(m["angle_deg"] - 80.0) / 80.0 * 100) for m in nominal)


@pytest.mark.slow
def test_nine_point_uncertainty_is_honest_and_beats_law_of_cosines() -> None:
    angles: dict[tuple[str, int, int], list[float]] = {}
    sigmas: dict[tuple[int, int], list[float]] = {}
    for seed in range(40):
        result = run_doc(sim_document(cell={"seed": seed}))
        for pose in result["poses"]:
            for m in pose["measurements"]:
                angles.setdefault((m["method"], pose["index"], m["perimeter_px"]), []).append(m["angle_deg"])
                if m["method"] == "plane_fit":
                    sigmas.setdefault((pose["index"], m["perimeter_px"]), []).append(m["angle_sigma_deg"])
    ratios = []
    for (pose, per), sig in sigmas.items():
        spread = statistics.stdev(angles[("plane_fit", pose, per)])
        reported = math.sqrt(statistics.fmean(s * s for s in sig))
        ratios.append(spread / reported)
    assert all(1 / 1.5 <= r <= 1.5 for r in ratios), ratios
    for pose in range(3):
        for per in (20, 30, 40, 50):
            assert statistics.stdev(angles[("law_of_cosines", pose, per)]) > statistics.stdev(
                angles[("plane_fit", pose, per)])


def test_failed_run_leaves_the_earlier_result_untouched(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    # (the reports have their own tests: tests/integration/report)
    assert main(["calibrate", "--out", str(out), "--quiet", "--no-report"]) == 0
    before = (out / "result.json").read_bytes()
    # the second pose is inside the safety box but beyond the simulated arm's reach:
    # the arm itself raises mid-plan
    doc = sim_document(plan={"poses": [{"xyz_m": [0.3, 0.0, 0.6], "rpy_deg": [180.0, 0.0, 0.0]},
                                       {"xyz_m": [0.69, 0.45, 0.6], "rpy_deg": [180.0, 0.0, 0.0]}]})
    config = write_toml(tmp_path / "bad.toml", doc)
    capsys.readouterr()
    code = main(["calibrate", "--config", str(config), "--out", str(out), "--quiet", "--no-report"])
    err = capsys.readouterr().err
    assert code == 1
    assert err.count("\n") == 1 and err.startswith("cellcal: error: ")
    assert (out / "result.json").read_bytes() == before
    # beside it only the resume journal of the one pose measured, and the message says how to resume
    assert sorted(p.name for p in out.iterdir()) == ["result.json", "result.json.journal.jsonl"]
    assert "1 of 2 poses are saved" in err and "--resume" in err


def test_check_touches_no_device(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["calibrate", "--check"]) == 0
    out = capsys.readouterr().out
    assert "camera:  backend 'sim'" in out and "config OK" in out


def test_console_script_default_run(tmp_path: Path) -> None:
    exe = Path(sys.executable).with_name("cellcal")
    proc = subprocess.run([str(exe), "calibrate", "--out", str(tmp_path), "--quiet"], capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert json.loads((tmp_path / "result.json").read_text())["schema"] == RESULT_SCHEMA


def test_bad_config_exits_2_with_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "c.toml"
    doc = sim_document(camera={"noise": "yes"})
    write_toml(path, doc)
    assert main(["calibrate", "--config", str(path), "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "key 'camera.noise'" in err and str(path) in err


@pytest.mark.parametrize(("name", "camera", "arm"), [("ur_oak.toml", "oak", "ur"), ("ur_o3r.toml", "o3r", "ur")])
def test_check_shows_what_connects_to_what(name: str, camera: str, arm: str,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    path = resources.files("cellcal.configs").joinpath(name)
    assert main(["calibrate", "--check", "--config", str(path)]) == 0
    out = capsys.readouterr().out
    assert f"camera:  backend '{camera}'" in out and f"arm:     backend '{arm}' at host=" in out
    assert "no device was touched" in out
