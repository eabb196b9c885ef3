"""The ``acme-z1-emulated`` backend: the real ``acme-z1`` backend against a fake Z1 started in-process.

``cellcal calibrate`` then runs with no second process and no hardware. In a simulated
cell (``[arm] backend = "sim"``) the fake device asks cellcal's public scene view
(:mod:`cellcal.devices.scene_view`) what the camera sees at every frame, so the camera
follows the simulated arm; elsewhere it sees the fixed plane of its settings.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import ClassVar

from cellcal.devices import BackendContext, Camera3D, DeviceInfo, Frame, Intrinsics
from cellcal.devices.measurement import MeasurementModel
from cellcal.devices.scene_view import scene_view

from .camera import Z1_MODEL, AcmeZ1Camera, AcmeZ1Config
from .fake_device import FakeZ1, FakeZ1Settings


@dataclass(frozen=True)
class AcmeZ1EmulatedConfig(FakeZ1Settings):
    """``[camera]`` table for ``backend = "acme-z1-emulated"``: the fake device's settings, and these."""

    follow_arm: bool = field(default=True, metadata={
        "doc": "in a simulated cell, render what the camera sees from the arm's pose (false: the fixed plane)"})
    timeout_s: float = field(default=2.0, metadata={"gt": 0.0, "le": 60.0, "doc": "default I/O timeout, s"})


class AcmeZ1EmulatedCamera(Camera3D):
    """An ``acme-z1`` camera connected to a :class:`FakeZ1` it starts on ``127.0.0.1``, port 0.

    Args:
        config: The validated ``[camera]`` table.
        context: The configuration document's context (where the scene view is published).
    """

    backend_name: ClassVar[str] = "acme-z1-emulated"
    Config: ClassVar[type[AcmeZ1EmulatedConfig]] = AcmeZ1EmulatedConfig

    def __init__(self, config: AcmeZ1EmulatedConfig, context: BackendContext | None = None):
        super().__init__()
        self.config = config
        self.context = context or BackendContext()
        self.default_timeout_s = config.timeout_s
        self._device: FakeZ1 | None = None
        self._camera: AcmeZ1Camera | None = None

    def _connect(self, timeout: float) -> None:
        # Look the scene view up now, not in __init__: the simulated arm publishes it when it is built.
        view = scene_view(self.context) if self.config.follow_arm else None
        settings = FakeZ1Settings(**{f.name: getattr(self.config, f.name) for f in dataclasses.fields(FakeZ1Settings)})
        self._device = FakeZ1(settings, scene=None if view is None else view.view_from_camera).start()
        self._camera = AcmeZ1Camera(AcmeZ1Config(host="127.0.0.1", port=self._device.port,
                                                 timeout_s=self.config.timeout_s))
        self._camera.connect(timeout)

    def _close(self) -> None:
        camera, device = self._camera, self._device
        self._camera = self._device = None
        if camera is not None:
            camera.close()
        if device is not None:
            device.stop()

    def _info(self) -> DeviceInfo:
        assert self._camera is not None
        info = self._camera.info()
        return dataclasses.replace(info, backend=self.backend_name, extra={**info.extra, "emulated": True})

    def _intrinsics(self) -> Intrinsics:
        assert self._camera is not None
        return self._camera.intrinsics

    def _configured_intrinsics(self) -> Intrinsics:
        # the fake device's image is fixed by this config: `cellcal calibrate --check` checks the plan against it
        fx, fy, cx, cy = self.config.intrinsics()
        return Intrinsics(width=self.config.width, height=self.config.height, fx=fx, fy=fy, cx=cx, cy=cy)

    def _measurement_model(self) -> MeasurementModel:
        return Z1_MODEL                          # what the real Z1 backend states; its frames carry it

    def _capture(self, timeout: float) -> Frame:
        assert self._camera is not None
        return self._camera.capture(timeout)
