"""The stereo fit in disparity space: exact recovery, quantised data, honest intervals, the expected plane."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cellcal.core.geometry.planes import Plane
from cellcal.core.methods.fullframe.disparity import (
    design_effect,
    disparity_from_plane,
    fit_disparity,
    plane_from_disparity,
    rounding_bias_px,
)
from cellcal.core.methods.fullframe.expected import ExpectedPlane
from cellcal.core.methods.fullframe.settings import FullFrameSettings
from cellcal.devices.errors import CalibrationError, CalibrationQualityError
from cellcal.devices.measurement import MeasurementModel

W, H, F, B = 320, 200, 220.0, 0.075     # px, px, px, m: an OAK-like pair at a quarter of 1280x800
XN, YN = np.meshgrid((np.arange(W) - (W - 1) / 2) / F, (np.arange(H) - (H - 1) / 2) / F)


def _plane(tx_deg: float, ty_deg: float, height_m: float) -> Plane:
    """A plane seen by the camera tilted by (tx, ty), at ``height_m`` along the optical axis."""
    tx, ty = math.radians(tx_deg), math.radians(ty_deg)
    n = np.array([math.sin(ty), -math.sin(tx) * math.cos(ty), -math.cos(tx) * math.cos(ty)])
    n /= np.linalg.norm(n)
    return Plane(n, height_m * abs(n[2]))


def _points(plane: Plane, sigma_d: float, bits: int, rng: np.random.Generator) -> np.ndarray:
    """(3, H*W) float32 points of a stereo camera measuring ``plane``: noisy disparity rounded to 2^-bits px."""
    v = disparity_from_plane(plane, F * B)
    d = v[0] * XN + v[1] * YN + v[2] + sigma_d * rng.standard_normal(XN.shape)
    d = np.round(d * 2**bits) / 2**bits
    z = F * B / d
    return np.stack([XN * z, YN * z, z]).reshape(3, -1).astype(np.float32)


def _model(bits: int, sigma_d: float | None) -> MeasurementModel:
    return MeasurementModel(kind="stereo", baseline_m=B, focal_px=F, subpixel_bits=bits, disparity_sigma_px=sigma_d)


def _errors(fit, plane: Plane) -> np.ndarray:
    """Error of the fit in its tangent parameters (rad, rad, m), truth minus estimate."""
    n_true, n_fit = np.asarray(plane.normal), np.asarray(fit.plane.normal)
    return np.array([(n_true - n_fit) @ fit.e1, (n_true - n_fit) @ fit.e2, plane.offset_m - fit.plane.offset_m])


def test_disparity_plane_round_trip_is_exact() -> None:
    plane = _plane(7.0, -4.0, 0.8)
    back = plane_from_disparity(disparity_from_plane(plane, F * B), F * B)
    assert np.allclose(back.normal, plane.normal, atol=1e-12)
    assert back.offset_m == pytest.approx(plane.offset_m, rel=1e-12)
    assert back.offset_m > 0                                    # normal toward the camera


def test_noise_free_subpixel_plane_is_recovered_to_the_rounding() -> None:
    plane = _plane(10.0, 5.0, 0.7)
    p = _points(plane, 0.0, 5, np.random.default_rng(0))
    fit = fit_disparity(p, np.arange(W * H), (H, W), _model(5, 0.0), FullFrameSettings())
    err = _errors(fit, plane)
    assert np.all(np.abs(err[:2]) < 2e-4)                        # rad: 1/32 px steps over 320 px
    assert abs(err[2]) < 2e-4                                    # m
    assert fit.inliers.mean() > 0.999


def test_integer_disparity_near_frontal_plane_does_not_lock_onto_one_level() -> None:
    """Today's range fit sat on one depth level of such data (RMS 0, tilt 0/0); the disparity fit sees the slope."""
    plane = _plane(2.0, -1.5, 0.7)
    p = _points(plane, 0.3, 0, np.random.default_rng(1))
    levels = np.unique(np.round(F * B / p[2]))
    assert levels.size >= 3                                      # the data spans a few disparity levels only
    fit = fit_disparity(p, np.arange(W * H), (H, W), _model(0, 0.3), FullFrameSettings())
    assert fit.inliers.mean() > 0.99                             # every level is on the plane, not one
    assert fit.band_px >= 1.0                                    # never narrower than one step
    err = _errors(fit, plane)
    sd = np.sqrt(np.diag(fit.cov))
    assert np.all(np.abs(err) < 3.0 * sd)
    assert math.degrees(abs(err[0])) < 0.1 and math.degrees(abs(err[1])) < 0.1
    assert fit.residual_rms_px > 0.25                            # about sqrt(0.3² + 1/12): not a lock-on


def test_unstated_disparity_noise_is_estimated_but_never_below_the_rounding() -> None:
    plane = _plane(12.0, 3.0, 0.9)
    p = _points(plane, 0.0, 0, np.random.default_rng(2))
    fit = fit_disparity(p, np.arange(W * H), (H, W), _model(0, None), FullFrameSettings())
    assert fit.sigma_used_px >= 1.0 / math.sqrt(12.0) - 1e-12
    assert any("not stated" in note for note in fit.notes)


