"""A camera backend whose SDK runs in a worker process: :class:`CameraWorker`, :class:`IsolatableCamera`.

The whole backend (its in-process code, ``isolate = false``) runs in a
:class:`~cellcal.devices.isolation.NativeHost` worker behind a
:class:`~cellcal.devices.isolation.camera_server.CameraServer`; frames come back through a
shared-memory ring (:mod:`.frames`), everything else as plain values. Every call waits at most
the caller's timeout plus :data:`IPC_GRACE_S`; a dead worker is a
:class:`~cellcal.devices.errors.NativeCrashError` now and on every later call, its ring
unlinked at once, and the next ``connect()`` starts a new worker. Design: docs/adr/0063-camera-workers.md.
"""

from __future__ import annotations

import contextlib
import dataclasses
import time
from typing import Any, ClassVar, Self

from ..camera import Camera3D
from ..errors import DeviceConnectionError, ProtocolError
from ..measurement import MeasurementModel
from ..types import DeviceInfo, Frame, Intrinsics
from .frames import DEFAULT_SLOTS, FrameRing, loads_builtins
from .host import NativeHost, RemoteObject

#: The parent waits for a call this much longer than the timeout the backend itself is given, s: the
#: backend's own timeout error (with its own words) arrives first; the pipe and the copy fit easily.
IPC_GRACE_S = 0.5
#: Seconds the worker gets to close the camera before it is told to exit.
CLOSE_CAMERA_S = 3.0
SERVER_MODULE = "cellcal.devices.isolation.camera_server"


def _unpack(cls: type[Any], data: Any, what: str) -> Any:
    """A dataclass rebuilt from the worker's pickled builtin fields."""
    if not isinstance(data, bytes):
        raise ProtocolError(f"the camera worker sent {type(data).__name__} for the {what}")
    try:
        return cls(**loads_builtins(data))
    except Exception as exc:  # unreadable, or fields the class refuses: a worker not to be trusted
        raise ProtocolError(f"the camera worker's {what} is unreadable: {exc}") from None


class CameraWorker:
    """A camera backend run in a worker process, seen from the parent.

    Args:
        name: Who this is for messages, e.g. ``"oak 14442C10D13EABCE00"``.
        library: The native library, e.g. ``"depthai"``.
        backend: The backend's registered name.
        factory: ``"module:callable"`` building the in-process camera in the worker from ``config``.
        config: The backend's config as it runs in the worker (``isolate = false``).
        call_timeout_s: Longest wait for a call that has no timeout of its own (intrinsics, info), s.
        first_wait_s: The first capture after connect may take this long whatever its timeout (a
            device that just switched state), s.
        override: The config's ``[camera.model]`` model, also given to the camera in the worker.
        slots: Slots of the frame ring.
    """

    def __init__(self, name: str, *, library: str, backend: str, factory: str, config: Any,
                 call_timeout_s: float, first_wait_s: float = 0.0, override: MeasurementModel | None = None,
                 slots: int = DEFAULT_SLOTS) -> None:
        self.name = name
        self.factory = factory
        self.config = config
        self.call_timeout_s = float(call_timeout_s)
        self._first_wait_s = float(first_wait_s)
        self.override = override
        self.slots = slots
        self.host = NativeHost(name, library=library, backend=backend, default_timeout_s=call_timeout_s,
                               on_crash=self._release_ring)
        self.model: MeasurementModel | None = None
        self._server: RemoteObject | None = None
        self._ring: FrameRing | None = None
        self._intr: Intrinsics | None = None

    @property
    def pid(self) -> int | None:
        """The worker's process id while it runs."""
        return self.host.pid

    @property
    def dead(self) -> bool:
        """Whether the worker died (or was stopped as untrustworthy); the camera must connect again."""
        return self.host._dead is not None

    @property
    def ring_name(self) -> str | None:
        """The shared-memory segment of the frame ring (None before the first frame, after close or a crash)."""
        return self._ring.name if self._ring is not None else None

    # ------------------------------------------------------------ life cycle
    def start(self, timeout: float) -> None:
        """Start the worker, build the camera there and connect it, all within ``timeout`` s (+ the grace)."""
        deadline = time.monotonic() + timeout
        self.host.start(timeout)
        left = max(deadline - time.monotonic(), 1e-3)
        # a backend whose connect fails closes itself before it answers (the OAK joins its threads)
        with self.host.deadline(left + IPC_GRACE_S + CLOSE_CAMERA_S, "connect"):
            server = self.host.module(SERVER_MODULE).CameraServer(self.factory, self.config, self.override)
            if not isinstance(server, RemoteObject):
                raise ProtocolError(f"{self.name}: the camera worker sent a {type(server).__name__}, not its camera")
            self._server = server
            server.connect(left)
            self.model = _unpack(MeasurementModel, server.measurement(), "measurement model")

    def close(self) -> None:
        """Close the camera in the worker, end the worker, unlink the ring; never raises."""
        server, self._server = self._server, None
        if server is not None and not self.dead:
            with contextlib.suppress(Exception), self.host.deadline(CLOSE_CAMERA_S, "close"):
                server.close()
        self.host.close()
        self._release_ring()

    def _release_ring(self) -> str:
        """Unlink the frame ring (the worker is gone or going); the clause for a crash message: none."""
        ring, self._ring = self._ring, None
        if ring is not None:
            ring.close()
        return ""

    def _require(self) -> RemoteObject:
        if self._server is None:
            raise DeviceConnectionError(f"{self.name}: the camera worker is not running")
        return self._server

    # ------------------------------------------------------------ calls
    def capture(self, timeout: float) -> Frame:
        """The backend's ``capture(timeout)`` in the worker; the frame wraps its slot of the ring, or is copied out."""
        server = self._require()
        ring = self._ring
        slot = ring.acquire() if ring is not None else 0
        answered = self.host.answered
        wait_s, self._first_wait_s = max(timeout, self._first_wait_s), 0.0
        try:
            with self.host.deadline(wait_s + IPC_GRACE_S, f"capture(timeout={timeout:g} s)"):
                reply = server.capture(slot, timeout)
                if isinstance(reply, dict) and "need" in reply:  # the first frame, or a larger one
                    ring = self._new_ring(reply["need"], server)
                    slot = ring.acquire()
                    answered = self.host.answered  # for the call that writes the slot
                    reply = server.put(slot)
        except BaseException:
            if ring is not None and not ring.closed:
                # answered: the worker is done with the slot; else it may still write it
                (ring.release if self.host.answered != answered else ring.abandon)(slot)
            raise
        assert ring is not None
        wrap = ring.free >= 1  # the frame holds its slot while another stays free for the next capture
        try:
            if not (isinstance(reply, dict) and reply.get("slot") == slot and isinstance(reply.get("layout"), list)
                    and isinstance(reply.get("header"), bytes)):
                raise ProtocolError(f"{self.name}: the camera worker's reply to capture is not a frame in slot {slot}")
            frame = ring.read(slot, reply["layout"], reply["header"], wrap=wrap)
        except BaseException:
            ring.release(slot)
            raise
        ring.release(None if wrap else slot)
        if frame.intrinsics != self._intr:
            self._intr = frame.intrinsics
        return frame

    def _new_ring(self, need: Any, server: RemoteObject) -> FrameRing:
        """A ring whose slots hold ``need`` bytes, attached in the worker (the old one unlinked)."""
        if type(need) is not int or need <= 0:
            raise ProtocolError(f"{self.name}: the camera worker asks for a slot of {need!r} bytes")
        self._release_ring()
        ring = FrameRing(need, self.slots)
        self._ring = ring
        server.attach(ring.name, ring.slot_bytes, ring.slots)
        return ring

    def intrinsics(self) -> Intrinsics:
        """The depth stream's intrinsics: the last frame's, else asked of the worker once."""
        if self._intr is None:
            server = self._require()
            with self.host.deadline(self.call_timeout_s + IPC_GRACE_S, "intrinsics"):
                self._intr = _unpack(Intrinsics, server.intrinsics(), "intrinsics")
        return self._intr

    def info(self) -> DeviceInfo:
        """The device's identity, asked of the worker."""
        server = self._require()
        with self.host.deadline(self.call_timeout_s + IPC_GRACE_S, "info"):
            info: DeviceInfo = _unpack(DeviceInfo, server.info(), "identity")
        return info


