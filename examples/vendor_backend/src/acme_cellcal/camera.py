"""The ``acme-z1`` backend: an ACME Z1 time-of-flight camera on the network, as a cellcal ``Camera3D``.

What a backend does, in the order docs/extending.md walks through it:

1. A frozen ``Config`` dataclass: the keys of the ``[camera]`` table, with ranges in
   field metadata (``parse_section`` enforces them and names the key on an error).
2. The hooks ``_connect(timeout)``, ``_close()``, ``_info()``, ``_intrinsics()`` and
   ``_capture(timeout)``. The public methods of ``Camera3D`` already check the life
   cycle (NotConnectedError) and the timeouts; the hooks only talk to the device.
3. Units and frames: the Z1 sends millimetres of Z-depth and microseconds; the backend
   hands out metres of *radial* distance, xyz in the OpenCV camera frame (x right,
   y down, z forward) and seconds since the epoch.
4. Errors and timeouts: every exchange is bounded by one deadline; a device that sends
   nothing is a DeviceTimeoutError, bytes off the protocol a ProtocolError, the
   device's error codes a VendorError.
5. How it measures: ``_measurement_model()`` states the Z1's ToF model from its data
   sheet; every frame ``capture()`` returns carries it (docs/extending.md, "Stating how
   the camera measures").
"""

from __future__ import annotations

import contextlib
import json
import math
import socket
import time
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
from cellcal.devices import (
    BackendContext,
    Camera3D,
    DeviceConnectionError,
    DeviceInfo,
    DeviceTimeoutError,
    Frame,
    Intrinsics,
    ProtocolError,
    VendorError,
)
from cellcal.devices.measurement import MeasurementModel
from numpy.typing import NDArray

from . import wire


@dataclass(frozen=True)
class AcmeZ1Config:
    """``[camera]`` table for ``backend = "acme-z1"``."""

    host: str = field(default="192.168.0.69", metadata={"doc": "the camera's IP address or host name"})
    port: int = field(default=50010, metadata={"ge": 1, "le": 65535, "doc": "the camera's TCP port"})
    timeout_s: float = field(default=2.0, metadata={"gt": 0.0, "le": 60.0, "doc": "default I/O timeout, s"})


#: The working range of the Z1, metres (radial distance).
RANGE_M = (0.2, 6.0)
#: The Z1's data sheet: Z-depth noise 1 mm (1-sigma) over its whole range, sent in whole millimetres.
Z1_MODEL = MeasurementModel(kind="tof", sigma_at_1m_m=0.001, distance_exponent=0.0, range_step_m=0.001,
                            source="backend", settings={"depth_unit_m": 0.001})


