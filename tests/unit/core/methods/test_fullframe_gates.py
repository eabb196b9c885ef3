"""Full-frame quality gates: valid and inlier fractions, the residual in units of the noise, coverage, flatness."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from tof_frames import RESOLUTIONS, ToFSetup, draw, make_frame, render, scattered_boxes, with_

from cellcal.core.methods.fullframe import GATE_NAMES, FullFrameSettings, check_gates, fit_full_frame
from cellcal.devices.errors import CalibrationQualityError
from cellcal.devices.types import Frame


def _masked(frame: Frame, valid: np.ndarray, xyz: np.ndarray | None = None) -> Frame:
    xyz = (frame.xyz if xyz is None else xyz).astype(np.float32).copy()
    xyz[~valid] = np.nan
    dist = np.linalg.norm(xyz, axis=-1).astype(np.float32)
    return dataclasses.replace(frame, xyz=xyz, distance=dist, valid=valid & np.isfinite(dist))


def _failed(frame: Frame | list[Frame], settings: FullFrameSettings | None = None) -> CalibrationQualityError:
    with pytest.raises(CalibrationQualityError) as info:
        check_gates(fit_full_frame(frame, settings))
    assert "\n" not in str(info.value)
    return info.value


def test_gate_mostly_invalid_frame() -> None:
    frame = make_frame(ToFSetup(), 7)
    valid = frame.valid.copy()
    valid[:, 60:] = False                                # 27 % of the image stays valid
    err = _failed(_masked(frame, valid))
    assert err.gate == "valid_fraction" and err.value == pytest.approx(60 / 224, abs=0.01)
    assert "valid pixels" in str(err) and "below the minimum of 50 %" in str(err)


def test_gate_plane_seen_in_one_corner_fails_coverage() -> None:
    """Data only in the left 60 % of the image, its top 45 % scattered junk (no second surface):
    valid and inlier fractions and flatness pass, but the plane is seen in one corner of the image."""
    frame = make_frame(ToFSetup(), 8)
    h, w = frame.shape
    valid = frame.valid.copy()
    valid[:, int(0.6 * w):] = False
    xyz = frame.xyz.astype(np.float64).copy()
    top = xyz[: int(0.45 * h)]
    top *= np.random.default_rng(3).uniform(0.5, 0.9, top.shape[:2])[..., None]   # along the same rays
    res = fit_full_frame(_masked(frame, valid, xyz))
    assert res.gates["valid_fraction"][2] and res.gates["inlier_fraction"][2] and res.gates["flatness"][2]
    with pytest.raises(CalibrationQualityError) as info:
        check_gates(res)
    assert info.value.gate == "coverage" and info.value.value < 0.5
    assert "image cells holding plane inliers" in str(info.value)


@pytest.mark.parametrize("seed", range(4))
def test_gates_accept_scattered_clutter_hiding_40_percent(seed: int) -> None:
    base = ToFSetup(flying=0.5)
    st = with_(base, boxes=scattered_boxes(0.4, 100 + seed, base))
    res = fit_full_frame(make_frame(st, seed))
    check_gates(res)
    assert res.flatness_m == 0.0 and res.flatness_where == ""


def test_gate_inlier_fraction() -> None:
    frame = make_frame(ToFSetup(), 9)
    xyz = frame.xyz.astype(np.float64).copy()
    flat = xyz.reshape(-1, 3)
    rng = np.random.default_rng(1)
    bad = rng.random(flat.shape[0]) < 0.6                # 60 % gross outliers, not a surface
    flat[bad] = rng.uniform([-1.0, -1.0, 0.2], [1.0, 1.0, 2.0], (int(bad.sum()), 3))
    assert _failed(_masked(frame, frame.valid, xyz)).gate == "inlier_fraction"


def test_residual_gate_is_in_units_of_the_expected_noise() -> None:
    """A camera three times noisier than the sim (10 mm at 1 m) seeing the plane from 1.4 to 3.4 m: every
    planar frame passes (the old fixed 10 mm gate failed them); 12.5 times the expected noise fails."""
    st = ToFSetup(noise_1m_m=0.01, distance_m=1.8, tilt_x_deg=40.0, max_range_m=6.0)
    rend = render(st)
    assert np.nanmax(rend.range_m) > 3.0
    for k in range(20):
        res = fit_full_frame(draw(rend, np.random.default_rng(k)))
        check_gates(res)
        assert res.residual_rms_m > 0.02 and res.noise_ratio == pytest.approx(3.1, abs=0.15)
    err = _failed(make_frame(ToFSetup(noise_1m_m=0.04), 0))
    assert err.gate == "residual_rms_m" and "12.5 x the" in str(err) and "the noise model expects" in str(err)
    # the camera's own noise level moves the gate with it
    check_gates(fit_full_frame(make_frame(ToFSetup(noise_1m_m=0.04), 0)), FullFrameSettings(expected_noise_m=0.04))


def test_residual_gate_has_an_optional_absolute_cap() -> None:
    res = fit_full_frame(make_frame(ToFSetup(), 2))
    check_gates(res)
    with pytest.raises(CalibrationQualityError) as info:
        check_gates(res, FullFrameSettings(max_residual_rms_m=0.0005))
    assert info.value.gate == "residual_rms_m" and info.value.threshold == 0.0005


@pytest.mark.parametrize(("width", "height"), RESOLUTIONS[:2])
@pytest.mark.parametrize(("surface", "param", "at_least_m"), [
    ("roof", 20.0, 0.1),        # +-20 deg, split 50/50: the fit returns one side
    ("step", 0.05, 0.04),       # 5 cm: one side
    ("crease", 1.0, 0.0011),    # two planes 1 deg apart: the fit returns their average
])
def test_flatness_gate_flags_a_roof_a_step_and_a_crease(width: int, height: int, surface: str, param: float,
                                                        at_least_m: float) -> None:
    st = with_(ToFSetup(width=width, height=height), surface=surface, surface_param=param)
    err = _failed(make_frame(st, 1))
    assert err.gate == "flatness" and err.value > at_least_m
    assert "departs from the global fit" in str(err) and "above the tolerance of 1 mm" in str(err)


@pytest.mark.slow
def test_flatness_gate_flags_a_crease_at_1280x800() -> None:
    st = with_(ToFSetup(width=1280, height=800), surface="crease", surface_param=1.0)
    assert _failed(make_frame(st, 1)).gate == "flatness"


def test_flatness_gate_passes_a_flat_plane_and_a_half_degree_crease_below_tolerance() -> None:
    for st in (ToFSetup(), with_(ToFSetup(), surface="crease", surface_param=0.5),
               ToFSetup(border_bias_m=0.002)):
        res = fit_full_frame(make_frame(st, 4))
        check_gates(res)
        assert res.flatness_m < 0.0008
    # ... and a tighter tolerance flags the 0.5 deg crease in the image half it lies in
    res = fit_full_frame(make_frame(with_(ToFSetup(), surface="crease", surface_param=0.5), 4))
    with pytest.raises(CalibrationQualityError, match="half of the image") as info:
        check_gates(res, FullFrameSettings(flatness_tolerance_m=0.0003))
    assert info.value.gate == "flatness"


def test_check_gates_with_other_thresholds() -> None:
    base = ToFSetup()
    res = fit_full_frame(make_frame(with_(base, boxes=scattered_boxes(0.3, 1, base)), 1))
    check_gates(res)                                     # defaults: passes
    with pytest.raises(CalibrationQualityError) as info:
        check_gates(res, FullFrameSettings(min_inlier_fraction=0.9))
    assert info.value.gate == "inlier_fraction" and info.value.threshold == 0.9


def test_gates_are_checked_in_their_order() -> None:
    res = fit_full_frame(make_frame(with_(ToFSetup(), surface="step", surface_param=0.05), 0))
    failed = [name for name in GATE_NAMES if name in res.gates and not res.gates[name][2]]
    assert failed[0] == "flatness" and set(res.gates) == set(GATE_NAMES) - {"expected_plane"}   # none expected
