"""The ifm O3R 3D head through ifm's own client, ifm3dpy (backend ``o3r-ifm3d``).

For users who want ifm's supported library; the own PCIC client (backend ``o3r``)
stays the default and the fallback. ifm3dpy is imported in ``_connect`` only; where it
is missing the backend says so in one line (:class:`MissingDependencyError`). ifm3dpy runs in a
worker process unless ``isolate = false`` (docs/adr/0063-camera-workers.md): a crash in it is a
:class:`~cellcal.devices.errors.NativeCrashError`, frames come back through shared memory.

ifm3dpy hands out XYZ in ifm's *user* frame; this backend returns it in the camera's
optical frame (the :class:`Frame` contract) by undoing TOF_INFO's extrinsicOpticToUser,
``p_optical = R^T (p_user - t)`` with ``R = Rx(rotX) Ry(rotY) Rz(rotZ)``. Intrinsics come
from TOF_INFO's inverse intrinsic model 1 (OpenCV's projection). ifm3dpy's calls hold the
GIL and its XML-RPC calls use ifm3d's own timeouts; frame waits are bounded here.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from cellcal.devices.base import BackendContext
from cellcal.devices.errors import (
    DeviceConnectionError,
    DeviceTimeoutError,
    MissingDependencyError,
    ProtocolError,
    VendorError,
)
from cellcal.devices.isolation.camera import IsolatableCamera
from cellcal.devices.measurement import MeasurementModel
from cellcal.devices.types import DeviceInfo, Frame, Intrinsics
from cellcal.drivers.o3r_json import firmware, port_info

#: The O3R 3D head's range noise, 1-sigma at 1 m and normal incidence, metres: ifm's O3R222
#: data sheet quotes a repeatability of < 7 mm at distances below 1 m (the figure the simulated
#: camera is built on, docs/adr/0014-simulated-cell.md), read as 2 sigma: 3.5 mm. A data-sheet
#: figure (a real frame agrees, see the exponent below); change it here and in drivers/o3r/camera.py
#: (the two drivers stand alone, and state the same model; a test checks both).
O3R_SIGMA_AT_1M_M = 0.0035
#: Exponent of the range in the O3R's noise law, set against a real O3R frame (ifm's own test
#: capture, tests/data/o3r): its pixel scatter is flat with range, 3.0 mm on a face 0.28 m away at
#: 50 deg incidence and 3-4.2 mm over 0.2-0.8 m, which with 3.5 mm at 1 m gives 0.3. Beyond ~1.5 m the
#: data sheet's figures grow faster (2 sigma 15 mm at 2 m, 51 mm at 4 m): the residual gate's
#: factor of 4 still covers 2 m; state a steeper law in [camera.model] for a cell working farther.
O3R_DISTANCE_EXPONENT = 0.3


def o3r_measurement_model() -> MeasurementModel:
    """The O3R head's ToF model from the data sheet (``source = "backend"``)."""
    return MeasurementModel(kind="tof", sigma_at_1m_m=O3R_SIGMA_AT_1M_M, distance_exponent=O3R_DISTANCE_EXPONENT,
                            source="backend", settings={"basis": "O3R222 data sheet repeatability, read as 2 sigma"})

#: ifm3dpy's buffers this backend asks for.
_BUFFERS = ("RADIAL_DISTANCE_IMAGE", "XYZ", "NORM_AMPLITUDE_IMAGE", "CONFIDENCE_IMAGE", "TOF_INFO")


