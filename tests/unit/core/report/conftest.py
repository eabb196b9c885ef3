"""Report data of real simulated runs, made once per module: a passing sim run and one refused by a gate."""

from __future__ import annotations

import copy
import json
import tomllib
from importlib import resources
from pathlib import Path
from typing import Any

import pytest

from cellcal.core.calibration.calibrator import Calibrator, build_devices
from cellcal.core.calibration.config import parse_config
from cellcal.devices.errors import CalibrationQualityError

SIM: dict[str, Any] = tomllib.loads(resources.files("cellcal.configs").joinpath("sim.toml").read_text())


def box_document() -> dict[str, Any]:
    """sim.toml with a 0.15 m box under the camera: the table the cell expects is not the plane it sees."""
    doc = copy.deepcopy(SIM)
    doc["sim"]["boxes"] = [{"center_xy_m": [0.3, 0.0], "size_m": [0.36, 0.28, 0.15]}]
    return doc


def run_report(doc: dict[str, Any], out: Path) -> tuple[dict[str, Any], Exception | None]:
    """Run ``doc``'s plan as ``cellcal calibrate`` does with its report; the report data and the error."""
    from cellcal.core.report.runs import CalibrationReport

    config = parse_config(doc, "<test>")
    camera, arm = build_devices(config)
    report = CalibrationReport(config, camera, out)
    calibrator = Calibrator(config, report.camera, arm, observer=report.observer())  # type: ignore[arg-type]
    error: Exception | None = None
    try:
        report.finished(json.loads(json.dumps(calibrator.run())))
    except CalibrationQualityError as exc:
        error = exc
        report.failed_run(exc, f"cellcal: error: {exc}", calibrator.poses)
    return json.loads(json.dumps(report.data)), error


@pytest.fixture(scope="module")
def passing(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    data, error = run_report(copy.deepcopy(SIM), tmp_path_factory.mktemp("pass"))
    assert error is None
    return data


@pytest.fixture(scope="module")
def refused(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    data, error = run_report(box_document(), tmp_path_factory.mktemp("box"))
    assert isinstance(error, CalibrationQualityError) and error.gate == "expected_plane"
    return data
