"""Stand-in for the vendor's SDK ("acme_sdk"): a synthetic ACME Z1 that sees one plane.

A real vendor package would ``import acme_sdk`` here instead; everything in this
module speaks the vendor's units — millimetres, degrees, microseconds — exactly so
that the backend in :mod:`acme_cellcal.camera` has to convert them to SI at the
boundary, as a real backend does.

The device renders a flat plane in front of it: ``plane_distance_mm`` along the
optical axis, tilted ``plane_tilt_deg`` about the camera's x axis. Each frame is a
uint16 Z-depth image (millimetres along the optical axis, 0 = no return), with
Gaussian noise and the returns outside the working range dropped. Frames come at
``frame_rate_hz``; :meth:`Z1Device.grab` waits for the next one, at most
``timeout_ms``.
"""

from __future__ import annotations

import math
import threading
import time
import zlib
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

#: Serial numbers of the devices "on the network".
DEVICES = ("Z1-000417", "Z1-000842")
FIRMWARE = "3.2.1"


class AcmeSdkError(RuntimeError):
    """What the SDK raises; carries the vendor's numeric code."""

    def __init__(self, code: int, text: str):
        self.code = code
        super().__init__(f"ACME error {code}: {text}")


@dataclass(frozen=True)
class Z1Settings:
    """Device settings in the vendor's units."""

    width: int = 160
    height: int = 120
    hfov_deg: float = 70.0
    frame_rate_hz: float = 30.0
    plane_distance_mm: float = 1200.0
    plane_tilt_deg: float = 20.0
    noise_mm: float = 1.0
    min_range_mm: float = 200.0
    max_range_mm: float = 6000.0


def list_devices() -> list[str]:
    """Serial numbers of the reachable devices."""
    return list(DEVICES)


class Z1Device:
    """One ACME Z1. ``open()`` before use, ``close()`` after."""

    def __init__(self, serial: str, settings: Z1Settings):
        if serial not in DEVICES:
            raise AcmeSdkError(404, f"no device with serial {serial!r}")
        self.serial = serial
        self.settings = settings
        self._rng = np.random.default_rng(zlib.crc32(serial.encode()))
        self._lock = threading.Lock()
        self._open = False
        self._t0 = 0.0
        self._next = 0

    def open(self) -> None:
        with self._lock:
            self._open = True
            self._t0 = time.monotonic()
            self._next = 0

    def close(self) -> None:
        with self._lock:
            self._open = False

    @property
    def firmware(self) -> str:
        return FIRMWARE

    def intrinsics(self) -> tuple[float, float, float, float]:
        """``(fx, fy, cx, cy)`` in pixels (square pixels, no distortion)."""
        s = self.settings
        f = (s.width / 2.0) / math.tan(math.radians(s.hfov_deg) / 2.0)
        return f, f, (s.width - 1) / 2.0, (s.height - 1) / 2.0

    def grab(self, timeout_ms: int) -> tuple[NDArray[np.uint16], int, int] | None:
        """The next frame: ``(depth_mm, timestamp_us, frame_id)``, or None after ``timeout_ms``."""
        with self._lock:
            if not self._open:
                raise AcmeSdkError(17, "device is not open")
            period = 1.0 / self.settings.frame_rate_hz
            due = self._t0 + self._next * period
            wait = due - time.monotonic()
            if wait > timeout_ms / 1000.0:
                return None
            if wait > 0:
                time.sleep(wait)
            frame_id = self._next
            self._next = max(self._next + 1, int((time.monotonic() - self._t0) / period) + 1)
            return self._render(), int(time.time() * 1e6), frame_id

    def _render(self) -> NDArray[np.uint16]:
        s = self.settings
        fx, fy, cx, cy = self.intrinsics()
        v, u = np.mgrid[0:s.height, 0:s.width].astype(np.float64)
        x, y = (u - cx) / fx, (v - cy) / fy      # ray (x, y, 1) per pixel
        tilt = math.radians(s.plane_tilt_deg)
        # plane through (0, 0, d) with normal (0, sin t, -cos t): z = d cos t / (cos t - y sin t)
        denom = math.cos(tilt) - y * math.sin(tilt)
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(denom > 1e-6, s.plane_distance_mm * math.cos(tilt) / denom, np.inf)
        z = z + self._rng.normal(0.0, s.noise_mm, z.shape)
        r = z * np.sqrt(x * x + y * y + 1.0)
        return np.where((r >= s.min_range_mm) & (r <= s.max_range_mm), np.rint(z), 0).astype(np.uint16)