@dataclass(frozen=True)
class O3RIfm3dConfig:
    """The ``[camera]`` table of the ``o3r-ifm3d`` backend."""

    host: str = field(default="192.168.0.69", metadata={"doc": "VPU address"})
    xmlrpc_port: int = field(default=80, metadata={"ge": 1, "le": 65535, "doc": "XML-RPC TCP port"})
    port: str = field(default="port2", metadata={"doc": "VPU port of the 3D head: port0..port5 (several heads on one "
                                                        "VPU: one camera entry per head)"})
    pcic_port: int = field(default=0, metadata={"ge": 0, "le": 65535,
                                                "doc": "PCIC TCP port; 0 = read /ports/<port>/data/pcicTCPPort"})
    trigger: Literal["free_run", "software"] = field(default="free_run",
                                                     metadata={"doc": "RUN (free_run) or IDLE + software trigger"})
    set_state: bool = field(default=True, metadata={"doc": "switch the port to the state the trigger needs"})
    start_timeout_s: float = field(default=5.0, metadata={"ge": 0.1, "le": 120.0,
                                                          "doc": "wait for ifm3dpy's frame grabber to start, s"})
    first_frame_timeout_s: float = field(default=10.0, metadata={
        "ge": 0.01, "le": 600.0, "doc": "longest wait for the first frame after a state change, s"})
    clock_tolerance_s: float = field(default=30.0, metadata={
        "ge": 0.001, "le": 1e9, "doc": "device clock this far from host time is not Unix time (receive time used), s"})
    isolate: bool = field(default=True, metadata={
        "doc": "run ifm3dpy in a worker process, so a crash in it is an error and not the end of cellcal; "
               "false runs it in-process (a debugger)"})


@dataclass
class _Latest:
    """The newest frame ifm3dpy delivered, and when."""

    frame: Any = None
    received_mono: float = 0.0
    received_epoch: float = 0.0


