"""The full-frame quality gates at their exact thresholds, with per-point sigmas, and the texts a user reads, whole.

Most tests take one real fit (a noisy cloud with per-point sigmas, :func:`fit_plane_points`)
and set the gate inputs on a copy of it to chosen values, so that what each gate must
decide is known without the code: fractions that are exact in binary (0.5, 18/36),
residuals that are powers of two (so a ratio of them is exact), a 3-4-5 triangle for the
noise and the quantisation floor added in quadrature. The fractions take discrete values
(18 of 36 coverage cells, 500 of 1000 points), so each threshold is reached exactly, and
the next float on either side of it is decided the other way. Real fits check the same
gates end to end: 40 % and 50 % inliers, per-point sigmas stated 10 x too small or too
large, a plane filling exactly the left half of the image.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from statistics import NormalDist

import numpy as np
import pytest
from test_fullframe_gates import _masked
from tof_frames import ToFSetup, make_frame

from cellcal.core.methods.fullframe import GATE_NAMES, FullFrameResult, FullFrameSettings, check_gates, fit_full_frame
from cellcal.core.methods.fullframe.fit import fit_plane_points
from cellcal.core.methods.fullframe.gates import (
    coverage_cells,
    expected_rms_m,
    floor_reference_m,
    gate_table,
    image_coverage,
    residual_threshold_m,
)
from cellcal.devices.errors import CalibrationQualityError
from cellcal.devices.measurement import MeasurementModel

MM = 1e-3
DEFAULTS = FullFrameSettings()


def below(x: float) -> float:
    """The next float below ``x``."""
    return math.nextafter(x, -math.inf)


def above(x: float) -> float:
    """The next float above ``x``."""
    return math.nextafter(x, math.inf)


def plane_cloud(n_plane: int, n_junk: int, sigma_m: np.ndarray | float, stated: float = 1.0,
                seed: int = 0) -> FullFrameResult:
    """A fit with per-point sigmas: ``n_plane`` points of the plane z = 1 m and ``n_junk`` far in front of it.

    Args:
        n_plane: Points on the plane (a 25 x ``n_plane / 25`` grid over 0.8 m x 0.6 m).
        n_junk: Points 0.1 to 0.5 m in front of the plane (clutter, far outside any inlier band).
        sigma_m: Range noise drawn along each plane point's ray (a normal law cut at 2 sigma, so that
            every plane point is an inlier), metres (scalar or per point).
        stated: The sigmas given to the fit are ``stated`` times the ones drawn.
        seed: Seed of the noise and the junk.
    """
    rng = np.random.default_rng(seed)
    u, v = np.meshgrid(np.linspace(-0.4, 0.4, 25), np.linspace(-0.3, 0.3, n_plane // 25))
    p = np.stack([u.ravel(), v.ravel(), np.ones(n_plane)], axis=1)
    r = np.linalg.norm(p, axis=1)
    sig = np.broadcast_to(np.asarray(sigma_m, dtype=float), (n_plane,))
    p *= ((r + np.clip(rng.standard_normal(n_plane), -2.0, 2.0) * sig) / r)[:, None]
    junk = np.column_stack([rng.uniform(-0.4, 0.4, n_junk), rng.uniform(-0.3, 0.3, n_junk),
                            rng.uniform(0.5, 0.9, n_junk)])
    sigmas = np.concatenate([sig * stated, np.full(n_junk, 0.001)])
    return fit_plane_points(np.vstack([p, junk]), sigmas)


@functools.cache
def _base() -> FullFrameResult:
    return plane_cloud(500, 0, 0.001)


#: The gate inputs of a fit that passes every gate (with the default settings and an expected plane).
PASSING: dict[str, object] = {
    "valid_fraction": 1.0, "inlier_fraction": 1.0, "residual_rms_m": 1 * MM, "coverage": 1.0,
    "flatness_m": 0.0, "flatness_where": "", "native_space": "range", "sigma_given": True,
    "residual_expected_m": 1 * MM, "residual_unit_rms_m": 1 * MM, "residual_floor_m": 0.0, "sigma_stated": True,
    "multipath_allowance_m": 0.0, "lock_on": "", "expected_departure": (0.0, 0.0),
    "expected_tolerance": (math.radians(1.0), 5 * MM), "measurement": MeasurementModel(),
}


def result(settings: FullFrameSettings = DEFAULTS, **fields: object) -> FullFrameResult:
    """The real fit with the gate inputs of ``PASSING`` and ``fields``, its gate table made under ``settings``."""
    res = dataclasses.replace(_base(), settings=settings, **{**PASSING, **fields})  # type: ignore[arg-type]
    return dataclasses.replace(res, gates=gate_table(settings, res))


def failure(res: FullFrameResult, settings: FullFrameSettings | None = None) -> CalibrationQualityError:
    """The error ``check_gates`` raises."""
    with pytest.raises(CalibrationQualityError) as info:
        check_gates(res, settings)
    return info.value


# ---------------------------------------------------------------------- real fits with per-point sigmas
def test_forty_percent_inliers_fail_although_no_plane_is_expected() -> None:
    """400 plane points and 600 clutter points: no expected plane (its gate is skipped), the inliers fail."""
    res = plane_cloud(400, 600, 0.001)
    assert res.sigma_given and res.n_inliers == 400 and res.inlier_fraction == 0.4
    assert "expected_plane" not in res.gates and res.gates["inlier_fraction"] == (0.4, 0.5, False)
    err = failure(res)
    assert (err.gate, err.value, err.threshold) == ("inlier_fraction", 0.4, 0.5)
    assert str(err) == ("quality gate 'inlier_fraction' failed: 0.4 vs threshold 0.5; "
                        "plane inliers among the valid pixels 40 %, 10 % below the minimum of 50 %")


def test_fifty_percent_inliers_pass_exactly_at_the_threshold() -> None:
    res = plane_cloud(500, 500, 0.001)
    assert res.n_inliers == 500 and res.inlier_fraction == 0.5 and res.gates["inlier_fraction"] == (0.5, 0.5, True)
    check_gates(res)
    err = failure(res, FullFrameSettings(min_inlier_fraction=above(0.5)))
    assert (err.gate, err.value) == ("inlier_fraction", 0.5)


def test_per_point_sigmas_are_the_unit_of_the_residual_gates() -> None:
    """Sigmas 0.5 to 2 mm along the rays: the expected RMS is theirs projected across the plane (cos of the
    incidence, 1/range on the plane z = 1 m), cut at 3 sigma like the inliers, not the default noise law; the
    gates are in units of it."""
    sig = np.random.default_rng(7).uniform(0.0005, 0.002, 500)
    res = plane_cloud(500, 0, sig)
    assert res.sigma_given and res.sigma_stated and res.native_space == "range"
    u, v = np.meshgrid(np.linspace(-0.4, 0.4, 25), np.linspace(-0.3, 0.3, 20))
    across = sig / np.sqrt(1.0 + u.ravel() ** 2 + v.ravel() ** 2)
    c = DEFAULTS.inlier_threshold_sigma                 # variance of a unit normal kept within +-c: 0.9733
    kept_var = 1.0 - 2.0 * c * NormalDist().pdf(c) / (2.0 * NormalDist().cdf(c) - 1.0)
    independent = math.sqrt(kept_var * float(np.mean(across[res.inlier_mask] ** 2)))
    assert expected_rms_m(res, DEFAULTS) == res.residual_expected_m
    assert res.residual_expected_m == pytest.approx(independent, rel=1e-3)
    assert floor_reference_m(res, DEFAULTS) == res.residual_expected_m      # stated, above a floor of 0
    assert residual_threshold_m(res, DEFAULTS) == 4.0 * res.residual_expected_m
    assert res.gates["residual_floor"] == (res.residual_rms_m / res.residual_expected_m, 0.25, True)
    assert res.gates["residual_rms_m"] == (res.residual_rms_m, 4.0 * res.residual_expected_m, True)
    check_gates(res)
    # the same points, sigmas stated 10x too small: 10x the expected RMS; 10x too large: 0.1x the floor
    small = plane_cloud(500, 0, sig, stated=0.1)
    assert small.residual_expected_m == pytest.approx(0.1 * res.residual_expected_m, rel=1e-3)
    err = failure(small)
    assert err.gate == "residual_rms_m" and err.threshold == 4.0 * small.residual_expected_m
    assert err.value / small.residual_expected_m == pytest.approx(10.0, rel=0.1)
    large = plane_cloud(500, 0, sig, stated=10.0)
    err = failure(large)
    assert err.gate == "residual_floor" and err.value == pytest.approx(0.1, rel=0.1) and err.threshold == 0.25


def test_a_plane_filling_the_left_half_of_the_image_is_at_both_fraction_thresholds() -> None:
    """No dropout, the right 112 of 224 columns invalid: 18 of the 36 coverage cells (columns 0-111 are the
    first three cell columns of 37, 37, 38 px), and half the pixels valid: both gates pass at exactly 0.5."""
    frame = make_frame(ToFSetup(dropout=0.0), 7)
    valid = frame.valid.copy()
    assert valid.all() and valid.shape == (172, 224)
    valid[:, 112:] = False
    res = fit_full_frame(_masked(frame, valid))
    assert res.gates["valid_fraction"] == (0.5, 0.5, True) and res.gates["coverage"] == (0.5, 0.5, True)
    check_gates(res)
    err = failure(res, FullFrameSettings(min_valid_fraction=above(0.5)))
    assert (err.gate, err.value) == ("valid_fraction", 0.5)
    err = failure(res, FullFrameSettings(min_coverage=above(0.5)))
    assert (err.gate, err.value) == ("coverage", 0.5)
    # a value just below its threshold never prints equal to it
    assert str(err) == ("quality gate 'coverage' failed: 0.5 vs threshold 0.5000000000000001; image cells holding "
                        "plane inliers 50 %, 1.11e-14 % below the minimum of 50.00000000000001 %")


# ---------------------------------------------------------------------- each gate at its threshold
@pytest.mark.parametrize(("gate", "field", "at", "beyond"), [
    ("valid_fraction", "valid_fraction", 0.5, below(0.5)),
    ("inlier_fraction", "inlier_fraction", 0.5, below(0.5)),
    ("coverage", "coverage", 18 / 36, 17 / 36),
    ("flatness", "flatness_m", 1 * MM, above(1 * MM)),
    ("residual_rms_m", "residual_rms_m", 4 * MM, above(4 * MM)),       # 4 x the expected 1 mm, exactly
])
def test_each_gate_passes_at_its_threshold_and_fails_one_float_beyond(gate: str, field: str, at: float,
                                                                     beyond: float) -> None:
    res = result(**{field: at})
    value, threshold, ok = res.gates[gate]
    assert (value, ok) == (at, True) and threshold == at
    check_gates(res)
    check_gates(res, DEFAULTS)
    failed = result(**{field: beyond})
    assert failed.gates[gate] == (beyond, threshold, False)
    err = failure(failed)
    assert (err.gate, err.value, err.threshold) == (gate, beyond, threshold)


def test_the_residual_floor_passes_at_a_quarter_of_the_expected_rms() -> None:
    """Expected 2**-10 m, RMS 2**-12 m: a ratio of 0.25 exactly; one float less fails."""
    res = result(residual_expected_m=2.0**-10, residual_rms_m=2.0**-12)
    assert res.gates["residual_floor"] == (0.25, 0.25, True)
    check_gates(res)
    err = failure(result(residual_expected_m=2.0**-10, residual_rms_m=below(2.0**-12)))
    assert err.gate == "residual_floor" and err.value == below(0.25) and err.threshold == 0.25


@pytest.mark.parametrize(("departure", "passes"), [
    ((math.radians(1.0), 5 * MM), True),                    # both exactly at their tolerance
    ((above(math.radians(1.0)), 5 * MM), False),           # the angle a hair beyond
    ((math.radians(1.0), above(5 * MM)), False),           # the offset a hair beyond, the angle within
    ((0.0, 6 * MM), False),                                 # a parallel plane 6 mm off
])
def test_the_expected_plane_needs_both_the_angle_and_the_offset_within_tolerance(
        departure: tuple[float, float], passes: bool) -> None:
    res = result(expected_departure=departure)
    assert res.gates["expected_plane"] == (departure[0], math.radians(1.0), passes)
    if passes:
        check_gates(res)
    else:
        err = failure(res)
        assert (err.gate, err.value, err.threshold) == ("expected_plane", departure[0], math.radians(1.0))


def test_the_gate_table_has_a_row_for_each_gate_that_applies() -> None:
    full = result()
    assert full.gates == {
        "valid_fraction": (1.0, 0.5, True), "residual_floor": (1.0, 0.25, True), "inlier_fraction": (1.0, 0.5, True),
        "residual_rms_m": (1 * MM, 4 * MM, True), "expected_plane": (0.0, math.radians(1.0), True),
        "coverage": (1.0, 0.5, True), "flatness": (0.0, 1 * MM, True)}
    assert list(full.gates) == ["valid_fraction", "residual_floor", "inlier_fraction", "residual_rms_m",
                                "expected_plane", "coverage", "flatness"]
    # a raw cloud: no image (coverage and flatness NaN), no expected plane, or one without tolerances
    for expected in ({"expected_departure": None, "expected_tolerance": None},
                     {"expected_departure": (0.0, 0.0), "expected_tolerance": None},
                     {"expected_departure": None, "expected_tolerance": (0.1, 0.1)}):
        bare = result(coverage=math.nan, flatness_m=math.nan, **expected)
        assert set(bare.gates) == {"valid_fraction", "residual_floor", "inlier_fraction", "residual_rms_m"}
        check_gates(bare)


# ---------------------------------------------------------------------- order and which settings apply
FAILING: dict[str, dict[str, object]] = {
    "valid_fraction": {"valid_fraction": 0.25},
    "residual_floor": {"lock_on": "every inlier on one level"},   # fails whatever the ratio
    "expected_plane": {"expected_departure": (0.0, 10 * MM)},
    "flatness": {"flatness_m": 2 * MM},
    "inlier_fraction": {"inlier_fraction": 0.25},
    "residual_rms_m": {"residual_rms_m": 5 * MM},
    "coverage": {"coverage": 0.25},
}


def test_the_first_failing_gate_in_their_order_is_named_whatever_else_fails() -> None:
    """Every gate failing, then repaired one at a time in the check order: each is named in turn."""
    assert GATE_NAMES == ("valid_fraction", "residual_floor", "expected_plane", "flatness", "inlier_fraction",
                          "residual_rms_m", "coverage")
    for k, name in enumerate(GATE_NAMES):
        fields: dict[str, object] = {}
        for later in GATE_NAMES[k:]:
            fields.update(FAILING[later])
        res = result(**fields)
        assert [g for g in GATE_NAMES if not res.gates[g][2]] == list(GATE_NAMES[k:])
        assert failure(res).gate == name
        assert failure(res, DEFAULTS).gate == name
    check_gates(result())


def test_gates_after_a_missing_one_are_still_checked() -> None:
    """No expected plane and no flatness (skipped, they come third and fourth): the inlier gate still fails."""
    res = result(expected_departure=None, expected_tolerance=None, flatness_m=math.nan, inlier_fraction=0.4)
    assert "expected_plane" not in res.gates and "flatness" not in res.gates
    assert failure(res).gate == "inlier_fraction"
    res = result(expected_departure=None, flatness_m=math.nan, coverage=0.25)
    assert failure(res).gate == "coverage"


def test_without_settings_the_fits_own_gate_table_is_applied() -> None:
    strict = FullFrameSettings(min_coverage=0.75)
    res = result(strict, coverage=0.5)
    assert res.gates["coverage"] == (0.5, 0.75, False)
    err = failure(res)                                     # the fit's own thresholds
    assert (err.gate, err.value, err.threshold) == ("coverage", 0.5, 0.75)
    check_gates(res, DEFAULTS)                             # others given: those apply, and pass
    lenient = result(coverage=0.25)
    check_gates(lenient, FullFrameSettings(min_coverage=0.25))
    assert failure(lenient).gate == "coverage"


def test_the_message_uses_the_settings_given_not_those_of_the_fit() -> None:
    """Range path, no sigmas: the expected RMS is the unit RMS x the noise at 1 m of the settings applied."""
    res = result(FullFrameSettings(expected_noise_m=0.004), sigma_given=False, sigma_stated=False,
                 residual_unit_rms_m=1.0, residual_rms_m=5 * MM)
    check_gates(res)                                       # 5 mm <= 4 x 4 mm
    err = failure(res, FullFrameSettings(expected_noise_m=0.001))
    assert str(err) == ("quality gate 'residual_rms_m' failed: 5 mm vs threshold 4 mm; inlier residual RMS 5 mm, "
                        "1 mm above the maximum of 4 mm (5 x the 1 mm the noise model expects for these pixels)")


# ---------------------------------------------------------------------- the expected RMS, the floor, the threshold
@pytest.mark.parametrize(("settings", "model", "expected"), [
    (FullFrameSettings(expected_noise_m=0.003), MeasurementModel(), 0.005),    # hypot(3, 4) mm
    (DEFAULTS, MeasurementModel(kind="tof", sigma_at_1m_m=0.003), 0.005),      # the camera's own noise
    (DEFAULTS, MeasurementModel(), math.hypot(3.2, 4.0) * MM),                 # the 3.2 mm default
])
def test_the_expected_rms_adds_the_quantisation_floor_in_quadrature(settings: FullFrameSettings,
                                                                    model: MeasurementModel,
                                                                    expected: float) -> None:
    res = result(settings, sigma_given=False, residual_unit_rms_m=1.0, residual_floor_m=4 * MM, measurement=model,
                 residual_expected_m=0.5 * MM)
    assert expected_rms_m(res, settings) == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize(("space", "given"), [("range", True), ("disparity", False), ("disparity", True)])
def test_given_sigmas_and_the_disparity_path_bring_their_own_expected_rms(space: str, given: bool) -> None:
    res = result(native_space=space, sigma_given=given, residual_unit_rms_m=1.0, residual_floor_m=4 * MM,
                 residual_expected_m=0.7 * MM)
    assert expected_rms_m(res, FullFrameSettings(expected_noise_m=0.003)) == 0.7 * MM


@pytest.mark.parametrize(("stated", "floor", "expected_ref"), [
    (True, 1 * MM, 2 * MM),      # the stated noise, above the floor
    (True, 3 * MM, 3 * MM),      # the floor, above the stated noise
    (False, 1 * MM, 1 * MM),     # nothing stated: the floor alone
    (False, 0.0, 0.0),
])
def test_the_floor_reference_is_the_larger_of_the_floor_and_the_stated_noise(stated: bool, floor: float,
                                                                            expected_ref: float) -> None:
    res = result(sigma_stated=stated, residual_floor_m=floor, residual_expected_m=2 * MM)
    assert floor_reference_m(res, DEFAULTS) == expected_ref


@pytest.mark.parametrize(("cap", "threshold"), [(None, 0.022), (0.01, 0.01), (0.03, 0.022), (0.022, 0.022)])
def test_the_residual_threshold_is_ratio_times_expected_plus_multipath_capped(cap: float | None,
                                                                             threshold: float) -> None:
    """4 x 5 mm + 2 mm of multipath allowance = 22 mm, unless the absolute cap is lower."""
    settings = FullFrameSettings(max_residual_rms_m=cap)
    res = result(settings, residual_expected_m=5 * MM, multipath_allowance_m=2 * MM)
    assert residual_threshold_m(res, settings) == pytest.approx(threshold, rel=1e-12)
    assert res.gates["residual_rms_m"][1] == pytest.approx(threshold, rel=1e-12)
    assert residual_threshold_m(res, FullFrameSettings(max_noise_ratio=2.0)) == pytest.approx(0.012, rel=1e-12)


# ---------------------------------------------------------------------- the residual floor and lock-on
def test_a_lock_on_fails_the_floor_gate_whatever_the_ratio() -> None:
    why = "every inlier on the 1.000 m level"
    res = result(lock_on=why, residual_floor_m=1 * MM, sigma_stated=False, residual_rms_m=2 * MM)
    assert res.gates["residual_floor"] == (2.0, 0.25, False)
    assert str(failure(res)) == ("quality gate 'residual_floor' failed: 2 vs threshold 0.25; the fit sat on one "
                                 "quantisation level: every inlier on the 1.000 m level; inlier residual RMS 2 mm "
                                 "against the 1 mm the sensor can deliver for these pixels (quantisation floor 1 mm)")
    bare = result(lock_on=why, residual_floor_m=0.0, sigma_stated=False, residual_rms_m=2 * MM)
    assert bare.gates["residual_floor"] == (0.0, 0.25, False)
    assert str(failure(bare)) == ("quality gate 'residual_floor' failed: 0 vs threshold 0.25; the fit sat on one "
                                  "quantisation level: every inlier on the 1.000 m level; inlier residual RMS 2 mm "
                                  "against a sensor that states no floor")


def test_a_sensor_stating_no_floor_passes_the_floor_gate_with_no_value() -> None:
    res = result(residual_floor_m=0.0, sigma_stated=False, residual_rms_m=0.0)
    value, threshold, ok = res.gates["residual_floor"]
    assert math.isnan(value) and threshold == 0.25 and ok
    check_gates(res)


@pytest.mark.parametrize(("stated", "text"), [
    (False, "quality gate 'residual_floor' failed: 0.2 vs threshold 0.25; inlier residual RMS 0.2 mm is 0.2 x the "
            "1 mm the sensor can deliver for these pixels (quantisation floor 1 mm), below the minimum of "
            "0.25 x: too good to be a measurement of this sensor (a fit on one quantisation level, or the wrong "
            "model)"),
    (True, "quality gate 'residual_floor' failed: 0.1 vs threshold 0.25; inlier residual RMS 0.2 mm is 0.1 x the "
           "2 mm the sensor can deliver for these pixels (quantisation floor 1 mm), below the minimum of "
           "0.25 x: too good to be a measurement of this sensor (a fit on one quantisation level, or the wrong "
           "model)"),
])
def test_the_floor_message_names_the_floor_and_the_noise_stated(stated: bool, text: str) -> None:
    res = result(residual_floor_m=1 * MM, sigma_stated=stated, residual_expected_m=2 * MM, residual_rms_m=0.2 * MM)
    assert str(failure(res)) == text


def test_the_floor_message_rounds_each_length_to_three_digits() -> None:
    """RMS 0.2354 mm and floor 1.234 mm sit just below a rounding step: 0.235 and 1.23 mm, ratio 0.190762."""
    res = result(residual_floor_m=1.234 * MM, sigma_stated=False, residual_rms_m=0.2354 * MM)
    assert str(failure(res)) == (
        "quality gate 'residual_floor' failed: 0.190762 vs threshold 0.25; inlier residual RMS 0.235 mm is 0.191 x "
        "the 1.23 mm the sensor can deliver for these pixels (quantisation floor 1.23 mm), below the "
        "minimum of 0.25 x: too good to be a measurement of this sensor (a fit on one quantisation level, or the "
        "wrong model)")


def test_a_fit_far_below_the_floor_reads_as_a_multiple_of_it_not_as_a_difference() -> None:
    """A noise-free camera stating 1 mm of noise: 1e-05 x the floor, printed beside its minimum of 0.25 x (it
    read "0.25 x below the minimum of 0.25 x" before: the difference printed equal to the threshold)."""
    res = result(residual_floor_m=0.0, sigma_stated=True, residual_expected_m=1 * MM, residual_rms_m=0.01 * MM * MM)
    err = failure(res)
    assert (err.gate, err.value, err.threshold, err.unit) == ("residual_floor", pytest.approx(1e-5, rel=1e-12),
                                                              0.25, "")
    assert str(err) == ("quality gate 'residual_floor' failed: 1e-05 vs threshold 0.25; inlier residual RMS 1e-05 mm "
                        "is 1e-05 x the 1 mm the sensor can deliver for these pixels (quantisation floor 0 mm), below "
                        "the minimum of 0.25 x: too good to be a measurement of this sensor (a fit on one "
                        "quantisation level, or the wrong model)")


@pytest.mark.parametrize(("departure", "shown", "limit", "beyond"), [
    (math.radians(15.0) + 1e-9, "15.0000001 deg", "15 deg", "5.73e-08 deg"),     # 1 nrad past 15 deg
    # the next float past it: 17 digits, which show radians(15) itself as 14.999999999999998 deg
    (above(math.radians(15.0)), "15.000000000000002 deg", "14.999999999999998 deg", "3.18e-15 deg"),
])
def test_an_angle_just_past_its_tolerance_never_prints_equal_to_it(departure: float, shown: str, limit: str,
                                                                    beyond: str) -> None:
    """The user's report: gate expected_plane "0.261799 vs threshold 0.261799" (radians, equal in print). Now in
    degrees, with the digits the difference needs; the attributes stay in radians."""
    tol = math.radians(15.0)
    err = failure(result(expected_departure=(departure, 3 * MM), expected_tolerance=(tol, 0.1)))
    assert (err.gate, err.value, err.threshold, err.unit) == ("expected_plane", departure, tol, "rad")
    assert str(err) == (f"quality gate 'expected_plane' failed: {shown} vs threshold {limit}; the fitted plane is "
                        f"{shown} from the expected one, {beyond} beyond the tolerance of {limit} (its offset, 3 mm, "
                        "is within 100 mm)")


def test_a_length_just_past_its_tolerance_never_prints_equal_to_it() -> None:
    err = failure(result(flatness_m=above(1 * MM)))
    assert (err.gate, err.value, err.threshold, err.unit) == ("flatness", above(1 * MM), 1 * MM, "m")
    assert str(err) == ("quality gate 'flatness' failed: 1.0000000000000002 mm vs threshold 1 mm; a local plane "
                        "departs from the global fit (beyond its uncertainty) by 1.0000000000000002 mm, 2.17e-16 mm "
                        "above the tolerance of 1 mm")


# ---------------------------------------------------------------------- the other texts, whole
@pytest.mark.parametrize(("fields", "text"), [
    ({"valid_fraction": 0.49},
     "quality gate 'valid_fraction' failed: 0.49 vs threshold 0.5; valid pixels 49 %, 1 % below the minimum of 50 %"),
    ({"inlier_fraction": 0.375},
     "quality gate 'inlier_fraction' failed: 0.375 vs threshold 0.5; plane inliers among the valid pixels 37.5 %, "
     "12.5 % below the minimum of 50 %"),
    ({"coverage": 17 / 36},
     "quality gate 'coverage' failed: 0.472222 vs threshold 0.5; image cells holding plane inliers 47.2 %, "
     "2.78 % below the minimum of 50 %"),
    ({"flatness_m": 1.5 * MM, "flatness_where": "the left half of the image"},
     "quality gate 'flatness' failed: 1.5 mm vs threshold 1 mm; a local plane departs from the global fit (beyond "
     "its uncertainty) by 1.5 mm, 0.5 mm above the tolerance of 1 mm (in the left half of the image)"),
    ({"flatness_m": 1.5 * MM},
     "quality gate 'flatness' failed: 1.5 mm vs threshold 1 mm; a local plane departs from the global fit (beyond "
     "its uncertainty) by 1.5 mm, 0.5 mm above the tolerance of 1 mm"),
    ({"residual_rms_m": 5 * MM},
     "quality gate 'residual_rms_m' failed: 5 mm vs threshold 4 mm; inlier residual RMS 5 mm, 1 mm above the "
     "maximum of 4 mm (5 x the 1 mm the noise model expects for these pixels)"),
    # an expected 1.234 mm just below a rounding step: 1.23 mm, the threshold 4 x 1.234 = 4.936 mm
    ({"residual_rms_m": 5 * MM, "residual_expected_m": 1.234 * MM},
     "quality gate 'residual_rms_m' failed: 5 mm vs threshold 4.936 mm; inlier residual RMS 5 mm, 0.064 mm above "
     "the maximum of 4.94 mm (4.05 x the 1.23 mm the noise model expects for these pixels)"),
    # nothing expected (no noise, no floor): a multipath allowance of 2 mm is the whole threshold
    ({"residual_rms_m": 3 * MM, "sigma_given": False, "sigma_stated": False, "residual_unit_rms_m": 0.0,
      "multipath_allowance_m": 2 * MM},
     "quality gate 'residual_rms_m' failed: 3 mm vs threshold 2 mm; inlier residual RMS 3 mm, 1 mm above the "
     "maximum of 2 mm"),
    ({"expected_departure": (math.radians(2.0), 3 * MM)},
     "quality gate 'expected_plane' failed: 2 deg vs threshold 1 deg; the fitted plane is 2 deg from the "
     "expected one, 1 deg beyond the tolerance of 1 deg (its offset, 3 mm, is within 5 mm)"),
    ({"expected_departure": (math.radians(0.5), 7.5 * MM)},
     "quality gate 'expected_plane' failed: 0.5 deg vs threshold 1 deg; the fitted plane is 7.5 mm from the "
     "expected one, 2.5 mm beyond the tolerance of 5 mm (its angle, 0.5 deg, is within 1 deg)"),
    # one part exactly at its tolerance is within it: only the other is named
    ({"expected_departure": (math.radians(1.0), 7.5 * MM)},
     "quality gate 'expected_plane' failed: 1 deg vs threshold 1 deg; the fitted plane is 7.5 mm from the "
     "expected one, 2.5 mm beyond the tolerance of 5 mm (its angle, 1 deg, is within 1 deg)"),
    ({"expected_departure": (math.radians(2.0), 5 * MM)},
     "quality gate 'expected_plane' failed: 2 deg vs threshold 1 deg; the fitted plane is 2 deg from the "
     "expected one, 1 deg beyond the tolerance of 1 deg (its offset, 5 mm, is within 5 mm)"),
    # both beyond: both named, with their excesses
    ({"expected_departure": (math.radians(1.5), 6 * MM)},
     "quality gate 'expected_plane' failed: 1.5 deg vs threshold 1 deg; the fitted plane is 1.5 deg and 6 mm "
     "from the expected one, 0.5 deg and 1 mm beyond the tolerances of 1 deg and 5 mm"),
])
def test_each_gate_says_what_failed_by_how_much_in_one_line(fields: dict[str, object], text: str) -> None:
    err = failure(result(**fields))
    assert str(err) == text and "\n" not in text


# ---------------------------------------------------------------------- coverage cells
def test_coverage_cells_split_an_uneven_image_as_evenly_as_integers_allow() -> None:
    """7 rows x 8 columns in a grid of 3 columns x 2 rows: rows 0-2 / 3-6, columns 0-1 / 2-4 / 5-7."""
    mask = np.zeros((7, 8), dtype=bool)
    mask[0, 0] = mask[6, 7] = mask[3, 2] = mask[4, 4] = mask[2, 5] = True
    cells = coverage_cells(mask, FullFrameSettings(coverage_grid=(3, 2)))
    assert cells.counts.tolist() == [[1, 0, 1], [0, 2, 1]]
    assert cells.area.tolist() == [[6, 9, 9], [8, 12, 12]]
    assert cells.row_edges.tolist() == [0, 3] and cells.col_edges.tolist() == [0, 2, 5]
    assert cells._fields == ("counts", "area", "row_edges", "col_edges")


def test_a_grid_finer_than_the_image_has_one_cell_per_pixel() -> None:
    mask = np.array([[True, False, True], [False, False, True]])
    cells = coverage_cells(mask, DEFAULTS)                 # 6 x 6 cells asked, 3 x 2 pixels
    assert cells.counts.tolist() == [[1, 0, 1], [0, 0, 1]] and cells.area.tolist() == [[1, 1, 1], [1, 1, 1]]
    assert cells.row_edges.tolist() == [0, 1] and cells.col_edges.tolist() == [0, 1, 2]
    assert image_coverage(mask, DEFAULTS) == 0.5


def test_cells_of_more_than_255_pixels_are_counted_in_full() -> None:
    """One cell of 40 x 40 pixels: 1600 inliers and 1600 region pixels (no 8-bit wrap-around)."""
    mask = np.ones((40, 40), dtype=bool)
    one = FullFrameSettings(coverage_grid=(1, 1))
    cells = coverage_cells(mask, one, region=mask)
    assert cells.counts.tolist() == [[1600]] and cells.area.tolist() == [[1600]]
    assert coverage_cells(mask, one).counts.tolist() == [[1600]]


def sparse(per_cell: int, *, short_cells: int = 0) -> np.ndarray:
    """A 30 x 60 mask (6 x 6 cells of 5 x 10 px) with ``per_cell`` (at most 10) inliers in every cell, one fewer
    in the first ``short_cells`` cells (row by row)."""
    mask = np.zeros((30, 60), dtype=bool)
    for k in range(36):
        r, c = divmod(k, 6)
        n = per_cell - (k < short_cells)
        spread = np.arange(0, 50, 5)[:n]                 # every 5th of the cell's 50 pixels, row by row
        mask[5 * r + spread // 10, 10 * c + spread % 10] = True
    return mask


def test_sparse_inliers_in_every_cell_cover_it_at_exactly_a_fifth() -> None:
    """10 inliers of 50 px in every cell is exactly min_cell_inlier_fraction = 0.2: all 36 cells count."""
    assert sparse(10).sum() == 360 and image_coverage(sparse(10), DEFAULTS) == 1.0
    assert image_coverage(sparse(10, short_cells=1), DEFAULTS) == 35 / 36
    assert image_coverage(sparse(10, short_cells=18), DEFAULTS) == 0.5
    assert image_coverage(sparse(10, short_cells=19), DEFAULTS) == 17 / 36
    assert image_coverage(sparse(9), DEFAULTS) == 0.0
    assert image_coverage(sparse(9), FullFrameSettings(min_cell_inlier_fraction=0.18)) == 1.0
    assert image_coverage(sparse(10), FullFrameSettings(min_cell_inlier_fraction=above(0.2))) == 0.0
    assert image_coverage(np.zeros((30, 60), dtype=bool), FullFrameSettings(min_cell_inlier_fraction=0.0)) == 1.0


def test_with_a_region_cells_are_judged_on_their_region_pixels_and_empty_ones_are_not_counted() -> None:
    """Region: the left 20 columns (2 of 6 cell columns, 12 cells) and 10 px of a third column's top cell."""
    region = np.zeros((30, 60), dtype=bool)
    region[:, :20] = True
    region[0, 20:30] = True                                # 10 px of the cell at row 0, column 2
    mask = sparse(10) & region
    cells = coverage_cells(mask, DEFAULTS, region)
    assert cells.area[0].tolist() == [50, 50, 10, 0, 0, 0] and cells.area[1].tolist() == [50, 50, 0, 0, 0, 0]
    assert cells.counts[0, 2] == 2                         # 2 of its 10 region pixels: a fifth, covered
    assert image_coverage(mask, DEFAULTS, region) == 1.0   # 13 cells counted, all covered
    mask[0, 20:30] = False
    assert image_coverage(mask, DEFAULTS, region) == 12 / 13
    assert image_coverage(mask, DEFAULTS) == 12 / 36       # without the region every cell counts
