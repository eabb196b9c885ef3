"""The ``acme-z1`` backend: an ACME Z1 time-of-flight camera as a cellcal ``Camera3D``.

What a backend does, in the order docs/extending.md walks through it:

1. A frozen ``Config`` dataclass: the keys of the ``[camera]`` table, with ranges in
   field metadata (``parse_section`` enforces them and names the key on an error).
2. The hooks ``_connect(timeout)``, ``_close()``, ``_info()``, ``_intrinsics()`` and
   ``_capture(timeout)``. The public methods of ``Camera3D`` already check the life
   cycle (NotConnectedError) and the timeouts; the hooks only talk to the device.
3. Units and frames: the SDK speaks millimetres of Z-depth and microseconds; the
   backend hands out metres of *radial* distance, xyz in the OpenCV camera frame
   (x right, y down, z forward) and seconds since the epoch.
4. Errors: SDK failures become cellcal's typed errors (DeviceConnectionError,
   DeviceTimeoutError, VendorError with the vendor's code).
5. The SDK is imported inside ``_connect`` only, so listing backends or validating a
   config works without it.
"""

from __future__ import annotations

import contextlib
import importlib
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
    MissingDependencyError,
    ProtocolError,
    VendorError,
)
from numpy.typing import NDArray

#: The module standing in for the vendor SDK (a real package would name "acme_sdk").
SDK_MODULE = "acme_cellcal._sdk"


@dataclass(frozen=True)
class AcmeZ1Config:
    """``[camera]`` table for ``backend = "acme-z1"``.

    The plane keys describe the synthetic scene the stand-in SDK renders; a real
    camera would not have them.
    """

    serial: str = field(default="", metadata={"doc": "device serial number; \"\" = first device found"})
    width: int = field(default=160, metadata={"gt": 0, "le": 640, "doc": "image width, px"})
    height: int = field(default=120, metadata={"gt": 0, "le": 480, "doc": "image height, px"})
    hfov_deg: float = field(default=70.0, metadata={"gt": 10.0, "lt": 170.0, "doc": "horizontal field of view, deg"})
    frame_rate_hz: float = field(default=30.0, metadata={"gt": 0.0, "le": 120.0, "doc": "frame rate, Hz"})
    plane_distance_m: float = field(default=1.2, metadata={"gt": 0.2, "le": 6.0,
                                                           "doc": "scene: plane distance on the optical axis, m"})
    plane_tilt_deg: float = field(default=20.0, metadata={"ge": -60.0, "le": 60.0,
                                                          "doc": "scene: plane tilt about the camera x axis, deg"})
    noise_m: float = field(default=0.001, metadata={"ge": 0.0, "le": 0.05, "doc": "depth noise sigma, m"})
    timeout_s: float = field(default=2.0, metadata={"gt": 0.0, "le": 60.0, "doc": "default I/O timeout, s"})


#: The working range of the Z1, metres (radial distance).
RANGE_M = (0.2, 6.0)


