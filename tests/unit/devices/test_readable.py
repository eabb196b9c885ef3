"""Numbers in messages: SI shown in millimetres and degrees, a value never printed equal to a different threshold."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from cellcal.devices.errors import CalibrationQualityError
from cellcal.devices.readable import distinct, quantity, quantity_pair


@pytest.mark.parametrize(("a", "b", "digits", "texts"), [
    (0.4, 0.5, 3, ("0.4", "0.5")),                               # different at the fewest digits: kept short
    (0.2617994, 0.2617993877991494, 6, ("0.2617994", "0.26179939")),   # the user's 15 deg, in radians
    (15.0000001, 15.0, 3, ("15.0000001", "15")),
    (math.nextafter(1.0, 2.0), 1.0, 3, ("1.0000000000000002", "1")),
    (2.0, 2.0, 3, ("2", "2")),                                    # equal numbers print equal
    (math.nan, 0.25, 3, ("nan", "0.25")),
])
def test_distinct_adds_digits_until_the_two_differ(a: float, b: float, digits: int, texts: tuple[str, str]) -> None:
    assert distinct(a, b, digits) == texts


@given(st.floats(-1e300, 1e300), st.floats(-1e300, 1e300))     # 3 digits of the largest floats round to inf
def test_two_different_finite_floats_never_print_equal(a: float, b: float) -> None:
    shown = distinct(a, b)
    assert (shown[0] == shown[1]) == (a == b)
    assert float(shown[0]) == pytest.approx(a, rel=5e-3) and float(shown[1]) == pytest.approx(b, rel=5e-3)


def test_quantities_read_in_millimetres_and_degrees() -> None:
    assert quantity(0.0015, "m") == "1.5 mm"
    assert quantity(math.radians(15.0), "rad") == "15 deg"
    assert quantity(0.25, "") == "0.25"
    assert quantity_pair(0.005, 0.004936, "m") == ("5 mm", "4.94 mm")
    assert quantity_pair(math.radians(15.0) + 1e-9, math.radians(15.0), "rad") == ("15.0000001 deg", "15 deg")


def test_two_si_values_rounded_onto_one_display_value_print_in_si() -> None:
    """0.9015260301538721 m and the next float are different lengths, but x 1000 both round to one float: the pair
    is printed in metres, where it differs."""
    a = 0.9015260301538721
    b = math.nextafter(a, 1.0)
    assert a * 1000.0 == b * 1000.0
    assert quantity_pair(b, a, "m") == ("0.9015260301538722 m", "0.9015260301538721 m")


def test_a_quality_gate_error_keeps_si_and_reads_in_mm_and_deg() -> None:
    err = CalibrationQualityError("expected_plane", math.radians(15.0) + 1e-9, math.radians(15.0), "why", unit="rad")
    assert (err.value, err.threshold, err.unit) == (math.radians(15.0) + 1e-9, math.radians(15.0), "rad")
    assert str(err) == "quality gate 'expected_plane' failed: 15.0000001 deg vs threshold 15 deg; why"
    assert str(CalibrationQualityError("flatness", 0.0015, 0.001, unit="m")) == \
        "quality gate 'flatness' failed: 1.5 mm vs threshold 1 mm"
    # a plain number keeps six digits unless it needs more: what the hand-eye gates' messages have always read
    assert str(CalibrationQualityError("observability", 5, 9)) == \
        "quality gate 'observability' failed: 5 vs threshold 9"
    assert str(CalibrationQualityError("noise_model", 10.0000001, 10)) == \
        "quality gate 'noise_model' failed: 10.0000001 vs threshold 10"
