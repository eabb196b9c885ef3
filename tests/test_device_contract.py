"""Every built-in backend that can run without hardware honours the device contract."""

from __future__ import annotations

import tomllib
from importlib import resources
from typing import Any

import pytest
from device_contract import check_arm, check_camera

from cellcal.devices import BackendContext, default_registry

SIM_DOC: dict[str, Any] = tomllib.loads(resources.files("cellcal.configs").joinpath("sim.toml").read_text())


def context(section: str) -> BackendContext:
    return BackendContext(source="<sim.toml>", section=section, document=SIM_DOC, shared={}, seed=3)


@pytest.mark.parametrize("name", ["sim", "o3r-emulated"])
def test_camera_contract(name: str) -> None:
    camera = default_registry().create_camera({**SIM_DOC["camera"], "backend": name}, context("camera"))
    check_camera(camera)


@pytest.mark.parametrize("name", ["sim", "xarm-emulated"])
def test_arm_contract(name: str) -> None:
    arm = default_registry().create_arm({**SIM_DOC["arm"], "backend": name}, context("arm"))
    check_arm(arm)
