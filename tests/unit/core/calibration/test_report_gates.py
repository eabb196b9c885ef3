"""The per-pose gate line of the calibrate report: every gate with its unit, the new ones included."""

from __future__ import annotations

import math

from cellcal.core.calibration.report import _gates


def test_gate_line_shows_units_for_the_floor_and_the_expected_plane() -> None:
    gates = {
        "valid_fraction": {"value": 0.998, "threshold": 0.5, "passed": True},
        "residual_floor": {"value": 0.12, "threshold": 0.25, "passed": False},
        "expected_plane": {"value": math.radians(2.0), "threshold": math.radians(15.0), "passed": True},
        "flatness": {"value": 0.0004, "threshold": 0.001, "passed": True},
    }
    line = _gates(gates)
    assert "valid 99.8 % (min 50 %, ok)" in line
    assert "rms vs sensor 0.12 x (min 0.25 x, FAILED)" in line
    assert "off expected 2 deg (max 15 deg, ok)" in line
    assert "flatness 0.4 mm (max 1 mm, ok)" in line


def test_an_unknown_gate_is_shown_without_a_unit_and_without_stray_spaces() -> None:
    line = _gates({"vendor_gate": {"value": 3.0, "threshold": 2.0, "passed": False}})
    assert line == "vendor_gate 3 (limit 2, FAILED)"
