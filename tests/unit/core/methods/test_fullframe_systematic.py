"""The full-frame fit's intervals carry the camera's systematic allowance; the error budget (issue #39, ADR 0059)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cellcal.core.methods.fullframe import fit_full_frame
from cellcal.core.methods.fullframe.systematic import FIELD_SHAPES
from cellcal.devices.systematic import SystematicError
from tests.support.systematic_frames import stereo_frame, stereo_model, tof_frame, tof_model, truth_plane

PLANE = truth_plane(0.7, 8.0, -5.0)
HEIGHT = PLANE.distance_along_optical_axis_m()


def _covers(ci: tuple[float, float], value: float) -> bool:
    return ci[0] <= value <= ci[1]


def test_a_known_fb_error_within_the_allowance_is_covered_and_without_the_allowance_it_is_not() -> None:
    error = SystematicError("stereo", fb_error=0.012)          # 1.2 sigma of the stereo default (1 %)
    honest = fit_full_frame(stereo_frame(PLANE, error, stereo_model(), np.random.default_rng(3)))
    ideal = fit_full_frame(stereo_frame(PLANE, error, stereo_model(zero=True), np.random.default_rng(3)))
    assert abs(honest.height_m - HEIGHT) > 0.008                # the scale error moved the height by 8 mm
    assert _covers(honest.height_ci_m, HEIGHT)                  # the allowance is what makes it honest ...
    assert not _covers(ideal.height_ci_m, HEIGHT)               # ... without it the interval is confidently wrong
    assert honest.interval_factors.allowance and not ideal.interval_factors.allowance
    note = [n for n in honest.interval_notes if "systematic allowance" in n]
    assert len(note) == 1 and "height x" in note[0] and "independent smooth shapes" in note[0]
    assert not any("systematic allowance" in n for n in ideal.interval_notes)


def test_zero_allowance_leaves_the_covariance_as_it_was() -> None:
    frame = stereo_frame(PLANE, None, stereo_model(zero=True), np.random.default_rng(5))
    res = fit_full_frame(frame)
    b = res.error_budget
    assert b is not None and not b.widened and b.allowance_shifts == {}
    assert b.sigma_before == pytest.approx(b.sigma_after, rel=0, abs=0)
    assert res.height_sigma_m == pytest.approx(b.sigma_before[3], rel=1e-6)   # the same covariance


@pytest.mark.parametrize("kind", ["stereo", "tof"])
def test_budget_says_what_a_1_percent_scale_and_a_1_mm_offset_do(kind: str) -> None:
    rng = np.random.default_rng(7)
    frame = (stereo_frame(PLANE, None, stereo_model(), rng) if kind == "stereo"
             else tof_frame(PLANE, None, tof_model(), rng))
    b = fit_full_frame(frame).error_budget
    assert b is not None and b.kind == kind
    assert b.depth_scale.height_m == pytest.approx(0.01 * HEIGHT, rel=0.02)       # depths 1 % long: height 1 % long
    assert b.depth_offset.height_m == pytest.approx(0.001, rel=0.1)               # 1 mm long: about 1 mm
    assert b.depth_scale.tilt_rad < 1e-6                                          # a scale about the camera: no tilt
    assert b.field_shape in FIELD_SHAPES
    d = b.to_dict()
    assert set(d) >= {"depth_scale_1pct", "depth_offset_1mm", "allowance", "allowance_shifts"}


def test_the_linear_response_is_the_refit_of_a_distorted_frame() -> None:
    """A field ``u`` of 0.5 px tilts the plane as the response says (first order, within 5 %)."""
    model = stereo_model(sigma_px=0.0, bits=8, zero=True)
    base = fit_full_frame(stereo_frame(PLANE, None, model, np.random.default_rng(1)))
    field = SystematicError("stereo", field_order=1, field_coeffs=(0.5, 0.0))   # u, v
    moved = fit_full_frame(stereo_frame(PLANE, field, model, np.random.default_rng(1)))
    resp = fit_full_frame(stereo_frame(PLANE, None, stereo_model(sigma_px=0.0, bits=8), np.random.default_rng(1)))
    b = resp.error_budget
    assert b is not None
    seen = moved.tilt_y_rad - base.tilt_y_rad                     # -0.0289 rad
    assert b.field_shape == "u"                                   # a shape along the plane's tilt moves it most
    k = len(FIELD_SHAPES)                                         # each shape's term is at field / sqrt(K)
    assert b.allowance_shifts["field:u"].tilt_y_rad * math.sqrt(k) == pytest.approx(seen, rel=0.02)
    assert {f"field:{name}" for name in FIELD_SHAPES} <= set(b.allowance_shifts)
    assert math.isfinite(b.sigma_after[1])


def test_tof_offset_within_the_allowance_is_covered() -> None:
    error = SystematicError("tof", offset_m=0.006, scale_error=0.002)
    honest = fit_full_frame(tof_frame(PLANE, error, tof_model(), np.random.default_rng(2)))
    ideal = fit_full_frame(tof_frame(PLANE, error, tof_model(zero=True), np.random.default_rng(2)))
    assert _covers(honest.height_ci_m, HEIGHT) and not _covers(ideal.height_ci_m, HEIGHT)