class AcmeZ1Camera(Camera3D):
    """ACME Z1 time-of-flight camera.

    Args:
        config: The validated ``[camera]`` table.
        context: Where the config came from (unused; kept for the registry's signature).
    """

    backend_name: ClassVar[str] = "acme-z1"
    Config: ClassVar[type[AcmeZ1Config]] = AcmeZ1Config

    def __init__(self, config: AcmeZ1Config, context: BackendContext | None = None):
        super().__init__()
        self.config = config
        self.context = context or BackendContext()
        self.default_timeout_s = config.timeout_s
        self._device: Any = None
        self._intr: Intrinsics | None = None
        self._rays_over_z: NDArray[np.float64] | None = None

    @staticmethod
    def _sdk() -> Any:
        try:
            return importlib.import_module(SDK_MODULE)
        except ImportError:
            raise MissingDependencyError("the ACME SDK", "sdk", package="cellcal-acme-camera") from None

    @classmethod
    def discover(cls, timeout: float = 2.0) -> list[DeviceInfo] | None:
        """The Z1 cameras reachable now (``cellcal devices --scan``)."""
        sdk = cls._sdk()
        return [DeviceInfo(backend=cls.backend_name, vendor="ACME", model="Z1", serial=s) for s in sdk.list_devices()]

    # ------------------------------------------------------------ life cycle
    def _connect(self, timeout: float) -> None:
        sdk = self._sdk()
        cfg = self.config
        serials = sdk.list_devices()
        serial = cfg.serial or (serials[0] if serials else "")
        settings = sdk.Z1Settings(width=cfg.width, height=cfg.height, hfov_deg=cfg.hfov_deg,
                                  frame_rate_hz=cfg.frame_rate_hz, plane_distance_mm=cfg.plane_distance_m * 1000.0,
                                  plane_tilt_deg=cfg.plane_tilt_deg, noise_mm=cfg.noise_m * 1000.0,
                                  min_range_mm=RANGE_M[0] * 1000.0, max_range_mm=RANGE_M[1] * 1000.0)
        try:
            device = sdk.Z1Device(serial, settings)
            device.open()
        except sdk.AcmeSdkError as exc:
            raise DeviceConnectionError(f"acme-z1: cannot open {serial or 'a device'}: {exc}") from None
        self._device = device
        fx, fy, cx, cy = device.intrinsics()
        self._intr = Intrinsics(width=cfg.width, height=cfg.height, fx=fx, fy=fy, cx=cx, cy=cy)
        v, u = np.mgrid[0:cfg.height, 0:cfg.width].astype(np.float64)
        self._rays_over_z = np.dstack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)])

    def _close(self) -> None:
        device, self._device = self._device, None
        if device is not None:
            with contextlib.suppress(Exception):  # _close must not raise
                device.close()

    def _info(self) -> DeviceInfo:
        return DeviceInfo(backend=self.backend_name, vendor="ACME", model="Z1", serial=self._device.serial,
                          firmware=self._device.firmware, extra={"frame_rate_hz": self.config.frame_rate_hz})

    def _intrinsics(self) -> Intrinsics:
        assert self._intr is not None
        return self._intr

    # ------------------------------------------------------------ capture
    def _capture(self, timeout: float) -> Frame:
        sdk = self._sdk()
        try:
            grabbed = self._device.grab(timeout_ms=max(1, int(timeout * 1000)))
        except sdk.AcmeSdkError as exc:
            raise VendorError("acme-z1", exc.code, str(exc)) from None
        if grabbed is None:
            raise DeviceTimeoutError(f"acme-z1 {self._device.serial}: no frame within {timeout:g} s")
        depth_mm, timestamp_us, frame_id = grabbed
        return self._to_frame(depth_mm, timestamp_us, frame_id)

    def _to_frame(self, depth_mm: NDArray[Any], timestamp_us: int, frame_id: int) -> Frame:
        intr = self._intrinsics()
        assert self._rays_over_z is not None
        if depth_mm.dtype != np.uint16 or depth_mm.shape != intr.shape:
            raise ProtocolError(f"acme-z1: frame is {depth_mm.dtype} {depth_mm.shape}, expected uint16 {intr.shape}")
        valid = depth_mm > 0
        z_m = np.where(valid, depth_mm * 1e-3, np.nan)            # vendor mm of Z-depth -> metres
        xyz = self._rays_over_z * z_m[..., None]                   # OpenCV camera frame, metres
        distance = np.linalg.norm(xyz, axis=2)                     # radial, as cellcal's Frame wants
        return Frame(distance=distance.astype(np.float32), xyz=xyz.astype(np.float32),
                     amplitude=valid.astype(np.float32), valid=valid, intrinsics=intr,
                     timestamp=timestamp_us * 1e-6, sequence=int(frame_id))