class AcmeZ1Camera(Camera3D):
    """ACME Z1 time-of-flight camera over TCP.

    Args:
        config: The validated ``[camera]`` table.
        context: Where the config came from (unused by a real camera).
    """

    backend_name: ClassVar[str] = "acme-z1"
    Config: ClassVar[type[AcmeZ1Config]] = AcmeZ1Config

    def __init__(self, config: AcmeZ1Config, context: BackendContext | None = None):
        super().__init__()
        self.config = config
        self.context = context or BackendContext()
        self.default_timeout_s = config.timeout_s
        self._sock: socket.socket | None = None
        self._info_reply: dict[str, Any] = {}
        self._intr: Intrinsics | None = None
        self._rays_over_z: NDArray[np.float64] | None = None

    # ------------------------------------------------------------ life cycle
    def _connect(self, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        self._open(deadline)
        info = self._info_from(self._exchange(wire.CMD_INFO, 0, deadline))
        self._info_reply = info
        self._intr = Intrinsics(width=info["width"], height=info["height"], fx=info["fx"], fy=info["fy"],
                                cx=info["cx"], cy=info["cy"])
        v, u = np.mgrid[0:self._intr.height, 0:self._intr.width].astype(np.float64)
        self._rays_over_z = np.dstack([(u - self._intr.cx) / self._intr.fx, (v - self._intr.cy) / self._intr.fy,
                                       np.ones_like(u)])

    def _open(self, deadline: float) -> None:
        where = f"{self.config.host}:{self.config.port}"
        try:
            self._sock = socket.create_connection((self.config.host, self.config.port),
                                                  timeout=max(1e-3, deadline - time.monotonic()))
        except TimeoutError:
            raise DeviceTimeoutError(f"acme-z1: no connection to {where} within the timeout") from None
        except OSError as exc:
            raise DeviceConnectionError(f"acme-z1: cannot reach {where}: {exc.strerror or exc}") from None

    def _close(self) -> None:
        sock, self._sock = self._sock, None
        if sock is not None:
            with contextlib.suppress(OSError):  # _close must not raise
                sock.close()

    def _info(self) -> DeviceInfo:
        return DeviceInfo(backend=self.backend_name, vendor="ACME", model="Z1", serial=str(self._info_reply["serial"]),
                          firmware=str(self._info_reply["firmware"]), extra={"address": self.config.host})

    def _intrinsics(self) -> Intrinsics:
        assert self._intr is not None
        return self._intr

    def _measurement_model(self) -> MeasurementModel:
        return Z1_MODEL

    # ------------------------------------------------------------ capture
    def _capture(self, timeout: float) -> Frame:
        deadline = time.monotonic() + timeout
        if self._sock is None:                        # the link was dropped after a timeout: reopen it
            self._open(deadline)
        # ask the device to wait a little less than we do, so its "no frame" reply still arrives in time
        kind, frame_id, body = self._exchange(wire.CMD_GRAB, max(1, int(timeout * 900)), deadline)
        if kind != wire.REPLY_FRAME:
            raise ProtocolError(f"acme-z1: expected a frame, got a {kind!r} reply")
        return self._to_frame(body, frame_id)

    def _to_frame(self, body: bytes, frame_id: int) -> Frame:
        intr = self._intrinsics()
        assert self._rays_over_z is not None
        width, height, timestamp_us = wire.FRAME_HEAD.unpack_from(body)
        if (height, width) != intr.shape or len(body) != wire.FRAME_HEAD.size + 2 * width * height:
            raise ProtocolError(f"acme-z1: a {width}x{height} frame of {len(body)} bytes; the camera is "
                                f"{intr.width}x{intr.height}", offset=0)
        depth_mm = np.frombuffer(body, dtype="<u2", offset=wire.FRAME_HEAD.size).reshape(height, width)
        valid = depth_mm > 0
        z_m = np.where(valid, depth_mm * 1e-3, np.nan)            # vendor mm of Z-depth -> metres
        xyz = self._rays_over_z * z_m[..., None]                   # OpenCV camera frame, metres
        distance = np.linalg.norm(xyz, axis=2)                     # radial, as cellcal's Frame wants
        return Frame(distance=distance.astype(np.float32), xyz=xyz.astype(np.float32),
                     amplitude=valid.astype(np.float32), valid=valid, intrinsics=intr,
                     timestamp=timestamp_us * 1e-6, sequence=int(frame_id))

    # ------------------------------------------------------------ the wire
    def _exchange(self, command: bytes, arg: int, deadline: float) -> tuple[bytes, int, bytes]:
        """Send one request and read its reply, all before ``deadline``; ``(kind, number, body)``.

        On a timeout or a broken stream the link is closed (a late reply would be read
        as the answer to the next request); the next capture reopens it.
        """
        try:
            assert self._sock is not None
            self._sock.settimeout(max(1e-3, deadline - time.monotonic()))
            self._sock.sendall(wire.REQUEST.pack(command, arg))
            kind, number, length = wire.HEADER.unpack(self._recv_exact(wire.HEADER.size, deadline))
            if kind not in (wire.REPLY_INFO, wire.REPLY_FRAME, wire.REPLY_ERROR) or length > wire.MAX_BODY:
                raise ProtocolError(f"acme-z1: bad reply header kind={kind!r} length={length}", offset=0)
            body = self._recv_exact(length, deadline)
        except TimeoutError:
            self._close_link()
            raise DeviceTimeoutError(f"acme-z1 {self.config.host}:{self.config.port}: no reply to "
                                     f"{command.decode()} within the timeout") from None
        except ProtocolError:
            self._close_link()
            raise
        except OSError as exc:
            self._close_link()
            raise DeviceConnectionError(f"acme-z1: link lost: {exc.strerror or exc}") from None
        if kind == wire.REPLY_ERROR:
            text = body.decode("utf-8", "replace")
            if number == wire.CODE_NO_FRAME:
                raise DeviceTimeoutError(f"acme-z1: no frame within the timeout ({text})")
            raise VendorError("acme-z1", number, text)
        return kind, number, body

    def _recv_exact(self, n: int, deadline: float) -> bytes:
        assert self._sock is not None
        buf = bytearray()
        while len(buf) < n:
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError
            self._sock.settimeout(left)
            chunk = self._sock.recv(n - len(buf))
            if not chunk:
                raise ConnectionResetError("the camera closed the connection")
            buf += chunk
        return bytes(buf)

    def _close_link(self) -> None:
        self._close()

    @staticmethod
    def _info_from(reply: tuple[bytes, int, bytes]) -> dict[str, Any]:
        """The INFO reply, validated: a device lies until checked."""
        kind, _, body = reply
        try:
            info = json.loads(body) if kind == wire.REPLY_INFO else None
        except ValueError:
            info = None
        if not isinstance(info, dict):
            raise ProtocolError("acme-z1: INFO reply is not a JSON object", offset=wire.HEADER.size)
        sizes = (info.get("width"), info.get("height"))
        if not all(isinstance(v, int) and 0 < v <= m for v, m in zip(sizes, (wire.MAX_WIDTH, wire.MAX_HEIGHT),
                                                                       strict=True)):
            raise ProtocolError(f"acme-z1: INFO reports an image of {sizes[0]}x{sizes[1]} px")
        for key in ("fx", "fy", "cx", "cy"):
            value = info.get(key)
            if not (isinstance(value, (int, float)) and math.isfinite(value)):
                raise ProtocolError(f"acme-z1: INFO key {key!r} is {value!r}, not a number")
        return info
