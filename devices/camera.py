"""The 3D camera interface."""

from __future__ import annotations

import dataclasses
from abc import abstractmethod
from collections.abc import Mapping
from typing import Any, Self

from .base import BackendContext, Device
from .errors import CalibrationError
from .measurement import UNKNOWN_MODEL, MeasurementModel
from .types import Frame, Intrinsics


class Camera3D(Device):
    """A 3D (depth) camera.

    Implementations provide :meth:`_capture` and :meth:`_intrinsics`, and state how they
    measure in :meth:`_measurement_model` (a backend that states nothing is ``unknown``);
    the public methods enforce the contract. ``capture`` never returns a frame older than
    its timeout and never returns a frame whose shape disagrees with the intrinsics, and
    every frame it returns carries the camera's :attr:`measurement_model`.

    Attributes:
        measurement_override: A model from the config's ``[camera.model]`` table, which
            replaces the backend's own (None: the backend's).
    """

    measurement_override: MeasurementModel | None = None

    @classmethod
    def from_config(cls, section: Mapping[str, Any] | None, context: BackendContext | None = None) -> Self:
        """As :meth:`Device.from_config`; a ``model`` table becomes :attr:`measurement_override`.

        Raises:
            ConfigError: On a bad key or value, naming it (``camera.model.baseline_m``).
        """
        context = context or BackendContext()
        rest = dict(section or {})
        table = rest.pop("model", None)
        camera = super().from_config(rest, context)
        if table is not None:
            where = f"{context.section or 'camera'}.model"
            camera.measurement_override = MeasurementModel.from_dict(
                table, where=where, source=context.source).with_source("config")
        return camera

    @property
    def measurement_model(self) -> MeasurementModel:
        """How this camera measures: the config's override, else the backend's own statement.

        Backends that read it from the device (the OAK's baseline) need a connection first;
        before it they state what they know without one.
        """
        if self.measurement_override is not None:
            return self.measurement_override
        model = self._measurement_model()
        if not isinstance(model, MeasurementModel):  # a backend bug, reported clearly
            raise CalibrationError(f"{self.backend_name}: _measurement_model returned {type(model).__name__}")
        return model

    def capture(self, timeout: float | None = None) -> Frame:
        """Return the newest complete frame.

        Args:
            timeout: Maximum time to wait, seconds; None uses the device default.

        Raises:
            NotConnectedError: If the camera is not connected.
            DeviceTimeoutError: If no fresh frame arrives within ``timeout``.
            DeviceConnectionError: If the link is lost and cannot be re-established.
            ProtocolError: If the device sends malformed data.
        """
        self._require_connected("capture")
        frame = self._capture(self._resolve_timeout(timeout))
        if not isinstance(frame, Frame):  # a backend bug, reported clearly
            raise CalibrationError(f"{self.backend_name}: capture returned {type(frame).__name__}, not Frame")
        model = self.measurement_model
        if model is not frame.measurement and (self.measurement_override is not None or not frame.measurement.known):
            frame = dataclasses.replace(frame, measurement=model)   # no copy of the arrays
        return frame

    @property
    def intrinsics(self) -> Intrinsics:
        """Intrinsics of the depth stream (OpenCV conventions, pixels).

        Raises:
            NotConnectedError: If the camera is not connected.
        """
        self._require_connected("read intrinsics")
        return self._intrinsics()

    def configured_intrinsics(self) -> Intrinsics | None:
        """The intrinsics the camera's configuration fixes, known without connecting; None if only the device can tell.

        ``cellcal calibrate --check`` checks the plan's pixels against them without touching
        the device (a simulated camera, a recording, a fake device whose image size is a key
        of its config); a camera that returns None is checked once it is connected, before
        the arm moves. Needs no connection.

        Raises:
            CalibrationError: If the backend returns something else than Intrinsics or None.
        """
        intr = self._configured_intrinsics()
        if intr is not None and not isinstance(intr, Intrinsics):  # a backend bug, reported clearly
            raise CalibrationError(f"{self.backend_name}: _configured_intrinsics returned {type(intr).__name__}")
        return intr

    def _configured_intrinsics(self) -> Intrinsics | None:
        """The intrinsics the configuration alone fixes (override in a backend that knows them; default None)."""
        return None

    @abstractmethod
    def _capture(self, timeout: float) -> Frame:
        """Return the newest complete frame within ``timeout`` seconds."""

    @abstractmethod
    def _intrinsics(self) -> Intrinsics:
        """Return the depth stream's intrinsics."""

    def _measurement_model(self) -> MeasurementModel:
        """How the camera measures (override in a backend; the default states nothing)."""
        return UNKNOWN_MODEL
