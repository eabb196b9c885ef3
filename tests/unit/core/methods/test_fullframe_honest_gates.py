"""Honest gates both ways (issue 27): the residual floor, the camera's own noise law, its multipath allowance."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from tof_frames import ToFSetup, make_frame

from cellcal.core.methods.fullframe import FullFrameSettings, check_gates, fit_full_frame
from cellcal.core.methods.fullframe.gates import expected_rms_m, floor_reference_m, gate_table, residual_threshold_m
from cellcal.devices.errors import CalibrationQualityError, ConfigError
from cellcal.devices.measurement import MeasurementModel
from cellcal.devices.types import Frame


def _stating(frame: Frame, **model: float) -> Frame:
    return dataclasses.replace(frame, measurement=MeasurementModel(kind="tof", source="config", **model))


def _raised(result: object, settings: FullFrameSettings | None = None) -> CalibrationQualityError:
    with pytest.raises(CalibrationQualityError) as info:
        check_gates(result, settings)   # type: ignore[arg-type]
    assert "\n" not in str(info.value)
    return info.value


def test_residual_floor_is_pinned_at_min_noise_ratio() -> None:
    """A camera stating twice the noise it delivers: RMS / stated RMS ~ 0.5; the gate holds at exactly that ratio."""
    res = fit_full_frame(_stating(make_frame(ToFSetup(), 3), sigma_at_1m_m=0.0064))
    value, threshold, ok = res.gates["residual_floor"]
    assert res.sigma_stated and ok and threshold == 0.25
    assert value == res.residual_rms_m / floor_reference_m(res, res.settings)
    assert value == pytest.approx(0.5, abs=0.03)
    check_gates(res, FullFrameSettings(min_noise_ratio=value))          # equal: passes
    err = _raised(res, FullFrameSettings(min_noise_ratio=float(np.nextafter(value, 1.0))))
    assert err.gate == "residual_floor" and err.value == value
    assert "the sensor can deliver for these pixels" in str(err) and "below the minimum of" in str(err)


def test_residual_floor_is_the_quantisation_step_when_no_noise_is_stated() -> None:
    """Noise-free ranges rounded to 1 mm: RMS = the floor q/sqrt(12) across the plane; a camera claiming 10 mm
    steps cannot deliver 0.29 mm and is refused; one stating nothing has no floor."""
    frame = make_frame(ToFSetup(noise_1m_m=0.0, quantisation_m=0.001), 0)
    res = fit_full_frame(_stating(frame, range_step_m=0.001))
    assert not res.sigma_stated and res.residual_floor_m < 0.001 / math.sqrt(12.0)
    assert res.residual_floor_m > 0.8 * 0.001 / math.sqrt(12.0)       # cos of the 10 deg view > 0.8
    assert res.gates["residual_floor"][0] == pytest.approx(1.0, abs=0.05)
    check_gates(res)
    coarse = fit_full_frame(_stating(frame, range_step_m=0.01))
    err = _raised(coarse)
    assert err.gate == "residual_floor" and err.value == pytest.approx(0.1, abs=0.01)
    assert "too good to be a measurement of this sensor" in str(err)
    unstated = fit_full_frame(frame)
    assert unstated.residual_floor_m == 0.0 and math.isnan(unstated.gates["residual_floor"][0])
    assert unstated.gates["residual_floor"][2]


def test_tof_noise_law_comes_from_the_camera_unless_the_config_sets_it() -> None:
    """A camera 12.5 x noisier than the 3.2 mm default: refused as unknown, accepted when it states its noise,
    refused again when [full_frame] insists on 3.2 mm."""
    frame = make_frame(ToFSetup(noise_1m_m=0.04), 0)
    assert _raised(fit_full_frame(frame)).gate == "residual_rms_m"
    stated = fit_full_frame(_stating(frame, sigma_at_1m_m=0.04, distance_exponent=1.5))
    check_gates(stated)
    assert stated.noise_ratio == pytest.approx(1.0, abs=0.05)
    assert stated.residual_expected_m == pytest.approx(expected_rms_m(stated, stated.settings))
    assert _raised(stated, FullFrameSettings(expected_noise_m=0.0032)).gate == "residual_rms_m"
    # the camera's exponent weights the fit: the same numbers as the config stating it
    law = fit_full_frame(_stating(frame, sigma_at_1m_m=0.04, distance_exponent=2.0))
    cfg = fit_full_frame(frame, FullFrameSettings(noise_distance_exponent=2.0, expected_noise_m=0.04))
    assert law.plane.offset_m == cfg.plane.offset_m and law.tilt_x_rad == cfg.tilt_x_rad


def test_multipath_allowance_adds_to_the_residual_gate() -> None:
    frame = make_frame(ToFSetup(), 1)
    plain = fit_full_frame(_stating(frame, sigma_at_1m_m=0.0032))
    allowed = fit_full_frame(_stating(frame, sigma_at_1m_m=0.0032, multipath_m=0.002))
    assert allowed.multipath_allowance_m == 0.002
    rms_max = allowed.gates["residual_rms_m"][1]
    assert rms_max == pytest.approx(4.0 * allowed.residual_expected_m + 0.002)
    assert rms_max == residual_threshold_m(allowed, allowed.settings)
    assert rms_max - plain.gates["residual_rms_m"][1] == pytest.approx(0.002, rel=1e-6)
    # pinned: the RMS itself as the cap passes, the next float below fails
    at = FullFrameSettings(max_residual_rms_m=allowed.residual_rms_m)
    check_gates(allowed, at)
    err = _raised(allowed, FullFrameSettings(max_residual_rms_m=float(np.nextafter(allowed.residual_rms_m, 0.0))))
    assert err.gate == "residual_rms_m"


def test_result_says_its_model_and_native_space() -> None:
    res = fit_full_frame(_stating(make_frame(ToFSetup(), 2), sigma_at_1m_m=0.0032, range_step_m=0.001))
    d = res.to_dict()
    assert d["native_space"] == "range" and d["measurement"]["kind"] == "tof"
    assert d["measurement"]["sigma_at_1m_m"] == 0.0032 and d["residual_floor_m"] == res.residual_floor_m
    assert set(d["interval_factors"]) == {"observed_scale", "spatial", "quantisation", "systematic_allowance"}
    assert gate_table(res.settings, res) == res.gates


@pytest.mark.parametrize(("key", "value"), [("expected_noise_m", 0.0), ("noise_distance_exponent", -1.0),
                                             ("min_noise_ratio", 1.5)])
def test_settings_reject_absurd_values_naming_the_key(key: str, value: float) -> None:
    with pytest.raises(ConfigError) as info:
        FullFrameSettings(**{key: value})
    assert f"full_frame.{key}" in str(info.value)
    assert FullFrameSettings().expected_noise_m is None and FullFrameSettings().noise_distance_exponent is None
