"""Backend registry: entry points, duplicates, config validation by the backend."""

from __future__ import annotations

import importlib.metadata as md
from dataclasses import dataclass, field

import numpy as np
import pytest

from cellcal.devices import BackendContext, Camera3D, ConfigError, DeviceInfo, Frame, Intrinsics, RegistryError
from cellcal.devices.registry import Registry


class ToyCamera(Camera3D):
    backend_name = "toy"

    @dataclass(frozen=True)
    class Config:
        exposure_s: float = field(default=0.001, metadata={"gt": 0})
        name: str = "toy"
        size_px: tuple[int, int] = (4, 3)

    def __init__(self, config: ToyCamera.Config, context: BackendContext | None = None):
        super().__init__()
        self.config = config

    def _connect(self, timeout: float) -> None: ...
    def _close(self) -> None: ...
    def _info(self) -> DeviceInfo:
        return DeviceInfo("toy", "test", "toy")

    def _intrinsics(self) -> Intrinsics:
        w, h = self.config.size_px
        return Intrinsics(w, h, 2.0, 2.0, (w - 1) / 2, (h - 1) / 2)

    def _capture(self, timeout: float) -> Frame:
        i = self._intrinsics()
        z = np.ones(i.shape, np.float32)
        return Frame(z, np.zeros((*i.shape, 3), np.float32), z, z > 0, i, 0.0, 0)


def test_builtin_backends_come_from_entry_points() -> None:
    reg = Registry()
    cams, arms = reg.names("camera"), reg.names("arm")
    assert {"sim", "o3r", "oak"} <= set(cams)
    assert {"sim", "xarm", "ur"} <= set(arms)
    builtin = {("camera", n) for n in ("sim", "o3r", "oak")} | {("arm", n) for n in ("sim", "xarm", "ur")}
    origins = {e.origin.split()[0] for e in reg.entries() if (e.kind, e.name) in builtin}
    assert origins == {"cellcal"}  # other installed distributions (vendor backends) may add their own


def test_runtime_registration_and_duplicates() -> None:
    reg = Registry()
    reg.register("camera", "toy", ToyCamera)
    assert reg.get("camera", "toy") is ToyCamera
    with pytest.raises(RegistryError, match="duplicate camera backend 'toy'"):
        reg.register("camera", "toy", ToyCamera)
    with pytest.raises(RegistryError, match="duplicate camera backend 'sim'"):
        reg.register("camera", "sim", ToyCamera)
    with pytest.raises(RegistryError, match="must subclass RobotArm"):
        reg.register("arm", "toy", ToyCamera)


def test_duplicate_entry_points_from_two_distributions(monkeypatch: pytest.MonkeyPatch) -> None:
    eps = [
        md.EntryPoint("acme", "acme_a:Cam", "cellcal.cameras"),
        md.EntryPoint("acme", "acme_b:Cam", "cellcal.cameras"),
    ]
    monkeypatch.setattr(md, "entry_points", lambda group: eps if group == "cellcal.cameras" else [])
    with pytest.raises(RegistryError, match=r"duplicate camera backend .acme.*acme_a:Cam.*acme_b:Cam"):
        Registry().entries()


def test_unknown_backend_names_the_choices() -> None:
    reg = Registry()
    with pytest.raises(ConfigError, match=r"cell.toml: key 'camera.backend': unknown camera backend 'nope'; "
                       r"registered: .*sim"):
        reg.create("camera", {"backend": "nope"}, BackendContext(source="cell.toml", section="camera"))


@pytest.mark.parametrize(
    ("section", "message"),
    [
        ({"exposure": 1.0},
         r"key 'camera.exposure': unknown key; did you mean 'exposure_s'\? "
         r"\(expected one of: exposure_s, name, size_px\)"),
        ({"exposure_s": "fast"}, r"key 'camera.exposure_s': expected a number, got str 'fast'"),
        ({"exposure_s": -1.0}, r"key 'camera.exposure_s': must be > 0, got -1.0"),
        ({"exposure_s": True}, r"key 'camera.exposure_s': expected a number, got bool"),
        ({"size_px": [4]}, r"key 'camera.size_px': expected a list of 2 integers, got 1 items"),
        ({"size_px": [4, 2.5]}, r"key 'camera.size_px\[1\]': expected an integer, got float 2.5"),
    ],
)
def test_backend_validates_its_own_section(section: dict[str, object], message: str) -> None:
    reg = Registry()
    reg.register("camera", "toy", ToyCamera)
    with pytest.raises(ConfigError, match=message):
        reg.create("camera", {"backend": "toy", **section}, BackendContext(source="cell.toml", section="camera"))


def test_created_backend_is_unconnected_and_typed() -> None:
    reg = Registry()
    reg.register("camera", "toy", ToyCamera)
    cam = reg.create_camera({"backend": "toy", "exposure_s": 0.01}, BackendContext(section="camera"))
    assert isinstance(cam, ToyCamera) and cam.config.exposure_s == 0.01 and not cam.connected
