"""Intervals never narrower than spatially correlated error and quantisation allow (issue 27)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from tof_frames import ToFSetup, make_frame

from cellcal.core.methods.fullframe import fit_full_frame
from cellcal.core.methods.fullframe.honesty import design_effect, quantisation_floor, rounding_allowance_m
from cellcal.core.methods.fullframe.passes import basis
from cellcal.devices.measurement import MeasurementModel


def test_design_effect_of_independent_and_of_correlated_residuals() -> None:
    h, w = 172, 224
    mask = np.ones(h * w, bool)
    rng = np.random.default_rng(5)
    white = rng.standard_normal(h * w).astype(np.float32)
    deff, se = design_effect(white, [mask], (h, w))
    assert se == pytest.approx(math.sqrt(2.0 / ((h // 7) * (w // 7))))      # 7-px blocks
    assert abs(deff - 1.0) < 3.0 * se
    # a smooth field shared by neighbouring pixels (half the variance): each 49-px block sums it coherently
    yy, xx = np.mgrid[0:h, 0:w]
    field = np.sin(xx / 15.0) * np.cos(yy / 11.0)
    shared = (white + (field / field.std()).reshape(-1)).astype(np.float32)
    deff_c, _ = design_effect(shared, [mask], (h, w))
    assert 15.0 < deff_c < 30.0                                              # ~ 1 + 49 * 0.5
    # pooled frames: each frame's blocks count
    deff_2, se_2 = design_effect(np.concatenate([white, white]), [mask, mask], (h, w))
    assert deff_2 == pytest.approx(deff) and se_2 == pytest.approx(se / math.sqrt(2.0))


def test_correlated_border_bias_widens_the_intervals_and_says_so() -> None:
    plain = fit_full_frame(make_frame(ToFSetup(), 4))
    biased = fit_full_frame(make_frame(ToFSetup(border_bias_m=0.002), 4))
    assert plain.interval_factors.spatial == 1.0 and plain.interval_notes == ()
    k = biased.interval_factors.spatial
    assert k > 2.0 and any("correlated across neighbouring pixels" in n for n in biased.interval_notes)
    assert biased.tilt_x_sigma_rad / plain.tilt_x_sigma_rad == pytest.approx(math.sqrt(k), rel=0.1)
    assert biased.to_dict()["interval_factors"]["spatial"] == k


def test_quantisation_floor_of_a_covariance() -> None:
    """Zero covariance takes the floor's: per tilt floor / (sqrt(N) L); a wider one is left alone."""
    rng = np.random.default_rng(2)
    uv = np.stack([rng.uniform(-0.2, 0.2, 4000), rng.uniform(-0.1, 0.1, 4000)])
    uv -= uv.mean(axis=1, keepdims=True)
    floor_m, n = 0.004, 100_000
    cov, held = quantisation_floor(np.zeros((3, 3)), floor_m, uv, n)
    assert held
    lu, lv = np.sqrt(np.mean(uv ** 2, axis=1))
    assert math.sqrt(cov[0, 0]) == pytest.approx(floor_m / (math.sqrt(n) * lu), rel=1e-3)
    assert math.sqrt(cov[1, 1]) == pytest.approx(floor_m / (math.sqrt(n) * lv), rel=1e-3)
    assert math.sqrt(cov[2, 2]) == pytest.approx(floor_m / math.sqrt(n), rel=1e-3)
    wide = cov * 4.0
    same, held = quantisation_floor(wide, floor_m, uv, n)
    assert not held and same is wide
    partly = np.diag([cov[0, 0] * 4.0, cov[1, 1] * 0.25, cov[2, 2] * 4.0])  # one direction below the floor
    out, held = quantisation_floor(partly, floor_m, uv, n)
    assert held and out[1, 1] == pytest.approx(cov[1, 1], rel=1e-6) and out[0, 0] == pytest.approx(partly[0, 0])
    assert np.all(np.linalg.eigvalsh(out - cov) > -1e-18) and np.all(np.linalg.eigvalsh(out - partly) > -1e-18)


@pytest.mark.parametrize(("step_m", "widened_by"), [(0.001, "quantisation"), (0.02, "spatial")])
def test_range_steps_hold_the_fit_intervals_at_the_floor(step_m: float, widened_by: str) -> None:
    """Noise-free ranges rounded to 1 mm or 2 cm: the intervals are at least what that quantisation allows.

    At 1 mm the sandwich is below the floor and is raised to it; at 2 cm the rounding errors form bands
    across the plane (correlated), and the design effect widens the intervals beyond the floor."""
    frame = make_frame(ToFSetup(noise_1m_m=0.0, quantisation_m=step_m), 1)
    frame = dataclasses.replace(frame, measurement=MeasurementModel(kind="tof", range_step_m=step_m))
    res = fit_full_frame(frame)
    f = res.interval_factors
    assert (f.quantisation, f.spatial > 1.0) == ((True, False) if widened_by == "quantisation" else (False, True))
    n = res.plane.normal
    e1, e2 = basis(n)
    pts = frame.xyz[res.inlier_mask].astype(np.float64)
    x = np.stack([pts @ e1, pts @ e2, np.ones(len(pts))])
    floor_cov = res.residual_floor_m ** 2 * np.linalg.inv(x @ x.T)
    e = np.stack([e1, e2], axis=1)
    tangent = e.T @ res.normal_covariance @ e                                # back to (d_e1, d_e2)
    assert np.all(np.linalg.eigvalsh(tangent - floor_cov[:2, :2]) > -0.02 * np.max(np.diag(floor_cov[:2, :2])))
    assert res.offset_variance_m2 >= 0.98 * floor_cov[2, 2]


def test_rounding_allowance_of_the_flatness_gate() -> None:
    """Undithered 1-step rounding bends local planes by up to q/pi; noise of 3 steps leaves nothing."""
    floor = 0.001 / math.sqrt(12.0)                                          # 1 mm steps
    assert rounding_allowance_m(floor, floor) == pytest.approx(0.001 / math.pi)
    s = 0.1 * 0.001                                                          # 0.1 step of noise
    assert rounding_allowance_m(floor, math.hypot(s, floor)) == pytest.approx(
        0.001 / math.pi * math.exp(-2.0 * math.pi ** 2 * 0.01))
    assert rounding_allowance_m(floor, 0.003) < 1e-12 and rounding_allowance_m(0.0, 0.003) == 0.0
