"""Full-frame plane fit: accuracy and robustness on the independent frame generator (tests/support/tof_frames.py)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from tof_frames import RESOLUTIONS, ToFSetup, draw, make_frame, render, scattered_boxes, with_

from cellcal.core.methods.fullframe import (
    FullFrameResult,
    FullFrameSettings,
    check_gates,
    fit_full_frame,
    fit_plane_points,
)
from cellcal.devices.types import Frame


def z_scores(res: FullFrameResult, st: ToFSetup) -> tuple[float, float, float]:
    """(tilt x, tilt y, height) errors against the generator's truth, in the result's sigmas."""
    truth = st.truth()
    return ((res.tilt_x_rad - truth.tilt_about_x_rad()) / res.tilt_x_sigma_rad,
            (res.tilt_y_rad - truth.tilt_about_y_rad()) / res.tilt_y_sigma_rad,
            (res.height_m - st.distance_m) / res.height_sigma_m)


def tilt_error_deg(res: FullFrameResult, st: ToFSetup) -> float:
    """Angle between the fitted and the true normal, degrees."""
    return math.degrees(math.acos(min(1.0, abs(float(res.plane.normal @ st.truth().normal)))))


def replace_points(frame: Frame, xyz: np.ndarray, valid: np.ndarray | None = None) -> Frame:
    xyz = xyz.astype(np.float32)
    dist = np.linalg.norm(xyz, axis=-1).astype(np.float32)
    v = np.isfinite(dist) if valid is None else valid
    return dataclasses.replace(frame, xyz=xyz, distance=dist, valid=v)


# ---------------------------------------------------------------------- accuracy
@pytest.mark.parametrize(("width", "height"), RESOLUTIONS)
def test_noise_free_plane_is_recovered_exactly(width: int, height: int) -> None:
    st = ToFSetup(width=width, height=height, noise_1m_m=0.0, dropout=0.0, mixed=False, tilt_y_deg=3.0)
    res = fit_full_frame(make_frame(st))
    truth = st.truth()
    assert tilt_error_deg(res, st) < 1e-4
    assert math.degrees(res.tilt_y_rad) == pytest.approx(math.degrees(truth.tilt_about_y_rad()), abs=1e-4)
    assert res.height_m == pytest.approx(0.6, abs=1e-6)
    assert res.plane.offset_m > 0 and res.plane.normal[2] < 0      # facing the camera
    assert res.inlier_fraction > 0.999 and res.passed


def test_derived_values_follow_the_plane_methods() -> None:
    res = fit_full_frame(make_frame(ToFSetup(), 3))
    pl = res.plane
    assert res.angle_rad == pytest.approx(pl.angle_to_optical_axis_rad(), abs=1e-12)
    assert res.tilt_x_rad == pytest.approx(pl.tilt_about_x_rad(), abs=1e-12)
    assert res.tilt_y_rad == pytest.approx(pl.tilt_about_y_rad(), abs=1e-12)
    assert res.height_m == pytest.approx(pl.distance_along_optical_axis_m(), abs=1e-12)
    lo, hi = res.tilt_x_ci_rad
    assert lo < res.tilt_x_rad < hi
    assert (hi - lo) / 2 == pytest.approx(1.959964 * res.tilt_x_sigma_rad, rel=1e-5)
    # the normal covariance is tangent to the sphere
    assert abs(res.plane.normal @ res.normal_covariance @ res.plane.normal) < 1e-6 * np.trace(res.normal_covariance)


@pytest.mark.parametrize(("width", "height"), [(224, 172), (101, 77), (640, 480)])
def test_clutter_of_boxes_with_flying_pixels_is_rejected(width: int, height: int) -> None:
    base = ToFSetup(width=width, height=height, flying=0.5)
    st = with_(base, boxes=scattered_boxes(0.4, 7, base))
    rend = render(st)
    frame = draw(rend, np.random.default_rng(1))
    res = fit_full_frame(frame)
    check_gates(res)
    assert tilt_error_deg(res, st) < 0.02
    assert all(abs(z) < 4.0 for z in z_scores(res, st))
    # points measured more than 1 cm off the true plane (boxes, flying pixels) are outliers
    truth = st.truth()
    dist = np.abs(np.nan_to_num(frame.xyz.astype(np.float64) @ truth.normal + truth.offset_m, nan=1.0))
    assert np.count_nonzero(res.inlier_mask & (dist > 0.01)) == 0
    # the plane is mostly inliers
    table = frame.valid & rend.on_base_plane(0.0) & ~rend.mixed
    assert np.count_nonzero(res.inlier_mask & table) / np.count_nonzero(table) > 0.75
    # the noise scale found is the generator's: 3.2 mm at 1 m
    assert res.noise_scale_m == pytest.approx(0.0032, rel=0.05)
    assert res.mixed_margin_px >= 1 and res.n_mixed > 0


@pytest.mark.statistical
@pytest.mark.slow
def test_1280x800_clutter_with_mixed_pixels_stays_within_its_intervals() -> None:
    base = ToFSetup(width=1280, height=800, flying=0.5)
    zs = []
    for layout in range(1):
        st = with_(base, boxes=scattered_boxes(0.4, 20 + layout, base))
        rend = render(st)
        for k in range(8):
            res = fit_full_frame(draw(rend, np.random.default_rng(k)))
            assert res.passed and tilt_error_deg(res, st) < 0.01
            zs.append(z_scores(res, st))
    z = np.array(zs)
    assert np.abs(z).max() < 3.5 and float(np.sqrt(np.mean(z ** 2))) < 1.6


def test_flying_pixels_and_gross_outliers_are_rejected() -> None:
    st = ToFSetup(dropout=0.0)
    frame = make_frame(st, 2)
    rng = np.random.default_rng(5)
    xyz = frame.xyz.astype(np.float64).copy()
    flat = xyz.reshape(-1, 3)
    n = flat.shape[0]
    fly = rng.choice(n, n // 10, replace=False)           # 10 % flying pixels: range off by 2-30 %
    flat[fly] *= rng.choice([-1.0, 1.0], fly.size)[:, None] * rng.uniform(0.02, 0.3, fly.size)[:, None] + 1.0
    gross = rng.choice(n, n // 20, replace=False)        # 5 % anywhere in a 2 m cube
    flat[gross] = rng.uniform([-1.0, -1.0, 0.1], [1.0, 1.0, 2.0], (gross.size, 3))
    res = fit_full_frame(replace_points(frame, xyz))
    clean = fit_full_frame(frame)
    assert 0.8 < res.inlier_fraction < 0.9
    assert all(abs(z) < 4.0 for z in z_scores(res, st)) and tilt_error_deg(res, st) < 0.02
    assert res.tilt_x_sigma_rad < 1.3 * clean.tilt_x_sigma_rad   # isolated outliers do not erode their neighbours


def test_pooled_frames_shrink_the_interval() -> None:
    st = ToFSetup()
    rend = render(st)
    rng = np.random.default_rng(4)
    frames = [draw(rend, rng) for _ in range(4)]
    one = fit_full_frame(frames[0])
    four = fit_full_frame(frames)
    assert four.n_frames == 4 and four.n_points == sum(int(f.valid.sum()) for f in frames)
    assert 1.7 < one.tilt_x_sigma_rad / four.tilt_x_sigma_rad < 2.3
    assert all(abs(z) < 4.0 for z in z_scores(four, st))
    assert four.inlier_mask.shape == frames[0].shape


def test_unweighted_and_given_sigma_agree_with_the_truth() -> None:
    st = ToFSetup(mixed=False)
    rend = render(st)
    frame = draw(rend, np.random.default_rng(6))
    pts = frame.xyz[frame.valid].astype(np.float64)
    unweighted = fit_plane_points(pts, settings=FullFrameSettings(weighted=False))
    sigma = 0.0032 * rend.true_range_m ** 1.5 / np.sqrt(rend.cos_incidence)   # the generator's own sigmas
    given = fit_plane_points(pts, sigma_m=sigma[frame.valid])
    for r in (unweighted, given):
        assert all(abs(z) < 4.0 for z in z_scores(r, st))
        assert math.isnan(r.coverage) and "coverage" not in r.gates and "flatness" not in r.gates
        assert r.inlier_mask.shape == (pts.shape[0],)
    assert 0.9 < given.noise_scale_m < 1.1           # sigma given exactly: unit scale
    assert 0.9 < given.noise_ratio < 1.1 and 0.9 < unweighted.noise_ratio < 1.1


def test_a_noisier_camera_with_a_different_noise_law_keeps_honest_intervals() -> None:
    """Noise growing as range² (the fit's model says range^1.5) and 1 mm steps: the sandwich keeps the sigmas right."""
    st = ToFSetup(noise_1m_m=0.006, noise_exponent=2.0, quantisation_m=0.001, distance_m=0.9, tilt_x_deg=25.0)
    rend = render(st)
    z = np.array([z_scores(fit_full_frame(draw(rend, np.random.default_rng(k))), st) for k in range(60)])
    assert np.all(np.abs(z.mean(axis=0)) < 0.45) and np.all((z.std(axis=0) > 0.7) & (z.std(axis=0) < 1.3))


# ---------------------------------------------------------------------- multipath
@pytest.mark.parametrize(("width", "height"), [(224, 172), (640, 480)])
def test_a_border_bias_is_estimated_and_its_effect_reported(width: int, height: int) -> None:
    st = ToFSetup(width=width, height=height, border_bias_m=0.002)
    res = fit_full_frame(make_frame(st, 3))
    est = res.multipath
    assert est.value == pytest.approx(0.002, abs=max(4 * est.sigma, 0.0002))
    assert est.interval[0] < 0.002 * 0.97 < est.interval[1] + 0.0001
    # the intervals do not cover the bias: the height is off by many sigmas, and the shift says by how much
    err = res.height_m - st.distance_m
    assert abs(err) > 10 * res.height_sigma_m
    assert abs(err + res.multipath_shift["height_m"]) < 0.1 * abs(err)
    tx_err = res.tilt_x_rad - st.truth().tilt_about_x_rad()
    assert abs(tx_err + res.multipath_shift["tilt_x_rad"]) < 0.15 * abs(tx_err)


def test_no_border_bias_no_multipath_estimate() -> None:
    st = ToFSetup()
    rend = render(st)
    z = [fit_full_frame(draw(rend, np.random.default_rng(k))).multipath for k in range(20)]
    zz = np.array([e.value / e.sigma for e in z])
    assert np.abs(zz).max() < 4.0 and abs(float(zz.mean())) < 1.0
    assert all(abs(e.value) < 0.0003 for e in z)