def test_residuals_larger_than_the_model_widen_the_intervals_and_say_so() -> None:
    plane = _plane(8.0, 8.0, 0.7)
    rng = np.random.default_rng(3)
    p = _points(plane, 0.4, 3, rng)
    honest = fit_disparity(p, np.arange(W * H), (H, W), _model(3, 0.4), FullFrameSettings())
    optimistic = fit_disparity(p, np.arange(W * H), (H, W), _model(3, 0.1), FullFrameSettings())
    ratio = optimistic.sigma_used_px / _model(3, 0.1).disparity_noise_px
    assert 3.0 < ratio < 5.0                                     # 0.4 px of noise against 0.1 stated
    assert any("intervals widened" in note for note in optimistic.notes)
    assert np.sqrt(optimistic.cov[0, 0]) == pytest.approx(np.sqrt(honest.cov[0, 0]), rel=0.15)


def test_design_effect_is_one_for_independent_residuals_and_counts_pooled_frames() -> None:
    rng = np.random.default_rng(4)
    r = rng.standard_normal(W * H)
    idx = np.arange(W * H)
    assert design_effect(r, idx, (H, W)) == pytest.approx(1.0, abs=0.15)
    twice = design_effect(np.concatenate([r, r]), np.concatenate([idx, idx]), (H, W))
    assert twice == pytest.approx(2.0, rel=0.1)                  # the same residuals twice: no new information


def test_rounding_bias_vanishes_with_dither() -> None:
    assert rounding_bias_px(0.0, 1.0) == pytest.approx(1.0 / math.pi)
    assert rounding_bias_px(0.5, 1.0) == pytest.approx(math.exp(-math.pi**2 / 2.0) / math.pi)
    assert rounding_bias_px(0.5, 1.0) < 0.003


@pytest.mark.statistical
@pytest.mark.parametrize(("bits", "sigma_d"), [(3, 0.1), (0, 0.5)])
def test_interval_coverage_on_dithered_quantised_planes(bits: int, sigma_d: float) -> None:
    rng = np.random.default_rng(5 + bits)
    z_scores = []
    for _ in range(60):
        plane = _plane(rng.uniform(-15, 15), rng.uniform(-15, 15), rng.uniform(0.5, 1.0))
        fit = fit_disparity(_points(plane, sigma_d, bits, rng), np.arange(W * H), (H, W), _model(bits, sigma_d),
                            FullFrameSettings())
        z_scores.append(_errors(fit, plane) / np.sqrt(np.diag(fit.cov)))
    z = np.abs(np.array(z_scores))
    coverage = np.mean(z < 1.96, axis=0)
    assert np.all(coverage >= 0.85)                              # 95 % nominal, 60 runs: binomial band
    assert np.all(np.sqrt(np.mean(z**2, axis=0)) > 0.6)          # and not needlessly wide


def test_expected_plane_picks_the_plane_the_user_means() -> None:
    floor = _plane(0.0, 0.0, 0.9)
    top = _plane(0.0, 0.0, 0.7)                                  # a box top 0.2 m above the floor
    rng = np.random.default_rng(6)
    p_floor, p_top = _points(floor, 0.1, 3, rng), _points(top, 0.1, 3, rng)
    on_top = (np.abs(XN) < 0.3).reshape(-1)                      # the box fills the middle 40 % of the image
    p = np.where(on_top[None, :], p_top, p_floor)
    model, cfg = _model(3, 0.1), FullFrameSettings()
    dominant = fit_disparity(p, np.arange(W * H), (H, W), model, cfg)
    assert dominant.plane.offset_m == pytest.approx(0.9, abs=0.002)
    meant = fit_disparity(p, np.arange(W * H), (H, W), model, cfg,
                          expected=ExpectedPlane(_plane(1.0, 0.0, 0.72), math.radians(5.0), 0.05))
    assert meant.plane.offset_m == pytest.approx(0.7, abs=0.002)
    with pytest.raises(CalibrationQualityError, match="expected_plane") as info:
        fit_disparity(p, np.arange(W * H), (H, W), model, cfg,
                      expected=ExpectedPlane(_plane(0.0, 0.0, 0.4), math.radians(5.0), 0.05))
    assert "dominant plane found" in str(info.value)


def test_a_range_camera_is_refused() -> None:
    p = _points(_plane(0.0, 0.0, 0.7), 0.0, 3, np.random.default_rng(7))
    with pytest.raises(CalibrationError, match="stereo or structured-light"):
        fit_disparity(p, np.arange(W * H), (H, W), MeasurementModel(kind="tof", sigma_at_1m_m=0.003),
                      FullFrameSettings())


def test_disparity_lattice_is_read_off_quantised_depths() -> None:
    from cellcal.core.methods.fullframe.disparity import disparity_lattice

    rng = np.random.default_rng(8)
    z_int = _points(_plane(20.0, 10.0, 0.8), 0.3, 0, rng)[2]
    assert disparity_lattice(z_int) == pytest.approx(F * B, rel=2e-3)             # integer disparity
    z_sub = _points(_plane(20.0, 10.0, 0.8), 0.3, 2, rng)[2]
    assert disparity_lattice(z_sub) == pytest.approx(F * B * 4, rel=2e-3)         # quarter-pixel steps
    z_mm = np.round(z_int.astype(np.float64), 3)                                   # an OAK's millimetre output
    assert disparity_lattice(z_mm) == pytest.approx(F * B, rel=0.01)
    assert disparity_lattice(rng.uniform(0.4, 1.2, 50_000)) is None               # continuous depths: none
    assert disparity_lattice(np.full(100, 0.7)) is None                            # one level tells nothing
