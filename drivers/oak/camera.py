"""Luxonis OAK depth camera over ``depthai`` v3 (registered as ``oak``).

Stereo or ToF depth (uint16 mm, Z-depth) aligned to one socket, turned into radial
distance and optical-frame XYZ (metres) with the device's own calibration, with the
pixel-aligned grey image of the same capture as ``Frame.amplitude``; the measurement model
(baseline, focal length, subpixel bits, filters) read from the device (:mod:`.model`).
``depthai`` is imported only in :meth:`OakCamera._connect`, in a worker process unless
``isolate = false`` (docs/adr/0063-camera-workers.md). Design: docs/adr/0015-vendor-drivers.md.
"""

from __future__ import annotations

import contextlib
import datetime
import importlib.util
import logging
import math
import time
from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal

import numpy as np
from numpy.typing import NDArray

from cellcal.devices.base import BackendContext
from cellcal.devices.errors import (
    DeviceConnectionError,
    DeviceError,
    DeviceTimeoutError,
    MissingDependencyError,
    ProtocolError,
    UsbBackendMissingError,
)
from cellcal.devices.geometry.camera_model import pixel_grid_rays
from cellcal.devices.isolation.camera import IsolatableCamera
from cellcal.devices.measurement import UNKNOWN_MODEL, MeasurementModel
from cellcal.devices.types import DeviceInfo, Frame, Intrinsics
from cellcal.drivers._blocking import BoundedCaller
from cellcal.drivers.oak.grey import check_same_capture, grey_image
from cellcal.drivers.oak.model import stereo_model, tof_model
from cellcal.drivers.oak.usb_scan import find_usb_devices

log = logging.getLogger(__name__)

Socket = Literal["CAM_A", "CAM_B", "CAM_C", "CAM_D", "CAM_E", "CAM_F"]
MONO_STEREO_SOCKETS = ("CAM_B", "CAM_C")
DEPTH_KEY, IMAGE_KEY = "depth", "image"        # names of the two messages in a Sync group


@dataclass(frozen=True)
class OakConfig:
    """``[camera]`` section for ``backend = "oak"``.

    Attributes:
        device_id: DeviceId (MxId), IP address or USB port name; "" = first device found.
        depth_source: ``"stereo"`` (StereoDepth node) or ``"tof"`` (ToF node).
        align_socket: Socket whose viewpoint and intrinsics the depth is given in.
        width: Depth output width, pixels.
        height: Depth output height, pixels.
        fps: Frame rate, Hz.
        stereo_preset: ``StereoDepth.PresetMode`` name.
        distortion: ``"device"`` (the socket's calibrated distortion) or ``"none"``; colour and
            ToF sockets only (a rectified mono view has no distortion).
        timeout_s: Default I/O timeout, s (booting an OAK over USB takes a few seconds).
        queue_size: Host queue length, frames (oldest dropped when full).
        amplitude: ``"image"``: ``Frame.amplitude`` is the grey image of the same capture,
            pixel-aligned with the depth (see :class:`OakCamera`); ``"none"``: zeros, and
            no image crosses the link (saves USB bandwidth).
        isolate: Run depthai in a worker process, so a crash in it is an error and not the end of
            cellcal, frames through shared memory (ADR 0063); ``false`` runs it in-process, for a
            debugger and for tests that mock depthai.
    """

    device_id: str = field(default="", metadata={"max_len": 256})
    depth_source: Literal["stereo", "tof"] = "stereo"
    align_socket: Socket = "CAM_A"
    width: int = field(default=640, metadata={"ge": 16, "le": 4096})
    height: int = field(default=400, metadata={"ge": 16, "le": 4096})
    fps: float = field(default=15.0, metadata={"ge": 0.1, "le": 120})
    stereo_preset: Literal["DEFAULT", "ROBOTICS", "HIGH_DETAIL", "FAST_ACCURACY", "FAST_DENSITY",
                           "DENSITY", "ACCURACY", "FACE"] = "DEFAULT"
    distortion: Literal["device", "none"] = "device"
    timeout_s: float = field(default=10.0, metadata={"ge": 0.01, "le": 600})
    queue_size: int = field(default=4, metadata={"ge": 1, "le": 64})
    amplitude: Literal["none", "image"] = "image"
    isolate: bool = True

    def __post_init__(self) -> None:
        if self.depth_source == "stereo" and self.align_socket not in ("CAM_A", *MONO_STEREO_SOCKETS):
            raise ValueError(f"stereo depth aligns to CAM_A, CAM_B or CAM_C, not {self.align_socket}")