class IsolatableCamera(Camera3D):
    """Base of a camera backend whose SDK can run in a worker process (its config's ``isolate``).

    The subclass's config has ``isolate: bool``; with it, ``_connect`` calls :meth:`_start_worker`
    and the other hooks hand over to :attr:`_worker`. The worker builds the same class (or
    :attr:`worker_factory`) with ``isolate = false``.
    """

    #: Runs its SDK in a worker process unless ``isolate = false`` (ADR 0038, ADR 0063).
    wraps_native_code: ClassVar[bool] = True
    #: The native library, for messages.
    native_library: ClassVar[str] = ""
    #: ``"module:callable"`` building the in-process camera in the worker from its config; "" = this class.
    worker_factory: ClassVar[str] = ""
    _worker: CameraWorker | None = None

    def connect(self, timeout: float | None = None) -> Self:
        """As :meth:`Device.connect <cellcal.devices.base.Device.connect>`; after the worker died, a new worker."""
        with self._lifecycle_lock:
            if self._connected and self._worker is not None and self._worker.dead:
                self.close()
            return super().connect(timeout)

    @property
    def worker_pid(self) -> int | None:
        """The worker process's id (None in-process or before connect)."""
        return self._worker.pid if self._worker is not None else None

    def _start_worker(self, name: str, timeout: float, call_timeout_s: float, first_wait_s: float = 0.0) -> None:
        """Start the worker and connect the camera in it within ``timeout`` s (the rest as :class:`CameraWorker`)."""
        cls = type(self)
        worker = CameraWorker(name, library=self.native_library, backend=self.backend_name,
                              factory=self.worker_factory or f"{cls.__module__}:{cls.__qualname__}",
                              config=dataclasses.replace(self.config, isolate=False),  # type: ignore[attr-defined]
                              call_timeout_s=call_timeout_s, first_wait_s=first_wait_s,
                              override=self.measurement_override)
        self._worker = worker
        worker.start(timeout)

    def _stop_worker(self) -> None:
        worker, self._worker = self._worker, None
        if worker is not None:
            worker.close()
