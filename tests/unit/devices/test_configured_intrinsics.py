"""``Camera3D.configured_intrinsics()``: what a camera's configuration fixes, before any connection."""

from __future__ import annotations

import tomllib
from importlib import resources
from typing import Any

import pytest

from cellcal.devices import BackendContext, Camera3D, Frame, Intrinsics, default_registry
from cellcal.devices.errors import CalibrationError
from cellcal.devices.forwarding import ForwardingCamera

SIM_DOC: dict[str, Any] = tomllib.loads(resources.files("cellcal.configs").joinpath("sim.toml").read_text())


class Bare(Camera3D):
    backend_name = "bare"
    answer: Any = None

    def _connect(self, timeout: float) -> None: ...
    def _close(self) -> None: ...
    def _info(self) -> Any: ...
    def _intrinsics(self) -> Intrinsics: raise AssertionError("never asked")
    def _capture(self, timeout: float) -> Frame: raise AssertionError("never asked")

    def _configured_intrinsics(self) -> Any:
        return self.answer if self.answer is not None else super()._configured_intrinsics()


def test_a_camera_that_needs_its_device_says_none_and_a_wrong_type_is_named() -> None:
    assert Bare().configured_intrinsics() is None
    bad = Bare()
    bad.answer = (64, 48)
    with pytest.raises(CalibrationError, match="bare: _configured_intrinsics returned tuple"):
        bad.configured_intrinsics()


@pytest.mark.parametrize("backend", ["sim", "o3r-emulated"])
def test_simulated_cameras_state_the_image_of_their_config_unconnected(backend: str) -> None:
    doc = {**SIM_DOC, "camera": {"backend": backend, "width": 64, "height": 48}}
    camera = default_registry().create_camera(doc["camera"], BackendContext(section="camera", document=doc,
                                                                            shared={}, seed=3))
    intr = camera.configured_intrinsics()
    assert not camera.connected and intr is not None
    assert (intr.width, intr.height, intr.cx, intr.cy) == (64, 48, 31.5, 23.5)
    assert ForwardingCamera(camera).configured_intrinsics() == intr    # a wrapper (a recorder) passes it on