def depth_to_xyz(depth_mm: NDArray[Any], rays_over_z: NDArray[np.float64]
                 ) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.bool_]]:
    """Turn a Z-depth image into camera-frame points.

    Each pixel's XYZ is its unit ray through the pixel centre (from
    :func:`~cellcal.devices.geometry.camera_model.pixel_grid_rays`, lens distortion
    inverted) scaled so its z equals the depth: ``xyz = ray / ray_z * depth_z``;
    the distance is ``|xyz|`` (radial).

    Args:
        depth_mm: uint16 depth along the optical axis, millimetres, 0 = invalid, (H, W).
        rays_over_z: Pixel rays scaled to z = 1, (H, W, 3); NaN where undefined.

    Returns:
        ``(xyz_m, distance_m, valid)``: float32 (H, W, 3) and (H, W) with NaN where
        invalid, and the validity mask.
    """
    z = depth_mm.astype(np.float64) * 1e-3
    valid = (depth_mm > 0) & np.all(np.isfinite(rays_over_z), axis=2)
    xyz = rays_over_z * z[..., None]
    xyz[~valid] = np.nan
    distance = np.linalg.norm(xyz, axis=2)
    return xyz.astype(np.float32), distance.astype(np.float32), valid


class OakCamera(IsolatableCamera):
    """A Luxonis OAK stereo or ToF camera over depthai v3.

    Pipeline (built in :meth:`_connect`):

    * ``depth_source = "stereo"``: two ``dai.node.Camera`` on CAM_B / CAM_C feed a
      ``dai.node.StereoDepth`` (``build(left, right, presetMode)``). The depth is
      aligned to ``align_socket`` at ``width`` x ``height``: for a mono socket to that
      socket's *rectified* view (``setDepthAlign(DepthAlign.RECTIFIED_LEFT / _RIGHT)`` +
      ``setOutputSize``; ``setDepthAlign(socket)`` is aligned to neither the rectified
      nor the raw view, depthai-core issue #840); for a colour socket by linking that
      camera's ``requestOutput((width, height))`` to ``stereo.inputAlignTo`` (RVC2) or
      through a ``dai.node.ImageAlign`` (RVC4).
    * ``depth_source = "tof"``: a ``dai.node.ToF`` built on ``align_socket``.

    Depth arrives as uint16 millimetres along the optical axis (Z-depth, not radial),
    0 = invalid; :func:`depth_to_xyz` makes XYZ and radial distance of it. Intrinsics
    come from the device's own calibration at the output size: for a colour or ToF
    socket ``readCalibration().getCameraIntrinsics(socket, w, h)`` and
    ``getDistortionCoefficients(socket)`` (14 OpenCV rational terms); with
    ``distortion = "none"`` the outputs are requested undistorted (colour camera
    ``enableUndistortion``, ToF ``setOutputUndistortion``) and the coefficients are
    dropped. Fisheye-calibrated colour / ToF sockets need ``distortion = "none"``. A
    rectified mono view is undistorted, and depthai rectifies both sides onto the
    stereo right camera's matrix (rectification homography ``K_right · R · K⁻¹``,
    ``CalibrationHandler.setStereoLeft/Right``), so its intrinsics are
    ``getCameraIntrinsics(getStereoRightCameraId(), w, h)`` with no distortion, and its
    optical frame is the rectified one (the sensor's, turned by the rectification
    rotation ``R``).

    ``amplitude = "image"`` (default) adds the grey image of the same capture,
    pixel-aligned with the depth, as ``Frame.amplitude`` (float32; see
    :func:`~cellcal.drivers.oak.grey.grey_image` for the units):

    * mono socket: the StereoDepth ``rectifiedLeft`` / ``rectifiedRight`` output
      matching it, brought to ``width`` x ``height`` by a ``dai.node.ImageManip``
      (``CENTER_CROP``, as ``setOutputSize`` scales the depth); grey levels 0..255;
    * colour socket: the luma (Y) plane of the very ``NV12`` output the depth is aligned
      to; grey levels 0..255;
    * ToF: the ToF node's ``amplitude`` output; raw amplitude counts.

    Depth and image meet in a ``dai.node.Sync`` (threshold half a frame period) and
    reach the host as one ``MessageGroup``. The host still checks that they belong to
    one capture — equal sequence numbers where both come from one sensor frame
    (rectified mono, ToF), capture times within the threshold where they come from two
    sensors (colour) — and raises :class:`~cellcal.devices.errors.FrameSyncError`
    otherwise; a depth without its image within the timeout is a
    :class:`DeviceTimeoutError` like a missing depth.

    Measurement model: ToF depth states ``tof`` at any time; stereo depth states ``stereo``
    once connected (before: ``unknown``), read from the device by
    :func:`~cellcal.drivers.oak.model.stereo_model` — the baseline depthai converts
    disparity with, the rectified right camera's focal length at the matching resolution,
    the subpixel fractional bits and the filters of the StereoDepth node's config after its
    preset. A device reporting an unusable value (a baseline of 0, NaN, 2 m) fails
    ``connect`` with a one-line :class:`DeviceError` naming it, unless a ``[camera.model]``
    table states the model instead (then it is logged).

    Timeouts: ``dai.Device(...)`` (search and boot) and ``Pipeline.start()`` (pipeline
    upload) take no timeout parameter, so both run in a
    :class:`~cellcal.drivers._blocking.BoundedCaller` worker joined with the connect
    timeout. Every queue read is ``MessageQueue.get(timedelta)`` (None on timeout). A
    closed queue or a closed device means the device is gone: :class:`DeviceConnectionError`.

    With ``isolate = true`` (the default) all of the above runs in a worker process
    (:class:`~cellcal.devices.isolation.camera.IsolatableCamera`); a crash of depthai there is a
    :class:`~cellcal.devices.errors.NativeCrashError` and ``connect()`` starts a new worker.
    """

    backend_name: ClassVar[str] = "oak"
    native_library: ClassVar[str] = "depthai"
    Config: ClassVar[type[OakConfig]] = OakConfig

    def __init__(self, config: OakConfig, context: BackendContext | None = None):
        super().__init__()
        self.config = config
        self.context = context or BackendContext()
        self.default_timeout_s = config.timeout_s
        self._caller = BoundedCaller(f"oak {config.device_id or '(first)'}")
        self._dai: Any = None
        self._device: Any = None
        self._pipeline: Any = None
        self._queue: Any = None
        self._intr: Intrinsics | None = None
        self._rays_over_z: NDArray[np.float64] | None = None
        self._clock_offset_s = 0.0
        self._identity: dict[str, str] = {}
        self._stereo_config: Any = None
        self._model: MeasurementModel = tof_model() if config.depth_source == "tof" else UNKNOWN_MODEL

    # ------------------------------------------------------------ discovery
    @classmethod
    def unavailable_reason(cls) -> str | None:
        """None if depthai can be imported; else the install hint (no import of depthai here)."""
        if importlib.util.find_spec("depthai") is not None:
            return None
        return str(MissingDependencyError("depthai", "oak"))

    @classmethod
    def discover(cls, timeout: float = 2.0) -> list[DeviceInfo] | None:
        """OAK devices reachable now: from depthai, else from USB enumeration (pyusb).

        ``dai.Device.getAllAvailableDevices()`` first; where depthai is absent or finds
        nothing, USB vendor 0x03E7 through ``pyusb`` (:mod:`cellcal.drivers.oak.usb_scan`),
        the boot state named from the product id.

        Raises:
            MissingDependencyError: If neither depthai nor pyusb with libusb is available.
        """
        found: list[DeviceInfo] = []
        depthai_missing = False
        try:
            import depthai as dai
        except ImportError:
            depthai_missing = True
        else:
            caller = BoundedCaller("oak discovery")
            try:
                infos = caller.call(dai.Device.getAllAvailableDevices, timeout, "list devices")
            except DeviceTimeoutError:
                log.warning("oak: depthai device search did not finish within %g s", timeout)
                infos = []
            for info in infos:
                found.append(DeviceInfo(
                    backend="oak", vendor="Luxonis", model=str(info.platform.name), serial=str(info.deviceId),
                    extra={"name": str(info.name), "state": str(info.state.name),
                           "protocol": str(info.protocol.name), "source": "depthai"}))
        if found:
            return found
        try:
            usb_devices = find_usb_devices()
        except (MissingDependencyError, UsbBackendMissingError) as exc:
            if depthai_missing:
                raise MissingDependencyError(f"depthai (and USB scanning is unavailable: {exc})", "oak") from None
            return found
        return [DeviceInfo(backend="oak", vendor="Intel Movidius / Luxonis", model=f"USB {d.vendor_id:04x}:"
                           f"{d.product_id:04x}", serial=f"usb {d.bus}-{d.port_path or d.address}",
                           extra={"state": d.state, "bus": d.bus, "address": d.address, "source": "pyusb"})
                for d in usb_devices]

    # ------------------------------------------------------------ life cycle
    def _connect(self, timeout: float) -> None:
        if self.config.isolate:
            if self.unavailable_reason() is not None:  # said here, before a worker is started for nothing
                raise MissingDependencyError("depthai", "oak")
            self._start_worker(f"oak {self.config.device_id or '(first)'}", timeout, self.config.timeout_s)
            return
        try:
            import depthai as dai
        except ImportError:
            raise MissingDependencyError("depthai", "oak") from None
        self._dai = dai
        cfg = self.config
        deadline = time.monotonic() + timeout
        who = cfg.device_id or "the first OAK device"

        def open_device() -> Any:
            return dai.Device(dai.DeviceInfo(cfg.device_id)) if cfg.device_id else dai.Device()

        try:
            self._device = self._caller.call(open_device, timeout, f"open {who}", on_late=lambda d: d.close())
        except RuntimeError as exc:
            hint = " (on Linux, check the udev rules for vendor 03e7)" if "NOT_FOUND" in str(exc).upper() else ""
            raise DeviceConnectionError(f"oak: cannot open {who}: {exc}{hint}") from None
        device = self._device
        self._identity = {"id": str(device.getDeviceId()), "platform": str(device.getPlatformAsString()),
                          "product": str(device.getProductName() or "")}
        socket = getattr(dai.CameraBoardSocket, cfg.align_socket)
        calib = device.readCalibration()
        self._intr = self._read_intrinsics(calib, socket)
        rays = pixel_grid_rays(self._intr)
        self._rays_over_z = rays / rays[..., 2:3]
        self._pipeline = dai.Pipeline(device)
        depth_out, image_out = self._build_graph(self._pipeline, socket)
        if cfg.depth_source == "stereo":
            self._read_model(calib)
        self._queue = self._output_queue(self._pipeline, depth_out, image_out)
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise DeviceTimeoutError(f"oak: no time left to start the pipeline on {who}")
        try:
            self._caller.call(self._pipeline.start, remaining, "start the pipeline")
        except RuntimeError as exc:
            raise DeviceConnectionError(f"oak {self._identity['id']}: pipeline failed to start: {exc}") from None
        self._clock_offset_s = time.time() - dai.Clock.now().total_seconds()

    def _build_graph(self, pipeline: Any, socket: Any) -> tuple[Any, Any]:
        """Create the nodes; return the depth output and the image output (None if not wanted)."""
        dai, cfg = self._dai, self.config
        want_image = cfg.amplitude == "image"
        if cfg.depth_source == "tof":
            tof = pipeline.create(dai.node.ToF).build(socket, fps=cfg.fps)
            tof.setOutputUndistortion(cfg.distortion == "none")
            return tof.depth, (tof.amplitude if want_image else None)
        left = pipeline.create(dai.node.Camera).build(dai.CameraBoardSocket.CAM_B)
        right = pipeline.create(dai.node.Camera).build(dai.CameraBoardSocket.CAM_C)
        preset = getattr(dai.node.StereoDepth.PresetMode, cfg.stereo_preset)
        stereo = pipeline.create(dai.node.StereoDepth).build(
            left.requestFullResolutionOutput(fps=cfg.fps), right.requestFullResolutionOutput(fps=cfg.fps),
            presetMode=preset)
        self._stereo_config = stereo.initialConfig            # the preset's settings: the model reads them
        if cfg.align_socket in MONO_STEREO_SOCKETS:
            return stereo.depth, self._align_to_rectified(pipeline, stereo, want_image)
        depth_out, color_out = self._align_to_colour(pipeline, stereo, socket)
        return depth_out, (color_out if want_image else None)

    def _align_to_rectified(self, pipeline: Any, stereo: Any, want_image: bool) -> Any:
        """Depth in the aligned mono socket's rectified view; that view resized to the output size."""
        dai, cfg = self._dai, self.config
        align = dai.StereoDepthConfig.AlgorithmControl.DepthAlign
        is_left = cfg.align_socket == "CAM_B"
        stereo.setDepthAlign(align.RECTIFIED_LEFT if is_left else align.RECTIFIED_RIGHT)
        stereo.setOutputSize(cfg.width, cfg.height)
        if not want_image:
            return None
        manip = pipeline.create(dai.node.ImageManip)
        manip.initialConfig.setOutputSize(cfg.width, cfg.height, dai.ImageManipConfig.ResizeMode.CENTER_CROP)
        manip.setMaxOutputFrameSize(cfg.width * cfg.height)          # one byte per grey pixel
        (stereo.rectifiedLeft if is_left else stereo.rectifiedRight).link(manip.inputImage)
        return manip.out

    def _align_to_colour(self, pipeline: Any, stereo: Any, socket: Any) -> tuple[Any, Any]:
        """Depth aligned to the colour socket's NV12 output; return the depth output and that output."""
        dai, cfg = self._dai, self.config
        color = pipeline.create(dai.node.Camera).build(socket)
        color_out = color.requestOutput((cfg.width, cfg.height), type=dai.ImgFrame.Type.NV12, fps=cfg.fps,
                                        enableUndistortion=cfg.distortion == "none")
        if self._device.getPlatform() == dai.Platform.RVC4:
            align = pipeline.create(dai.node.ImageAlign)
            stereo.depth.link(align.input)
            color_out.link(align.inputAlignTo)
            return align.outputAligned, color_out
        color_out.link(stereo.inputAlignTo)
        return stereo.depth, color_out

    def _output_queue(self, pipeline: Any, depth_out: Any, image_out: Any) -> Any:
        """The host queue: plain depth frames, or depth + image groups from a ``dai.node.Sync``."""
        dai, cfg = self._dai, self.config
        if image_out is None:
            return depth_out.createOutputQueue(maxSize=cfg.queue_size, blocking=False)
        sync = pipeline.create(dai.node.Sync)
        sync.setSyncThreshold(datetime.timedelta(seconds=self._max_pair_dt_s))
        depth_out.link(sync.inputs[DEPTH_KEY])
        image_out.link(sync.inputs[IMAGE_KEY])
        return sync.out.createOutputQueue(maxSize=cfg.queue_size, blocking=False)

    def _read_model(self, calib: Any) -> None:
        """Read the stereo model from the device (see :mod:`.model`); a bad value fails unless overridden."""
        try:
            self._model = stereo_model(self._device, calib, self._stereo_config, self.config.stereo_preset,
                                       self._identity.get("id", ""))
        except DeviceError as exc:
            if self.measurement_override is None:
                raise
            self._model = UNKNOWN_MODEL
            log.warning("%s; using the [camera.model] table", exc)

    def _measurement_model(self) -> MeasurementModel:
        if self._worker is not None and self._worker.model is not None:
            return self._worker.model
        return self._model

    def _read_intrinsics(self, calib: Any, socket: Any) -> Intrinsics:
        dai, cfg = self._dai, self.config
        if cfg.depth_source == "stereo" and cfg.align_socket in MONO_STEREO_SOCKETS:
            return self._rectified_intrinsics(calib)
        try:
            k = calib.getCameraIntrinsics(socket, cfg.width, cfg.height)
            coeffs: list[float] = []
            if cfg.distortion == "device":
                model = calib.getDistortionModel(socket)
                if model != dai.CameraModel.Perspective:
                    raise DeviceError(f"oak: {cfg.align_socket} is calibrated with the {model.name} model; "
                                      "set distortion = \"none\" (undistorted output)")
                coeffs = list(calib.getDistortionCoefficients(socket))
        except RuntimeError as exc:
            raise DeviceError(f"oak: no calibration for {cfg.align_socket}: {exc}") from None
        return Intrinsics.from_opencv(cfg.width, cfg.height, k, coeffs)

    def _rectified_intrinsics(self, calib: Any) -> Intrinsics:
        """A rectified mono view: the stereo right camera's matrix at the output size, no distortion."""
        cfg = self.config
        try:
            k = calib.getCameraIntrinsics(calib.getStereoRightCameraId(), cfg.width, cfg.height)
        except RuntimeError as exc:
            raise DeviceError(f"oak: no stereo calibration for the rectified {cfg.align_socket} view: {exc}") from None
        return Intrinsics.from_opencv(cfg.width, cfg.height, k, [])

    def _close(self) -> None:
        self._stop_worker()
        for action in (lambda: self._pipeline.stop(), lambda: self._queue.close(), lambda: self._device.close()):
            with contextlib.suppress(Exception):
                action()
        self._pipeline = self._queue = self._device = None
        self._caller.join(2.0)

    def _info(self) -> DeviceInfo:
        if self._worker is not None:
            return self._worker.info()
        return DeviceInfo(backend="oak", vendor="Luxonis", model=self._identity.get("product") or
                          self._identity.get("platform", "OAK"), serial=self._identity.get("id", ""),
                          extra={"platform": self._identity.get("platform", ""),
                                 "depth_source": self.config.depth_source, "socket": self.config.align_socket})

    def _intrinsics(self) -> Intrinsics:
        if self._worker is not None:
            return self._worker.intrinsics()
        assert self._intr is not None
        return self._intr

    # ------------------------------------------------------------ capture
    @property
    def _max_pair_dt_s(self) -> float:
        """Largest capture-time difference of a depth / image pair: half a frame period, s."""
        return 0.5 / self.config.fps

    def _capture(self, timeout: float) -> Frame:
        if self._worker is not None:
            return self._worker.capture(timeout)
        dai = self._dai
        gone = (RuntimeError, dai.MessageQueue.QueueException)
        what = "depth frame" if self.config.amplitude == "none" else "depth + image pair"
        try:
            if self._device.isClosed():
                raise DeviceConnectionError(f"oak {self._identity.get('id', '')}: device disconnected")
            now = dai.Clock.now().total_seconds()
            # Frames queued earlier are used only if younger than the timeout.
            queued = [m for m in self._queue.tryGetAll() if m is not None]
            newest_s = self._depth_of(queued[-1]).getTimestamp().total_seconds() if queued else -math.inf
            msg = queued[-1] if now - newest_s <= timeout else None
            if msg is None:
                msg = self._queue.get(datetime.timedelta(seconds=timeout))
        except gone as exc:
            raise DeviceConnectionError(f"oak {self._identity.get('id', '')}: device disconnected ({exc})") from None
        if msg is None:
            raise DeviceTimeoutError(f"oak: no {what} within {timeout:g} s")
        return self._to_frame(msg)

    def _depth_of(self, msg: Any) -> Any:
        """The depth ``ImgFrame`` of a queued message (itself, or the depth of a Sync group)."""
        if self.config.amplitude == "none":
            return msg
        if not isinstance(msg, self._dai.MessageGroup) or DEPTH_KEY not in msg.getMessageNames():
            raise ProtocolError(f"oak: expected a depth + image group, got {type(msg).__name__}")
        return msg[DEPTH_KEY]

    def _image_of(self, group: Any, depth: Any, shape: tuple[int, int]) -> NDArray[np.float32]:
        """The group's grey image as float32, after checking it belongs to the depth's capture."""
        if IMAGE_KEY not in group.getMessageNames():
            raise ProtocolError(f"oak: depth + image group has no image (got {group.getMessageNames()})")
        image = group[IMAGE_KEY]
        colour = self.config.depth_source == "stereo" and self.config.align_socket not in MONO_STEREO_SOCKETS
        check_same_capture(depth, image, "time" if colour else "sequence", self._max_pair_dt_s)
        return grey_image(image, shape)

    def _to_frame(self, msg: Any) -> Frame:
        intr = self._intrinsics()
        assert self._rays_over_z is not None
        depth_msg = self._depth_of(msg)
        depth = np.asarray(depth_msg.getFrame())
        if depth.dtype != np.uint16 or depth.shape != intr.shape:
            raise ProtocolError(f"oak: depth frame is {depth.dtype} {depth.shape}, expected uint16 {intr.shape}")
        amplitude = (np.zeros(intr.shape, dtype=np.float32) if self.config.amplitude == "none"
                     else self._image_of(msg, depth_msg, intr.shape))
        xyz, distance, valid = depth_to_xyz(depth, self._rays_over_z)
        return Frame(distance=distance, xyz=xyz, amplitude=amplitude, valid=valid, intrinsics=intr,
                     timestamp=self._clock_offset_s + depth_msg.getTimestamp().total_seconds(),
                     sequence=int(depth_msg.getSequenceNum()))
