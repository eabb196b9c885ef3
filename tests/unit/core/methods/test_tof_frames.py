"""The independent ToF frame generator the full-frame tests run on (tests/support/tof_frames.py) is right."""

from __future__ import annotations

import math

import numpy as np
import pytest
from tof_frames import ToFBox, ToFSetup, draw, make_frame, render, scattered_boxes, with_


def test_noise_free_points_lie_on_the_plane_and_match_the_intrinsics() -> None:
    st = ToFSetup(noise_1m_m=0.0, dropout=0.0, mixed=False)
    f = make_frame(st)
    pl = st.truth()
    pts = f.xyz[f.valid].astype(np.float64)
    assert np.abs(pts @ pl.normal + pl.offset_m).max() < 2e-7          # float32 coordinates
    assert pl.distance_along_optical_axis_m() == pytest.approx(0.6)
    assert math.degrees(pl.tilt_about_x_rad()) == pytest.approx(10.0)
    intr = f.intrinsics                                                  # pixel (u, v) projects back to itself
    v, u = np.nonzero(f.valid)
    p = f.xyz[v, u].astype(np.float64)
    assert np.allclose(p[:, 0] / p[:, 2] * intr.fx + intr.cx, u, atol=1e-3)
    assert np.allclose(p[:, 1] / p[:, 2] * intr.fy + intr.cy, v, atol=1e-3)
    assert np.allclose(np.linalg.norm(p, axis=1), f.distance[f.valid], rtol=1e-6)


def test_range_noise_follows_its_model_along_the_ray() -> None:
    st = ToFSetup(dropout=0.0, mixed=False)
    rend = render(st)
    rng = np.random.default_rng(1)
    err = np.stack([draw(rend, rng).distance - rend.true_range_m for _ in range(20)])
    sigma = 0.0032 * rend.true_range_m ** 1.5 / np.sqrt(rend.cos_incidence)
    zz = (err / sigma)[:, rend.valid]
    assert abs(float(zz.mean())) < 0.01 and float(zz.std()) == pytest.approx(1.0, abs=0.01)
    f = draw(rend, rng)                                                  # the noise is along the ray
    ray = rend.rays[f.valid]
    assert np.allclose(np.cross(f.xyz[f.valid], ray), 0.0, atol=2e-6)


def test_boxes_stand_on_the_plane_and_mix_at_their_edges() -> None:
    box = ToFBox((0.0, 0.0), (0.1, 0.1, 0.05))
    st = ToFSetup(noise_1m_m=0.0, dropout=0.0, boxes=(box,))
    rend = render(st)
    pl = st.truth()
    top = (rend.label == 10) & ~rend.mixed & rend.valid
    pts = rend.rays[top] * rend.range_m[top][:, None]
    heights = pts @ pl.normal + pl.offset_m
    assert heights.max() == pytest.approx(0.05, abs=1e-6)             # the box top, 5 cm above the plane
    assert rend.mixed.any() and not rend.mixed[rend.on_base_plane(1e-9)].any()
    # mixed pixels lie between the surfaces they see; the rest is exact
    between = rend.mixed & (rend.range_m >= rend.near_m - 1e-9) & (rend.range_m <= rend.far_m + 1e-9)
    assert np.count_nonzero(between) == np.count_nonzero(rend.mixed)
    exact = rend.valid & ~rend.mixed
    assert np.allclose(rend.range_m[exact], rend.true_range_m[exact])


def test_mixing_band_scales_with_the_resolution() -> None:
    box = ToFBox((0.0, 0.0), (0.1, 0.1, 0.05))
    widths = []
    for w, h in ((224, 172), (1280, 800)):
        rend = render(ToFSetup(width=w, height=h, noise_1m_m=0.0, dropout=0.0, boxes=(box,)))
        widths.append(np.count_nonzero(rend.mixed) / math.sqrt(np.count_nonzero(rend.label == 10)))
    assert widths[1] > 2 * widths[0]             # the band's width in pixels grows with the focal length


def test_border_bias_grows_to_its_value_at_the_corners() -> None:
    st = ToFSetup(noise_1m_m=0.0, dropout=0.0, mixed=False, border_bias_m=0.002)
    rend = render(st)
    bias = rend.range_m - rend.true_range_m
    h, w = bias.shape
    assert abs(bias[h // 2, w // 2]) < 1e-5 and bias[0, 0] == pytest.approx(0.002, rel=1e-6)


@pytest.mark.parametrize("fraction", [0.2, 0.4])
def test_scattered_boxes_hide_about_the_fraction_asked(fraction: float) -> None:
    st = ToFSetup()
    boxes = scattered_boxes(fraction, 3, st)
    rend = render(with_(st, boxes=boxes, mixed=False))
    hidden = 1.0 - np.count_nonzero(rend.valid & (rend.label < 10)) / np.count_nonzero(render(st).valid)
    assert fraction - 0.06 < hidden < fraction + 0.06


def test_two_half_planes_meet_at_the_split() -> None:
    for surface, param in (("roof", 20.0), ("crease", 1.0), ("step", 0.05)):
        rend = render(with_(ToFSetup(noise_1m_m=0.0, dropout=0.0, mixed=False), surface=surface,
                            surface_param=param))
        share = np.count_nonzero(rend.label == 1) / np.count_nonzero(rend.valid)
        assert 0.4 < share < 0.6, (surface, share)