class O3RIfm3dCamera(IsolatableCamera):
    """ifm O3R 3D head over ifm3dpy's ``O3R`` and ``FrameGrabber``.

    ``trigger = "free_run"`` wants the port in RUN (``capture`` returns the newest frame
    received after the previous capture); ``"software"`` wants IDLE (``capture`` sends a
    software trigger and returns the frame received after it). Timestamps follow the
    ``o3r`` backend: the device's time when its clock is Unix time, else the receive
    time, with the device time in ``Frame.metadata["device_timestamp_s"]``.

    Args:
        config: Backend config; None uses the defaults.
        context: Backend context (unused; accepted for the registry).
    """

    backend_name = "o3r-ifm3d"
    Config = O3RIfm3dConfig
    native_library = "ifm3dpy"

    def __init__(self, config: O3RIfm3dConfig | None = None, context: BackendContext | None = None) -> None:
        super().__init__()
        self.config = config or O3RIfm3dConfig()
        self.default_timeout_s = 2.0
        self._o3r: Any = None
        self._fg: Any = None
        self._ids: Any = None
        self._deser: Any = None
        self._cond = threading.Condition()
        self._latest = _Latest()
        self._taken_mono = 0.0
        self._intr: Intrinsics | None = None
        self._state_changed = False
        self._firmware = ""
        self._pcic_port = 0

    @classmethod
    def unavailable_reason(cls) -> str | None:
        """None if ifm3dpy can be imported; else the install hint (ifm3dpy is not imported here)."""
        import importlib.util

        if importlib.util.find_spec("ifm3dpy") is not None:
            return None
        return str(_missing())

    # ------------------------------------------------------------------ connect / close
    def _connect(self, timeout: float) -> None:
        if self.config.isolate:
            if self.unavailable_reason() is not None:  # said here, before a worker is started for nothing
                raise _missing()
            cfg = self.config
            # a head switched to another state takes a while for its first frame (the worker's capture waits)
            self._start_worker(f"o3r-ifm3d {cfg.host} {cfg.port}", timeout,
                               max(self.default_timeout_s, cfg.first_frame_timeout_s), cfg.first_frame_timeout_s)
            return
        try:
            from ifm3dpy import deserialize
            from ifm3dpy.device import O3R
            from ifm3dpy.framegrabber import FrameGrabber, buffer_id
        except ImportError:
            raise _missing() from None
        cfg = self.config
        deadline = time.monotonic() + timeout
        self._deser, self._ids = deserialize, buffer_id
        self._o3r = O3R(cfg.host, cfg.xmlrpc_port)
        self._pcic_port = cfg.pcic_port or self._set_up_port()
        fg = FrameGrabber(self._o3r, pcic_port=self._pcic_port)
        fg.on_new_frame(self._on_frame)
        self._fg = fg
        wait_ms = max(1, int(1000 * min(cfg.start_timeout_s, max(deadline - time.monotonic(), 0.001))))
        ok, _ = fg.start([getattr(buffer_id, b) for b in _BUFFERS]).wait_for(wait_ms)
        if not ok:
            raise DeviceTimeoutError(f"o3r-ifm3d {cfg.host}: ifm3dpy's frame grabber did not start on PCIC port "
                                     f"{self._pcic_port} within {wait_ms / 1000:g} s")

    def _set_up_port(self) -> int:
        """Read the port's PCIC port, type and state with ifm3dpy; switch its state if needed."""
        cfg = self.config
        node = self._call(lambda: self._o3r.get(["/ports"]), "get /ports")
        # every value checked as the o3r backend checks it: a missing, 2D or IMU port is one line naming the heads
        info = port_info(node, cfg.port, host=cfg.host, where=f"o3r-ifm3d {cfg.host} get(['/ports'])", kind="3D")
        pcic, state = info.pcic_port, info.state
        want = "RUN" if cfg.trigger == "free_run" else "IDLE"
        if state != want:
            if not cfg.set_state:
                raise DeviceConnectionError(f"O3R {cfg.host} {cfg.port} is in {state}, trigger '{cfg.trigger}' "
                                            f"needs {want} (or set_state = true)")
            self._call(lambda: self._o3r.set({"ports": {cfg.port: {"state": want}}}), f"set state {want}")
            self._state_changed = True
        sw = self._call(lambda: self._o3r.get(["/device/swVersion"]), "get /device/swVersion")
        self._firmware = firmware(sw, f"o3r-ifm3d {cfg.host} get(['/device/swVersion'])")
        return pcic

    def _call(self, fn: Any, what: str) -> Any:
        """An ifm3dpy configuration call; its errors as cellcal errors."""
        try:
            return fn()
        except RuntimeError as exc:  # ifm3dpy raises ifm3dpy.device.Error, a RuntimeError
            code = getattr(exc, "code", 0)
            text = str(getattr(exc, "message", exc))[:200]
            if code:
                raise VendorError("o3r-ifm3d", code, f"{self.config.host} {what}: {text}") from None
            raise DeviceConnectionError(f"o3r-ifm3d {self.config.host} {what}: {text}") from None

    def _close(self) -> None:
        self._stop_worker()
        fg, self._fg = self._fg, None
        if fg is not None:
            fg.stop().wait_for(2000)
            del fg
        self._o3r = None
        with self._cond:
            self._latest = _Latest()

    # ------------------------------------------------------------------ frames
    def _on_frame(self, frame: Any) -> None:
        """ifm3dpy's callback (its thread): keep the newest frame."""
        with self._cond:
            self._latest = _Latest(frame, time.monotonic(), time.time())
            self._cond.notify_all()

    def _wait_newer(self, after_mono: float, timeout: float) -> _Latest:
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                got = self._latest
                if got.frame is not None and got.received_mono > after_mono:
                    return got
                left = deadline - time.monotonic()
                if left <= 0:
                    raise DeviceTimeoutError(f"o3r-ifm3d {self.config.host}: no new frame within {timeout:g} s")
                self._cond.wait(left)

    def _capture(self, timeout: float) -> Frame:
        if self._worker is not None:
            return self._worker.capture(timeout)
        if self._state_changed:  # a head that just switched state takes a while for its first frame
            timeout = max(timeout, self.config.first_frame_timeout_s)
        if self.config.trigger == "software":
            sent = time.monotonic()
            self._fg.sw_trigger()
            got = self._wait_newer(sent, timeout)
        else:
            got = self._wait_newer(self._taken_mono, timeout)
        self._taken_mono = got.received_mono
        self._state_changed = False
        return self._to_frame(got)

    def _to_frame(self, got: _Latest) -> Frame:
        b, f = self._ids, got.frame
        raw_info = np.asarray(f.get_buffer(b.TOF_INFO), dtype=np.uint8).ravel()
        # TOF_INFO v4 (428 bytes) carries the measurement block; older firmware sends v3 or less
        info = (self._deser.TOFInfoV4 if raw_info.size >= 428 else self._deser.TOFInfoV3).deserialize(raw_info)
        dist = np.asarray(f.get_buffer(b.RADIAL_DISTANCE_IMAGE), dtype=np.float32)
        h, w = dist.shape[:2]
        dist = dist.reshape(h, w)
        conf = np.asarray(f.get_buffer(b.CONFIDENCE_IMAGE)).reshape(h, w)
        # invalid where the confidence's bit 0 is set or there is no distance
        valid = ((conf & 1) == 0) & (dist > 0)
        xyz = _user_to_optical(np.asarray(f.get_buffer(b.XYZ), dtype=np.float32).reshape(h, w, 3),
                               info.extrinsic_optic_to_user)
        dist = np.where(valid, dist, np.float32(np.nan)).astype(np.float32)
        xyz[~valid] = np.nan
        amp = np.asarray(f.get_buffer(b.NORM_AMPLITUDE_IMAGE), dtype=np.float32).reshape(h, w)
        if self._intr is None or (self._intr.width, self._intr.height) != (w, h):
            self._intr = _intrinsics(info.inverse_intrinsic_calibration, w, h)
        device_s = f.timestamps()[0].timestamp() if f.timestamps() else 0.0
        timestamp, source = self._timestamp(device_s, got.received_epoch)
        meta = {"timestamp_source": source, "device_timestamp_s": device_s, "tof_info_version": int(info.version),
                "mode": _text(info.mode), "imager": _text(info.imager),
                "measurement_block_index": int(getattr(info, "measurement_block_index", 0)),
                "confidence_bits": 8 * conf.dtype.itemsize}
        return Frame(distance=dist, xyz=xyz, amplitude=amp, valid=valid, intrinsics=self._intr, timestamp=timestamp,
                     sequence=int(f.frame_count()), confidence=conf, metadata=meta)

    def _timestamp(self, device_s: float, received: float) -> tuple[float, str]:
        """The device time if it is Unix time (within ``clock_tolerance_s`` of the receive time), else receive time."""
        if device_s and abs(device_s - received) <= self.config.clock_tolerance_s:
            return device_s, "device"
        return received, "receive"

    def _measurement_model(self) -> MeasurementModel:
        return o3r_measurement_model()

    def _intrinsics(self) -> Intrinsics:
        if self._worker is not None:
            return self._worker.intrinsics()
        if self._intr is None:
            self._capture(max(self.default_timeout_s, self.config.first_frame_timeout_s))
        assert self._intr is not None
        return self._intr

    def _info(self) -> DeviceInfo:
        if self._worker is not None:
            return self._worker.info()
        cfg = self.config
        return DeviceInfo(backend=self.backend_name, vendor="ifm electronic", model="O3R 3D head (ifm3dpy)",
                          firmware=self._firmware,
                          extra={"host": cfg.host, "port": cfg.port, "pcic_port": self._pcic_port,
                                 "trigger": cfg.trigger, "client": "ifm3dpy"})


