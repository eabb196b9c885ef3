"""A fake ACME Z1: serves the Z1's wire protocol on 127.0.0.1 and renders a plane.

Used by the tests (the factory fixture starts one on port 0) and by the
``acme-z1-emulated`` backend (which starts one in-process). It speaks the vendor's units
on the wire — millimetres of Z-depth, microseconds — so the backend must convert.

What it sees: a fixed plane (``plane_distance_m`` on the optical axis, tilted
``plane_tilt_deg`` about the camera's x axis), or — given a ``scene`` callable such as
cellcal's :func:`~cellcal.devices.scene_view.scene_view` ``(...).view_from_camera`` —
the plane of a simulated cell as the camera sees it at each frame, so the camera
follows the simulated arm. ``stalled=True`` answers INFO but never a GRAB: a device
that stops sending frames, for the kit's stalled-device check.
"""

from __future__ import annotations

import contextlib
import json
import math
import socket
import threading
import time
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from cellcal.devices.pose import Pose
from cellcal.devices.scene_view import SceneSnapshot
from numpy.typing import NDArray

from . import wire

#: How often the server threads look at their stop flag, seconds.
POLL_S = 0.05


@dataclass(frozen=True)
class FakeZ1Settings:
    """What the fake device is and sees (SI units; the wire converts)."""

    serial: str = field(default="Z1-000417", metadata={"doc": "serial number the device reports"})
    width: int = field(default=160, metadata={"gt": 0, "le": wire.MAX_WIDTH, "doc": "image width, px"})
    height: int = field(default=120, metadata={"gt": 0, "le": wire.MAX_HEIGHT, "doc": "image height, px"})
    hfov_deg: float = field(default=70.0, metadata={"gt": 10.0, "lt": 170.0, "doc": "horizontal field of view, deg"})
    frame_rate_hz: float = field(default=30.0, metadata={"gt": 0.0, "le": 120.0, "doc": "frame rate, Hz"})
    noise_m: float = field(default=0.001, metadata={"ge": 0.0, "le": 0.05, "doc": "Z-depth noise sigma, m"})
    plane_distance_m: float = field(default=1.2, metadata={
        "gt": 0.2, "le": 6.0, "doc": "fixed scene (no simulated cell): plane distance on the optical axis, m"})
    plane_tilt_deg: float = field(default=20.0, metadata={
        "ge": -60.0, "le": 60.0, "doc": "fixed scene: plane tilt about the camera x axis, deg"})

    def intrinsics(self) -> tuple[float, float, float, float]:
        """``(fx, fy, cx, cy)`` in pixels (square pixels, no distortion)."""
        f = (self.width / 2.0) / math.tan(math.radians(self.hfov_deg) / 2.0)
        return f, f, (self.width - 1) / 2.0, (self.height - 1) / 2.0

    def fixed_scene(self) -> SceneSnapshot:
        """The fixed plane as a snapshot in the camera frame."""
        tilt = math.radians(self.plane_tilt_deg)
        # plane through (0, 0, d) with normal (0, sin t, -cos t), facing the camera
        normal = np.array([0.0, math.sin(tilt), -math.cos(tilt)])
        point = np.array([0.0, 0.0, self.plane_distance_m])
        return SceneSnapshot.from_base_frame(Pose.identity(), point, normal, (), time.time())


#: Working range of the Z1, metres of radial distance.
RANGE_M = (0.2, 6.0)


