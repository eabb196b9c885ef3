"""The systematic-error model: what a camera adds, its inverse, its derivatives and its JSON (issue #39)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from cellcal.devices.errors import ConfigError
from cellcal.devices.measurement import MeasurementModel
from cellcal.devices.systematic import SystematicError, field_basis, field_terms, normalised_pixels

U, V = normalised_pixels(64, 48, 31.5, 23.5)


def _tof() -> SystematicError:
    # a ToF camera 0.3 % long, 4 mm offset, 1.5 mm wiggle at 0.625 m, a 2 mm bowl at the corner
    return SystematicError("tof", scale_error=0.003, offset_m=0.004, wiggle_cos_m=0.0012, wiggle_sin_m=-0.0009,
                           wiggle_period_m=0.625, field_order=2, field_coeffs=(0.0, 0.0, 0.001, 0.0, 0.001))


def test_the_field_has_every_monomial_up_to_its_order_and_no_constant() -> None:
    assert field_terms(0) == []
    assert field_terms(2) == [(1, 0), (0, 1), (2, 0), (1, 1), (0, 2)]
    assert len(field_terms(4)) == 14  # 2 + 3 + 4 + 5
    basis = field_basis([0.5], [-2.0], 2)
    np.testing.assert_array_equal(basis, [[0.5, -2.0, 0.25, -1.0, 4.0]])


def test_normalised_pixels_put_the_principal_point_at_zero_and_the_corners_near_one() -> None:
    assert U[23, 31] == pytest.approx(-0.5 / 32) and V[23, 31] == pytest.approx(-0.5 / 24)
    assert U[0, 0] == pytest.approx(-31.5 / 32) and V[-1, -1] == pytest.approx(23.5 / 24)


def test_a_stereo_error_scales_offsets_and_bends_the_disparity_as_stated() -> None:
    err = SystematicError("stereo", fb_error=0.01, disparity_offset_px=0.2, field_order=2,
                          field_coeffs=(0.0, 0.0, 0.3, 0.0, 0.2))
    d_true = np.full(U.shape, 60.0)
    d_meas = err.distort(d_true, U, V)
    # at u = v = 0 the field vanishes: 1.01 * 60 + 0.2 px
    centre = err.distort(np.array([60.0]), np.array([0.0]), np.array([0.0]))
    assert centre[0] == pytest.approx(60.8, abs=1e-12)
    # at a corner the bowl adds 0.3 u^2 + 0.2 v^2
    assert d_meas[0, 0] - 60.8 == pytest.approx(0.3 * U[0, 0] ** 2 + 0.2 * V[0, 0] ** 2, abs=1e-12)
    np.testing.assert_allclose(err.correct(d_meas, U, V), d_true, rtol=0, atol=1e-12)


def test_a_tof_error_with_wiggle_is_inverted_to_a_nanometre() -> None:
    err = _tof()
    r_true = np.linspace(0.3, 2.0, U.size).reshape(U.shape)
    r_meas = err.distort(r_true, U, V)
    assert np.ptp(r_meas - r_true) > 0.005  # the error is there, several mm across the range...
    np.testing.assert_allclose(err.correct(r_meas, U, V), r_true, rtol=0, atol=1e-9)  # ...and removed


def test_the_jacobian_is_the_derivative_of_distort_in_every_parameter() -> None:
    err = _tof()
    r = np.linspace(0.4, 1.2, 50)
    u, v = U.ravel()[:50], V.ravel()[:50]
    jac = err.jacobian(r, u, v)
    x0 = err.vector
    for k in range(x0.size):
        step = np.zeros_like(x0)
        step[k] = 1e-6
        plus = SystematicError.from_vector("tof", x0 + step, field_order=2, wiggle_period_m=0.625)
        minus = SystematicError.from_vector("tof", x0 - step, field_order=2, wiggle_period_m=0.625)
        numeric = (plus.distort(r, u, v) - minus.distort(r, u, v)) / 2e-6
        np.testing.assert_allclose(jac[:, k], numeric, rtol=0, atol=1e-7, err_msg=err.names[k])


def test_json_round_trip_keeps_the_terms_and_the_covariance(tmp_path) -> None:
    cov = np.diag(np.arange(1, 10, dtype=float)) * 1e-8
    err = SystematicError.from_vector("tof", _tof().vector, field_order=2, wiggle_period_m=0.625, covariance=cov)
    path = tmp_path / "sys.json"
    path.write_text(json.dumps(err.to_dict()))
    back = SystematicError.from_dict(json.loads(path.read_text()))
    assert back == err
    np.testing.assert_array_equal(np.asarray(back.covariance), cov)
    np.testing.assert_allclose(back.leftover_sigma(["offset_m", "fb_error"]), [math.sqrt(2e-8), 0.0])


@pytest.mark.parametrize(("data", "key", "why"), [
    ({"kind": "lidar"}, "systematic.kind", "must be 'stereo' or 'tof'"),
    ({"kind": "stereo", "fb_error": 0.7}, "systematic.fb_error", "below 0.5"),
    ({"kind": "stereo", "fb_error": True}, "systematic.fb_error", "must be a number"),
    ({"kind": "stereo", "field_order": 2, "field_coeffs": [1.0]}, "systematic.field_coeffs", "needs 5"),
    ({"kind": "stereo", "field_order": 9}, "field_order", "must be 0..4"),
    ({"kind": "tof", "covariance": [[1.0]]}, "systematic.covariance", "4x4"),
    ({"kind": "tof", "offset": 0.1}, "systematic.offset", "unknown key"),
    ({"fb_error": 0.1}, "systematic.kind", "missing"),
])
def test_a_bad_systematic_table_is_one_line_naming_the_key(data: dict, key: str, why: str) -> None:
    with pytest.raises(ConfigError) as err:
        SystematicError.from_dict(data)
    assert key in str(err.value) and why in str(err.value) and "\n" not in str(err.value)


def test_the_allowance_is_the_kinds_default_unless_stated() -> None:
    stereo = MeasurementModel(kind="stereo", baseline_m=0.075, focal_px=440.0)
    assert stereo.allowance == (0.01, 0.1, 0.5)
    ideal = MeasurementModel(kind="tof", sigma_at_1m_m=0.003, scale_allowance=0.0, offset_allowance=0.0,
                             field_allowance=0.0)
    assert ideal.allowance == (0.0, 0.0, 0.0)
    assert MeasurementModel().allowance == (0.0, 0.0, 0.0)
    back = MeasurementModel.from_dict(MeasurementModel(kind="tof", offset_allowance=0.001).to_dict())
    assert back.allowance == (0.002, 0.001, 0.002)