def _missing() -> MissingDependencyError:
    return MissingDependencyError("ifm3dpy", "o3r-ifm3d")


def _text(chars: Any) -> str:
    return str(chars).split("\0", 1)[0]


def _user_to_optical(xyz_user: NDArray[np.float32], extrinsic: Any) -> NDArray[np.float32]:
    """ifm's user-frame XYZ back in the optical frame: ``R^T (p - t)``, ``R = Rx(rotX) Ry(rotY) Rz(rotZ)``."""
    from scipy.spatial.transform import Rotation

    e = extrinsic
    rot = Rotation.from_euler("XYZ", [e.rot_x, e.rot_y, e.rot_z]).as_matrix().astype(np.float32)
    shifted = xyz_user.reshape(-1, 3) - np.array([e.trans_x, e.trans_y, e.trans_z], dtype=np.float32)
    # row vectors: (R^T p^T)^T = p R
    out: NDArray[np.float32] = (shifted @ rot).reshape(xyz_user.shape).astype(np.float32)
    return out


def _intrinsics(calib: Any, width: int, height: int) -> Intrinsics:
    """OpenCV intrinsics of TOF_INFO's inverse model 1: ``cx = mx - 0.5``; ifm k1..k5 = k1, k2, p1, p2, k3."""
    p = [float(v) for v in calib.parameters]
    if int(calib.model_id) != 1 or not all(math.isfinite(v) for v in p[:10]):
        raise ProtocolError(f"o3r-ifm3d: inverse intrinsic model {int(calib.model_id)} is not a Bouguet model "
                            f"this backend maps to OpenCV")
    fx, fy, mx, my, _alpha, k1, k2, k3, k4, k5 = p[:10]
    return Intrinsics(width=width, height=height, fx=fx, fy=fy, cx=mx - 0.5, cy=my - 0.5,
                      k1=k1, k2=k2, p1=k3, p2=k4, k3=k5)