class FakeZ1:
    """The fake device: a TCP server on ``127.0.0.1`` (``port=0`` picks a free port).

    Use as a context manager, or ``start()`` / ``stop()``.

    Args:
        settings: What the device is and sees.
        scene: Called at every frame for what the camera sees; None = the fixed plane.
        stalled: Answer INFO but never a GRAB.
        port: TCP port; 0 = any free one (see :attr:`port`).
    """

    def __init__(self, settings: FakeZ1Settings | None = None, *, scene: Callable[[], SceneSnapshot] | None = None,
                 stalled: bool = False, port: int = 0):
        self.settings = settings or FakeZ1Settings()
        self.scene = scene
        self.stalled = stalled
        self._rng = np.random.default_rng(zlib.crc32(self.settings.serial.encode()))
        self._render_lock = threading.Lock()
        self._stop = threading.Event()
        self._listener = socket.create_server(("127.0.0.1", port))
        self._listener.settimeout(POLL_S)
        self._threads: list[threading.Thread] = []
        self._t0 = time.monotonic()
        self._next = 0
        fx, fy, cx, cy = self.settings.intrinsics()
        v, u = np.mgrid[0:self.settings.height, 0:self.settings.width].astype(np.float64)
        self._rays = np.dstack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)])  # (x, y, 1): t is the Z-depth

    @property
    def port(self) -> int:
        """The TCP port the device listens on."""
        return int(self._listener.getsockname()[1])

    def start(self) -> FakeZ1:
        """Start accepting connections."""
        self._spawn(self._accept_loop, "fake Z1 accept")
        return self

    def stop(self) -> None:
        """Stop serving, close every socket and join every thread."""
        self._stop.set()
        for t in list(self._threads):
            t.join(5.0)
        self._listener.close()

    def __enter__(self) -> FakeZ1:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ------------------------------------------------------------ serving
    def _spawn(self, target: Callable[..., None], name: str, *args: object) -> None:
        t = threading.Thread(target=target, args=args, name=name, daemon=True)
        self._threads = [x for x in self._threads if x.is_alive()] + [t]
        t.start()

    def _accept_loop(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            self._spawn(self._serve, "fake Z1 connection", conn)

    def _serve(self, conn: socket.socket) -> None:
        conn.settimeout(POLL_S)
        with conn:
            while not self._stop.is_set():
                request = _recv_exact(conn, wire.REQUEST.size, self._stop)
                if request is None:
                    return                                    # client gone, or stopping
                command, arg = wire.REQUEST.unpack(request)
                reply = self._reply(command, arg)
                if reply is not None:
                    with contextlib.suppress(OSError):
                        conn.sendall(reply)

    def _reply(self, command: bytes, arg: int) -> bytes | None:
        if command == wire.CMD_INFO:
            fx, fy, cx, cy = self.settings.intrinsics()
            body = json.dumps({"serial": self.settings.serial, "firmware": "3.2.1", "width": self.settings.width,
                               "height": self.settings.height, "fx": fx, "fy": fy, "cx": cx, "cy": cy}).encode()
            return wire.HEADER.pack(wire.REPLY_INFO, 0, len(body)) + body
        if command == wire.CMD_GRAB:
            if self.stalled:
                return None                                   # never answers a GRAB
            return self._grab(arg)
        return _error(400, f"unknown command {command!r}")

    def _grab(self, timeout_ms: int) -> bytes:
        with self._render_lock:
            period = 1.0 / self.settings.frame_rate_hz
            wait = self._t0 + self._next * period - time.monotonic()
            if wait > timeout_ms / 1000.0:
                return _error(wire.CODE_NO_FRAME, f"no frame within {timeout_ms} ms")
            if wait > 0:
                time.sleep(wait)
            frame_id = self._next
            self._next = max(self._next + 1, int((time.monotonic() - self._t0) / period) + 1)
            depth = self._render()
        s = self.settings
        body = wire.FRAME_HEAD.pack(s.width, s.height, int(time.time() * 1e6)) + depth.astype("<u2").tobytes()
        return wire.HEADER.pack(wire.REPLY_FRAME, frame_id, len(body)) + body

    def _render(self) -> NDArray[np.uint16]:
        """One Z-depth image, millimetres, 0 where there is no return."""
        snap = self.scene() if self.scene is not None else self.settings.fixed_scene()
        z_m = snap.plane_range(self._rays)                         # Z-depth to the plane, metres (inf: missed)
        z_m = z_m + self._rng.normal(0.0, self.settings.noise_m, z_m.shape)
        radial_m = z_m * np.linalg.norm(self._rays, axis=2)        # the range limits apply to radial distance
        ok = np.isfinite(z_m) & (radial_m >= RANGE_M[0]) & (radial_m <= RANGE_M[1])
        return np.where(ok, np.rint(z_m * 1000.0), 0).astype(np.uint16)


def _error(code: int, text: str) -> bytes:
    body = text.encode()
    return wire.HEADER.pack(wire.REPLY_ERROR, code, len(body)) + body


def _recv_exact(conn: socket.socket, n: int, stop: threading.Event) -> bytes | None:
    """``n`` bytes from ``conn``, or None on EOF, error or ``stop``."""
    buf = bytearray()
    while len(buf) < n:
        if stop.is_set():
            return None
        try:
            chunk = conn.recv(n - len(buf))
        except TimeoutError:
            continue
        except OSError:
            return None
        if not chunk:
            return None
        buf += chunk
    return bytes(buf)
