"""The arm's stated model: each backend's figures and ``[arm.model]`` over them (issue #39, ADR 0055)."""

from __future__ import annotations

import pytest

from cellcal.devices.arm_model import UNSTATED_ARM_MODEL, ArmModel
from cellcal.devices.base import BackendContext
from cellcal.devices.errors import ConfigError
from cellcal.devices.registry import default_registry
from cellcal.drivers.ur.arm import UR_MODEL
from cellcal.drivers.xarm.arm import XARM_MODEL

IDEAL = {"sim": {"arm_errors": {"enabled": False}}}


def sim_arm(section: dict[str, object], document: dict[str, object] | None = None):
    ctx = BackendContext(source="cell.toml", section="arm", document=document or IDEAL)
    return default_registry().create_arm({"backend": "sim", **section}, ctx)


def test_the_ideal_sim_arm_states_its_repeatability_and_no_error() -> None:
    assert sim_arm({}).arm_model() == ArmModel(1e-4, 0.0, 0.0, "sim")


def test_arm_model_overrides_the_backends_figures_key_by_key() -> None:
    model = sim_arm({"model": {"accuracy_m": 0.002, "accuracy_rad": 0.004}}).arm_model()
    assert model == ArmModel(1e-4, 0.002, 0.004, "config")


@pytest.mark.parametrize(("table", "key"), [({"accuracy_mm": 1.0}, "accuracy_mm"), ({"accuracy_m": -1.0}, "accuracy_m"),
                                            ({"accuracy_rad": "big"}, "accuracy_rad")])
def test_a_bad_arm_model_key_is_one_config_error_naming_it(table: dict[str, object], key: str) -> None:
    with pytest.raises(ConfigError) as caught:
        sim_arm({"model": table})
    assert f"arm.model.{key}" in str(caught.value) or key in str(caught.value)
    assert "\n" not in str(caught.value)


def test_arm_model_must_be_a_table() -> None:
    with pytest.raises(ConfigError, match=r"arm\.model"):
        sim_arm({"model": 3})


def test_vendor_figures() -> None:
    assert XARM_MODEL.repeatability_m == 1e-4 and XARM_MODEL.source == "backend"
    assert UR_MODEL.repeatability_m == 5e-5 and 1e-3 <= UR_MODEL.accuracy_m <= 2e-3
    assert UNSTATED_ARM_MODEL.accuracy_m == 1e-3


def test_the_safety_wrapper_forwards_the_model() -> None:
    from cellcal.devices.safety import SafeArm, SafetyLimits

    inner = sim_arm({"model": {"accuracy_m": 0.003}})
    limits = SafetyLimits((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0), 0.5, 2.0)
    assert SafeArm(inner, limits).arm_model().accuracy_m == 0.003
