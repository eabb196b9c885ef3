"""Both O3R backends state the head's ToF model (data sheet at 1 m, a real frame nearer), and the same one."""

from __future__ import annotations

import math

import pytest

from cellcal.devices.registry import default_registry
from cellcal.drivers.o3r.camera import O3R_SIGMA_AT_1M_M, O3RCamera
from cellcal.drivers.o3r_ifm3d.camera import O3RIfm3dCamera


def test_the_o3r_states_tof_with_the_data_sheet_noise() -> None:
    model = O3RCamera.from_config({"host": "127.0.0.1"}).measurement_model   # no connection needed
    assert model.kind == "tof" and model.source == "backend"
    # < 7 mm repeatability below 1 m, read as 2 sigma
    assert model.sigma_at_1m_m == O3R_SIGMA_AT_1M_M == pytest.approx(0.007 / 2)
    assert float(model.range_sigma_m(1.0)) == pytest.approx(0.0035)
    # the real frame's 3.0 mm on a face 0.28 m away at 50 deg (tests/integration/real_sensors/test_real_o3r.py)
    face = float(model.range_sigma_m(0.28, cos_incidence=math.cos(math.radians(50.0))))
    assert face == pytest.approx(0.003, abs=2e-4)
    assert float(model.range_sigma_m(1.0, cos_incidence=0.5)) == pytest.approx(0.0035 * math.sqrt(2.0))


def test_both_o3r_backends_state_the_same_model() -> None:
    own = O3RCamera.from_config({"host": "127.0.0.1"}).measurement_model
    ifm = O3RIfm3dCamera.from_config({"host": "127.0.0.1"}).measurement_model   # ifm3dpy is imported on connect only
    assert own == ifm and own.to_dict() == ifm.to_dict()
    registry = default_registry()
    assert registry.create_camera({"backend": "o3r", "host": "127.0.0.1"}).measurement_model == own
