"""Quality gates of a full-frame fit: the gate table and :func:`check_gates` (image coverage: ``points.py``)."""

from __future__ import annotations

import math

from cellcal.core.methods.fullframe.points import CoverageCells, coverage_cells, image_coverage
from cellcal.core.methods.fullframe.result import FullFrameResult
from cellcal.core.methods.fullframe.settings import FullFrameSettings
from cellcal.devices.errors import CalibrationQualityError
from cellcal.devices.readable import distinct, quantity, quantity_pair

__all__ = ["GATE_NAMES", "GATE_UNITS", "CoverageCells", "check_gates", "coverage_cells", "expected_rms_m",
           "floor_reference_m", "image_coverage", "residual_threshold_m"]

#: Gate names in the order they are checked.
#: A lock-on, a wrong plane and a second surface come early: each also halves the inliers and the
#: coverage, and naming it says why.
GATE_NAMES = ("valid_fraction", "residual_floor", "expected_plane", "flatness", "inlier_fraction",
              "residual_rms_m", "coverage")

#: Gate name -> the SI unit of its value and threshold (``""``: a fraction or a ratio), for the error message.
GATE_UNITS = {"valid_fraction": "", "residual_floor": "", "expected_plane": "rad", "flatness": "m",
              "inlier_fraction": "", "residual_rms_m": "m", "coverage": ""}

#: How a flatness refusal judged in sensor terms begins (``staircase.judge``): said after the value, not as a place.
SENSOR_TERMS = ("a staircase of ", "a bend of ")

#: Gate name -> (what is measured, how it failed, display unit) for the error message.
_GATE_TEXT = {
    "valid_fraction": ("valid pixels", "below the minimum", "%"),
    "inlier_fraction": ("plane inliers among the valid pixels", "below the minimum", "%"),
    "residual_rms_m": ("inlier residual RMS", "above the maximum", "mm"),
    "coverage": ("image cells holding plane inliers", "below the minimum", "%"),
    "flatness": ("a local plane departs from the global fit (beyond its uncertainty) by", "above the tolerance",
                 "mm"),
}


def expected_rms_m(result: FullFrameResult, settings: FullFrameSettings) -> float:
    """The inliers' RMS orthogonal residual the sensor model predicts, metres.

    Range path without given sigmas: the noise law's RMS for these pixels at the noise the
    settings or the camera state (``expected_noise_m``), with the quantisation floor added
    in quadrature (Sheppard). Otherwise (given sigmas, the disparity path) what the fit found.
    """
    if result.native_space != "range" or result.sigma_given:
        return result.residual_expected_m
    noise = result.residual_unit_rms_m * settings.noise_at_1m_m(result.measurement)
    return math.hypot(noise, result.residual_floor_m)


def floor_reference_m(result: FullFrameResult, settings: FullFrameSettings) -> float:
    """The least RMS residual the sensor can deliver: its quantisation floor, or its stated noise if larger, m."""
    stated = expected_rms_m(result, settings) if result.sigma_stated else 0.0
    return max(result.residual_floor_m, stated)


def residual_threshold_m(result: FullFrameResult, settings: FullFrameSettings) -> float:
    """The ``residual_rms_m`` gate's threshold, metres.

    ``max_noise_ratio`` times the expected RMS plus the camera's multipath allowance,
    capped by ``max_residual_rms_m``.
    """
    threshold = float(settings.max_noise_ratio * expected_rms_m(result, settings) + result.multipath_allowance_m)
    if settings.max_residual_rms_m is not None:
        threshold = min(threshold, settings.max_residual_rms_m)
    return threshold


def _floor_gate(result: FullFrameResult, settings: FullFrameSettings) -> tuple[float, float, bool]:
    """``residual_floor``: (RMS over the floor reference, ``min_noise_ratio``, passed); a lock-on fails."""
    ref = floor_reference_m(result, settings)
    locked = bool(result.lock_on)
    if ref > 0:
        value = result.residual_rms_m / ref
        return value, settings.min_noise_ratio, value >= settings.min_noise_ratio and not locked
    return (0.0 if locked else math.nan), settings.min_noise_ratio, not locked


