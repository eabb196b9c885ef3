"""The worker's side of a camera run in a worker process: :class:`CameraServer`.

Built in the worker by :class:`~cellcal.devices.isolation.camera.CameraWorker` over the
:class:`~cellcal.devices.isolation.NativeHost` pipe. It holds the backend's own camera (its
SDK imported here only) and answers in plain values: a captured frame is written into the
parent's shared-memory ring (:mod:`.frames`) and only its slot, layout and scalars go back.
"""

from __future__ import annotations

import contextlib
import importlib
import pickle
from typing import Any

from ..camera import Camera3D
from ..measurement import MeasurementModel
from ..types import Frame
from . import frames


def _pack(obj: Any) -> bytes:
    """A dataclass's fields, pickled as builtin values (the parent unpickles nothing else)."""
    return pickle.dumps(frames.fields_of(obj), protocol=pickle.HIGHEST_PROTOCOL)


def _load(factory: str) -> Any:
    """``"package.module:Name"`` -> the object ``Name`` of that module."""
    module, _, name = factory.partition(":")
    obj: Any = importlib.import_module(module)
    for part in name.split("."):
        obj = getattr(obj, part)
    return obj


class CameraServer:
    """One camera backend, run in-process in the worker.

    Args:
        factory: ``"module:callable"``; ``callable(config)`` returns the (unconnected) camera.
        config: The backend's config, as it runs here (in-process).
        override: The config's ``[camera.model]`` model (the backend may rely on it at connect).
    """

    def __init__(self, factory: str, config: Any, override: MeasurementModel | None = None) -> None:
        camera = _load(factory)(config)
        if not isinstance(camera, Camera3D):
            raise TypeError(f"{factory} built a {type(camera).__name__}, not a Camera3D")
        camera.measurement_override = override
        self.camera = camera
        self._ring: frames.Mapping | None = None
        self._slot_bytes = 0
        self._slots = 0
        self._held: Frame | None = None

    def connect(self, timeout: float) -> None:
        """Connect the camera."""
        self.camera.connect(timeout)

    def measurement(self) -> bytes:
        """The camera's measurement model: its fields, pickled as builtin values."""
        return _pack(self.camera.measurement_model)

    def intrinsics(self) -> bytes:
        """The camera's intrinsics: the :class:`~cellcal.devices.types.Intrinsics` fields, pickled."""
        return _pack(self.camera.intrinsics)

    def info(self) -> bytes:
        """The camera's identity: the :class:`~cellcal.devices.types.DeviceInfo` fields, pickled."""
        return _pack(self.camera.info())

    def attach(self, name: str, slot_bytes: int, slots: int) -> None:
        """Map the parent's ring ``name`` (``slots`` slots of ``slot_bytes``) in place of any earlier one."""
        self.detach()
        self._ring = frames.Mapping(name, slot_bytes * slots)
        self._slot_bytes, self._slots = slot_bytes, slots

    def detach(self) -> None:
        """Unmap the ring (the parent unlinks it)."""
        ring, self._ring = self._ring, None
        if ring is not None:
            ring.close()

    def capture(self, slot: int, timeout: float) -> dict[str, Any]:
        """Capture a frame into ``slot``; ``{"need": bytes}`` instead when no ring holds it (it is kept)."""
        frame = self.camera.capture(timeout)
        self._held = frame
        return self.put(slot)

    def put(self, slot: int) -> dict[str, Any]:
        """Write the frame kept by :meth:`capture` into ``slot``: its layout and header, or what it needs."""
        frame = self._held
        if frame is None:
            raise RuntimeError("no frame is waiting for a slot")
        entries, nbytes = frames.layout(frame)
        if self._ring is None or nbytes > self._slot_bytes:
            return {"need": nbytes}
        if not 0 <= slot < self._slots:
            raise ValueError(f"slot {slot} is not in a ring of {self._slots}")
        frames.write(self._ring.buf, slot * self._slot_bytes, frame, entries)
        self._held = None
        return {"slot": slot, "layout": entries, "header": frames.header(frame)}

    def close(self) -> None:
        """Close the camera and unmap the ring; never raises."""
        with contextlib.suppress(Exception):
            self.camera.close()
        self._held = None
        self.detach()
