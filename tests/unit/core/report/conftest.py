"""Report data of real simulated runs, made once per module: a passing sim run and one refused by a gate."""

from __future__ import annotations

import copy
from typing import Any

import pytest
from report_runs import SIM, box_document, corner_box_document, run_report, thin_plate_document

from cellcal.devices.errors import CalibrationQualityError


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


@pytest.fixture(scope="module")
def not_flat(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    data, error = run_report(thin_plate_document(), tmp_path_factory.mktemp("plate"))
    assert isinstance(error, CalibrationQualityError) and error.gate == "flatness"
    return data


@pytest.fixture(scope="module")
def not_covered(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    data, error = run_report(corner_box_document(), tmp_path_factory.mktemp("corner"))
    assert isinstance(error, CalibrationQualityError) and error.gate == "coverage"
    return data