def gate_table(settings: FullFrameSettings, result: FullFrameResult) -> dict[str, tuple[float, float, bool]]:
    """Gate name -> (value, threshold, passed) of a result under ``settings``.

    Coverage and flatness are skipped when NaN (no image), ``expected_plane`` without an
    expected plane.
    """
    r = result
    rms_max = residual_threshold_m(r, settings)
    gates = {
        "valid_fraction": (r.valid_fraction, settings.min_valid_fraction,
                           r.valid_fraction >= settings.min_valid_fraction),
        "residual_floor": _floor_gate(r, settings),
        "inlier_fraction": (r.inlier_fraction, settings.min_inlier_fraction,
                            r.inlier_fraction >= settings.min_inlier_fraction),
        "residual_rms_m": (r.residual_rms_m, rms_max, r.residual_rms_m <= rms_max),
    }
    if r.expected_departure is not None and r.expected_tolerance is not None:
        (angle, offset), (tol_a, tol_o) = r.expected_departure, r.expected_tolerance
        gates["expected_plane"] = (angle, tol_a, angle <= tol_a and offset <= tol_o)
    if math.isfinite(r.coverage):
        gates["coverage"] = (r.coverage, settings.min_coverage, r.coverage >= settings.min_coverage)
    if math.isfinite(r.flatness_m):
        gates["flatness"] = (r.flatness_m, settings.flatness_tolerance_m, r.flatness_m <= settings.flatness_tolerance_m)
    return gates


def _floor_message(value: float, threshold: float, result: FullFrameResult, settings: FullFrameSettings) -> str:
    ref = floor_reference_m(result, settings)
    rms = f"inlier residual RMS {quantity(result.residual_rms_m, 'm')}"
    what = (f"the {quantity(ref, 'm')} the sensor can deliver for these pixels (quantisation floor "
            f"{quantity(result.residual_floor_m, 'm')})") if ref > 0 else "a sensor that states no floor"
    if result.lock_on:
        return f"the fit sat on one quantisation level: {result.lock_on}; {rms} against {what}"
    shown, limit = distinct(value, threshold)
    return (f"{rms} is {shown} x {what}, below the minimum of {limit} x: "
            "too good to be a measurement of this sensor (a fit on one quantisation level, or the wrong model)")


def _expected_message(result: FullFrameResult) -> str:
    angle, offset = result.expected_departure or (math.nan, math.nan)
    tol_a, tol_o = result.expected_tolerance or (math.nan, math.nan)
    # each part as the user reads it, degrees and millimetres, never printed equal to its tolerance
    a, ta = quantity_pair(angle, tol_a, "rad")
    o, to = quantity_pair(offset, tol_o, "m", digits=4)
    da, do = quantity(angle - tol_a, "rad"), quantity(offset - tol_o, "m", digits=4)
    angle_bad, offset_bad = not angle <= tol_a, not offset <= tol_o
    if angle_bad and offset_bad:
        return (f"the fitted plane is {a} and {o} from the expected one, {da} and {do} beyond the tolerances of "
                f"{ta} and {to}")
    if offset_bad:
        return (f"the fitted plane is {o} from the expected one, {do} beyond the tolerance of {to} (its angle, {a}, "
                f"is within {ta})")
    return (f"the fitted plane is {a} from the expected one, {da} beyond the tolerance of {ta} (its offset, {o}, "
            f"is within {to})")


def _message(name: str, value: float, threshold: float, result: FullFrameResult,
             settings: FullFrameSettings) -> str:
    if name == "residual_floor":
        return _floor_message(value, threshold, result, settings)
    if name == "expected_plane":
        return _expected_message(result)
    what, side, unit = _GATE_TEXT[name]
    if unit == "mm":
        shown, limit = quantity_pair(value, threshold, "m")
        by = quantity(abs(value - threshold), "m")
    else:
        pct, pct_limit = distinct(value * 100.0, threshold * 100.0)
        shown, limit = f"{pct} %", f"{pct_limit} %"
        by = f"{abs(value - threshold) * 100.0:.3g} %"
    text = f"{what} {shown}, {by} {side} of {limit}"
    expected = expected_rms_m(result, settings)
    if name == "residual_rms_m" and expected > 0:
        text += f" ({value / expected:.3g} x the {quantity(expected, 'm')} the noise model expects for these pixels)"
    elif name == "flatness" and result.flatness_where.startswith(SENSOR_TERMS):
        text += f": {result.flatness_where}"                # what the sensor terms saw (ADR 0060)
    elif name == "flatness" and result.flatness_where:
        text += f" (in {result.flatness_where})"
    return text


def check_gates(result: FullFrameResult, settings: FullFrameSettings | None = None) -> None:
    """Raise for the first quality gate the result fails.

    Args:
        result: A fit from :func:`fit_full_frame` or :func:`fit_plane_points`.
        settings: Thresholds to apply; None re-applies the ones the fit was made with.
            (``flatness_grid`` and ``flatness_sigma`` shape the measured value: changing
            them needs a new fit.)

    Raises:
        CalibrationQualityError: Naming the gate, the value, the threshold and by how
            much it was missed.
    """
    cfg = settings or result.settings
    gates = result.gates if settings is None else gate_table(settings, result)
    for name in GATE_NAMES:
        if name not in gates:
            continue
        value, threshold, ok = gates[name]
        if not ok:
            raise CalibrationQualityError(name, value, threshold, _message(name, value, threshold, result, cfg),
                                          unit=GATE_UNITS[name])
