"""The 3D camera interface."""

from __future__ import annotations

from abc import abstractmethod

from .base import Device
from .errors import CalibrationError
from .types import Frame, Intrinsics


class Camera3D(Device):
    """A 3D (depth) camera.

    Implementations provide :meth:`_capture` and :meth:`_intrinsics`; the public
    methods enforce the contract. ``capture`` never returns a frame older than its
    timeout and never returns a frame whose shape disagrees with the intrinsics.
    """

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
        return frame

    @property
    def intrinsics(self) -> Intrinsics:
        """Intrinsics of the depth stream (OpenCV conventions, pixels).

        Raises:
            NotConnectedError: If the camera is not connected.
        """
        self._require_connected("read intrinsics")
        return self._intrinsics()

    @abstractmethod
    def _capture(self, timeout: float) -> Frame:
        """Return the newest complete frame within ``timeout`` seconds."""

    @abstractmethod
    def _intrinsics(self) -> Intrinsics:
        """Return the depth stream's intrinsics."""
