"""The full-frame result keeps its noise and the camera's systematic allowance apart (issue #39, ADR 0059 "Amended")."""

from __future__ import annotations

import numpy as np
import pytest

from cellcal.core.methods.fullframe import fit_full_frame
from tests.support.systematic_frames import stereo_frame, stereo_model, tof_frame, tof_model, truth_plane

PLANE = truth_plane(0.7, 8.0, -5.0)


def _rebuilt(res):  # type: ignore[no-untyped-def]
    cov_n = np.array(res.noise_normal_covariance, dtype=np.float64)
    var_d = res.noise_offset_sigma_m**2
    cross = np.array(res.noise_normal_offset_covariance, dtype=np.float64)
    for n, c in res.systematic_shifts.values():
        cov_n = cov_n + np.outer(n, n)
        var_d += c * c
        cross = cross + np.asarray(n) * c
    return cov_n, var_d, cross


@pytest.mark.parametrize("kind", ["stereo", "tof"])
def test_noise_plus_the_shifts_is_the_total(kind: str) -> None:
    rng = np.random.default_rng(11)
    frame = (stereo_frame(PLANE, None, stereo_model(), rng) if kind == "stereo"
             else tof_frame(PLANE, None, tof_model(), rng))
    res = fit_full_frame(frame)
    assert res.systematic_shifts and {"scale", "offset"} <= set(res.systematic_shifts)
    cov_n, var_d, cross = _rebuilt(res)
    scale = float(np.abs(res.normal_covariance).max())
    assert np.abs(cov_n - res.normal_covariance).max() <= 1e-12 * scale
    assert var_d == pytest.approx(res.offset_variance_m2, rel=1e-12)
    big = float(np.abs(res.normal_offset_covariance).max())
    assert np.abs(cross - res.normal_offset_covariance).max() <= 1e-12 * big
    assert res.noise_offset_sigma_m < res.offset_sigma_m          # the allowance is most of a plane's offset error
    d = res.to_dict()
    assert set(d["systematic_shifts"]) == set(res.systematic_shifts)
    assert d["noise_offset_sigma_m"] == pytest.approx(res.noise_offset_sigma_m)
    assert np.array(d["noise_normal_covariance"]).shape == (3, 3) and len(d["noise_normal_offset_covariance"]) == 3
    assert set(next(iter(d["systematic_shifts"].values()))) == {"normal", "offset_m"}


def test_zero_allowance_noise_is_the_total_and_no_shifts() -> None:
    res = fit_full_frame(stereo_frame(PLANE, None, stereo_model(zero=True), np.random.default_rng(5)))
    assert res.systematic_shifts == {}
    assert np.array_equal(res.noise_normal_covariance, res.normal_covariance)
    assert res.noise_offset_sigma_m == res.offset_sigma_m
    assert np.array_equal(res.noise_normal_offset_covariance, res.normal_offset_covariance)
    assert res.to_dict()["systematic_shifts"] == {}
