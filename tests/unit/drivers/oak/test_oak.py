"""OAK backend over depthai v3, mocked at the library boundary.

Real depthai objects are used where they work without hardware: the host-side
``dai.MessageQueue`` the backend reads (with its real timeout and close semantics),
``dai.ImgFrame`` depth messages, ``dai.CalibrationHandler`` (its own intrinsics
scaling) and ``dai.DeviceInfo``. The device, pipeline and nodes are strict autospecs
of the real classes (signatures parsed from the pybind11 docstrings).
"""

from __future__ import annotations

import datetime
import sys
import threading
import time
from typing import Any
from unittest import mock

import numpy as np
import pytest

dai = pytest.importorskip("depthai")
from _vendor_autospec import strict_autospec  # noqa: E402

from cellcal.devices.base import BackendContext  # noqa: E402
from cellcal.devices.errors import (  # noqa: E402
    ConfigError,
    DeviceConnectionError,
    DeviceTimeoutError,
    FrameSyncError,
    MissingDependencyError,
    ProtocolError,
)
from cellcal.devices.geometry.camera_model import project  # noqa: E402
from cellcal.devices.registry import default_registry  # noqa: E402
from cellcal.devices.types import Intrinsics  # noqa: E402
from cellcal.drivers.oak import usb_scan  # noqa: E402
from cellcal.drivers.oak.camera import OakCamera  # noqa: E402
from cellcal.drivers.oak.grey import grey_image  # noqa: E402

REAL_DEVICE = dai.Device
REAL_PIPELINE = dai.Pipeline
DEVICE_ID = "14442C10D13EABCE00"
W, H = 64, 40
CAL_K = [[800.0, 0.0, 639.5], [0.0, 802.0, 401.0], [0.0, 0.0, 1.0]]   # at 1280 x 800
CAL_D = [0.12, -0.21, 0.0012, -0.0008, 0.05, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
RIGHT_K = [[790.0, 0.0, 650.5], [0.0, 791.0, 398.5], [0.0, 0.0, 1.0]]  # stereo right camera, at 1280 x 800
LEFT_K = [[810.0, 0.0, 630.0], [0.0, 811.0, 405.0], [0.0, 0.0, 1.0]]


BASELINE_CM = 7.5                                                     # design (spec) translation, as depthai stores it
MONO_SIZE = (1280, 800)                                               # the stereo sensors' full resolution


def calibration(right_k: list[list[float]] = RIGHT_K, size: tuple[int, int] = MONO_SIZE,
                spec_cm: float = BASELINE_CM, measured_cm: float = 7.46) -> Any:
    """A real CalibrationHandler as an OAK-D's EEPROM holds it: intrinsics, stereo pair, left-to-right extrinsics."""
    calib = dai.CalibrationHandler()
    calib.setCameraIntrinsics(dai.CameraBoardSocket.CAM_A, CAL_K, 1280, 800)
    calib.setDistortionCoefficients(dai.CameraBoardSocket.CAM_A, CAL_D)
    calib.setCameraIntrinsics(dai.CameraBoardSocket.CAM_B, LEFT_K, *size)
    calib.setCameraIntrinsics(dai.CameraBoardSocket.CAM_C, right_k, *size)
    calib.setCameraExtrinsics(dai.CameraBoardSocket.CAM_B, dai.CameraBoardSocket.CAM_C, np.eye(3).tolist(),
                              [-measured_cm, 0.0, 0.0], [-spec_cm, 0.0, 0.0])
    calib.setStereoLeft(dai.CameraBoardSocket.CAM_B, np.eye(3).tolist())
    calib.setStereoRight(dai.CameraBoardSocket.CAM_C, np.eye(3).tolist())
    return calib


def camera_features(size: tuple[int, int] = MONO_SIZE) -> list[Any]:
    """``Device.getConnectedCameraFeatures()`` of an OAK-D: colour CAM_A, mono CAM_B / CAM_C of ``size``."""
    out = []
    for socket, (w, h) in (("CAM_A", (1920, 1080)), ("CAM_B", size), ("CAM_C", size)):
        f = dai.CameraFeatures()
        f.socket, f.width, f.height = getattr(dai.CameraBoardSocket, socket), w, h
        out.append(f)
    return out


def apply_rvc2_preset(config: Any, preset: Any) -> None:
    """What depthai-core's ``StereoDepth::setRvc2ProfilePreset`` sets of the fields the model reads."""
    name = preset.name
    config.setLeftRightCheck(True)
    if name in ("DEFAULT", "ROBOTICS"):
        config.setExtendedDisparity(False)
        config.setSubpixel(True)
        config.setSubpixelFractionalBits(3)
        config.setMedianFilter(dai.StereoDepthConfig.MedianFilter.KERNEL_7x7)
    elif name in ("FACE", "HIGH_DETAIL"):
        config.setExtendedDisparity(True)
        config.setSubpixel(True)
        config.setSubpixelFractionalBits(5)
        config.setMedianFilter(dai.StereoDepthConfig.MedianFilter.MEDIAN_OFF)


def depth_message(depth_mm: np.ndarray, seq: int) -> Any:
    f = dai.ImgFrame()
    f.setType(dai.ImgFrame.Type.RAW16)
    f.setWidth(depth_mm.shape[1])
    f.setHeight(depth_mm.shape[0])
    f.setFrame(depth_mm)
    f.setSequenceNum(seq)
    f.setTimestamp(dai.Clock.now())
    return f


def image_message(kind: str, pixels: np.ndarray, seq: int, stride: int | None = None) -> Any:
    """An ImgFrame as the device sends it: GRAY8 / RAW8 / RAW16 pixels, or NV12 with ``pixels`` as luma.

    ``stride`` pads each row of the first plane to that many bytes (as the device's ISP does).
    """
    h, w = pixels.shape
    bpp = pixels.dtype.itemsize
    stride = stride or w * bpp
    plane = np.full((h, stride), 0xEE, np.uint8)                   # padding bytes: never read as pixels
    plane[:, :w * bpp] = np.ascontiguousarray(pixels).view(np.uint8).reshape(h, w * bpp)
    data = plane.ravel()
    if kind == "NV12":
        data = np.concatenate([data, np.full(stride * h // 2, 128, np.uint8)])   # chroma plane
    f = dai.ImgFrame()
    f.setType(getattr(dai.ImgFrame.Type, kind))
    f.setWidth(w)
    f.setHeight(h)
    f.setStride(stride)
    f.setData(data)
    f.setSequenceNum(seq)
    f.setTimestamp(dai.Clock.now())
    return f


class FakeSyncQueue(dai.MessageQueue):  # type: ignore[misc]
    """The host queue of a ``dai.node.Sync``: the device-side grouping emulated on each read.

    Messages sent to the outputs linked into the node's inputs are paired like the real
    node does: the oldest head of each input is grouped when all heads lie within the
    configured threshold, otherwise the oldest head is dropped.
    """

    def __init__(self, fake: FakeOak, node: Any, max_size: int):
        super().__init__("sync", max_size, False)
        self.fake, self.node = fake, node
        self.pending: dict[str, list[Any]] = {name: [] for name in node.inputs}

    def _pump(self) -> None:
        threshold = self.node.setSyncThreshold.call_args.args[0].total_seconds()
        for name, inp in self.node.inputs.items():
            source = self.fake.source_linked_to(inp)
            if source is not None:
                self.pending[name] += [m for m in source.tryGetAll() if m is not None]
        while all(self.pending.values()):
            heads = {name: msgs[0] for name, msgs in self.pending.items()}
            stamps = {name: m.getTimestamp().total_seconds() for name, m in heads.items()}
            if max(stamps.values()) - min(stamps.values()) <= threshold:
                group = dai.MessageGroup()
                for name, m in heads.items():
                    group[name] = m
                    self.pending[name].pop(0)
                self.send(group)
            else:
                self.pending[min(stamps, key=lambda k: stamps[k])].pop(0)

    def tryGetAll(self) -> list[Any]:  # noqa: N802 - depthai's name
        self._pump()
        return list(super().tryGetAll())

    def get(self, timeout: datetime.timedelta) -> Any:
        self._pump()
        return super().get(timeout)


class FakeOak:
    """Device + pipeline graph; each node output has its own real host MessageQueue."""

    def __init__(self) -> None:
        self.device = strict_autospec(REAL_DEVICE)
        self.device.getDeviceId.return_value = DEVICE_ID
        self.device.getPlatformAsString.return_value = "RVC2"
        self.device.getProductName.return_value = "OAK-D-PRO"
        self.device.getPlatform.return_value = dai.Platform.RVC2
        self.device.isClosed.return_value = False
        self.device.readCalibration.return_value = calibration()
        self.device.getConnectedCameraFeatures.return_value = camera_features()
        #: Run on the StereoDepth node's config after its preset (a test's own stereo settings).
        self.stereo_settings: Any = None
        self.opened_with: list[Any] = []
        self.nodes: list[Any] = []
        self.outputs: list[Any] = []
        self.sources: dict[int, Any] = {}
        self.sync_queue: FakeSyncQueue | None = None
        self.pipeline = strict_autospec(REAL_PIPELINE)
        self.pipeline.create.side_effect = self.create

    def open(self, *args: Any) -> Any:
        self.opened_with.append(args)
        return self.device

    def make_pipeline(self, device: Any) -> Any:
        assert device is self.device
        return self.pipeline

    def output(self) -> Any:
        out = strict_autospec(dai.Node.Output)
        out.createOutputQueue.return_value = dai.MessageQueue("out", 8, False)
        return out

    def _output(self) -> Any:
        out = self.output()
        self.outputs.append(out)
        return out

    def create(self, node_cls: Any, *args: Any, **kwargs: Any) -> Any:
        node = strict_autospec(node_cls)
        if hasattr(node_cls, "build"):
            node.build.return_value = node
        if node_cls is dai.node.Camera:
            node.requestOutput.return_value = self._output()
            node.requestFullResolutionOutput.return_value = self._output()
        if node_cls is dai.node.StereoDepth:
            node.depth, node.rectifiedLeft, node.rectifiedRight = self._output(), self._output(), self._output()
            node.inputAlignTo = strict_autospec(dai.Node.Input)
            node.initialConfig = dai.StereoDepthConfig()           # the real config message
            check_overloads = node.build.side_effect

            def build(*args: Any, **kwargs: Any) -> Any:           # the device applies the preset in build()
                result = check_overloads(*args, **kwargs)
                apply_rvc2_preset(node.initialConfig, kwargs.get("presetMode", dai.node.StereoDepth.PresetMode.DEFAULT))
                if self.stereo_settings is not None:
                    self.stereo_settings(node.initialConfig)
                return result

            node.build.side_effect = build
        if node_cls is dai.node.ToF:
            node.depth, node.amplitude = self._output(), self._output()
        if node_cls is dai.node.ImageAlign:
            node.input, node.inputAlignTo = strict_autospec(dai.Node.Input), strict_autospec(dai.Node.Input)
            node.outputAligned = self._output()
        if node_cls is dai.node.ImageManip:
            node.initialConfig = strict_autospec(dai.ImageManipConfig)
            node.inputImage = strict_autospec(dai.Node.Input)
            node.out = self._output()
        if node_cls is dai.node.Sync:
            node.inputs = {"depth": strict_autospec(dai.Node.Input), "image": strict_autospec(dai.Node.Input)}
            node.out = strict_autospec(dai.Node.Output)
            node.out.createOutputQueue.side_effect = lambda maxSize=16, blocking=False: self._sync_queue(
                node, maxSize)
        self.nodes.append(node)
        return node

    def _sync_queue(self, node: Any, max_size: int) -> FakeSyncQueue:
        self.sync_queue = FakeSyncQueue(self, node, max_size)
        return self.sync_queue

    def nodes_of(self, node_cls: Any) -> list[Any]:
        return [n for n in self.nodes if n._spec_class.__name__ == node_cls.__name__]

    def source_linked_to(self, inp: Any) -> Any:
        """The device-side stream of the output the driver linked to ``inp`` (None if none is)."""
        for out in self.outputs:
            if any(c.args == (inp,) for c in out.link.call_args_list):
                if id(out) not in self.sources:
                    self.sources[id(out)] = out.createOutputQueue(maxSize=8, blocking=False)
                return self.sources[id(out)]
        return None

    # What the tests send, and where.
    @property
    def queue(self) -> Any:
        """The host queue the driver reads: the Sync node's, else the depth output's."""
        if self.sync_queue is not None:
            return self.sync_queue
        (out,) = [o for o in self.outputs if o.createOutputQueue.called]
        return out.createOutputQueue.return_value

    def send_depth(self, msg: Any) -> None:
        if self.sync_queue is None:
            self.queue.send(msg)
        else:
            self.source_linked_to(self.sync_queue.node.inputs["depth"]).send(msg)

    def send_image(self, msg: Any) -> None:
        assert self.sync_queue is not None
        self.source_linked_to(self.sync_queue.node.inputs["image"]).send(msg)


@pytest.fixture
def oak(mocker: Any) -> FakeOak:
    fake = FakeOak()
    mocker.patch.object(dai, "Device", side_effect=fake.open)
    mocker.patch.object(dai, "Pipeline", side_effect=fake.make_pipeline)
    return fake


def connected(**config: Any) -> Any:
    cam = OakCamera.from_config({"backend": "oak", "device_id": DEVICE_ID, "width": W, "height": H, **config})
    cam.connect(timeout=5.0)
    return cam


@pytest.fixture
def camera(oak: FakeOak) -> Any:
    cam = connected()
    yield cam
    cam.close()


def test_connect_selects_device_and_reads_its_intrinsics(camera: OakCamera, oak: FakeOak) -> None:
    (args,) = oak.opened_with
    assert isinstance(args[0], dai.DeviceInfo) and args[0].deviceId == DEVICE_ID
    intr = camera.intrinsics
    scaled = calibration().getCameraIntrinsics(dai.CameraBoardSocket.CAM_A, W, H)
    assert (intr.width, intr.height) == (W, H)
    assert intr.fx == pytest.approx(scaled[0][0]) and intr.cy == pytest.approx(scaled[1][2])
    assert intr.fx == pytest.approx(800.0 * W / 1280, rel=1e-6)   # the device's own scaling
    assert intr.k1 == pytest.approx(0.12, rel=1e-6) and intr.p2 == pytest.approx(-0.0008, rel=1e-5)
    oak.pipeline.start.assert_called_once_with()
    (stereo,) = oak.nodes_of(dai.node.StereoDepth)
    (sync,) = oak.nodes_of(dai.node.Sync)
    color = oak.nodes_of(dai.node.Camera)[-1]
    color.build.assert_called_once_with(dai.CameraBoardSocket.CAM_A)
    color.requestOutput.assert_called_once_with((W, H), type=dai.ImgFrame.Type.NV12, fps=15.0,
                                                enableUndistortion=False)
    # the colour output is both what the depth is aligned to and the image paired with it
    color_out = color.requestOutput.return_value
    assert color_out.link.call_args_list == [mock.call(stereo.inputAlignTo), mock.call(sync.inputs["image"])]
    stereo.depth.link.assert_called_once_with(sync.inputs["depth"])
    sync.setSyncThreshold.assert_called_once_with(datetime.timedelta(seconds=0.5 / 15.0))
    assert not oak.nodes_of(dai.node.ImageManip)
    assert camera.info().serial == DEVICE_ID


def test_depth_image_to_xyz_agrees_with_core_camera_model(camera: OakCamera, oak: FakeOak) -> None:
    rng = np.random.default_rng(3)
    depth = rng.integers(300, 4000, size=(H, W)).astype(np.uint16)
    depth[5, 7] = depth[20, 33] = 0                     # invalid pixels
    luma = rng.integers(0, 256, size=(H, W)).astype(np.uint8)
    oak.send_depth(depth_message(depth, seq=41))
    oak.send_image(image_message("NV12", luma, seq=77, stride=W + 32))   # another sensor: own sequence
    frame = camera.capture(timeout=1.0)
    assert frame.sequence == 41 and frame.shape == (H, W)
    # the amplitude is the colour frame's luma plane, grey levels as float32, padding skipped
    assert frame.amplitude.dtype == np.float32
    np.testing.assert_array_equal(frame.amplitude, luma.astype(np.float32))
    valid = depth > 0
    np.testing.assert_array_equal(frame.valid, valid)
    assert np.isnan(frame.xyz[5, 7]).all() and np.isnan(frame.distance[20, 33])
    # z is the depth (metres), the distance is radial
    np.testing.assert_allclose(frame.xyz[..., 2][valid], depth[valid] * 1e-3, atol=1e-6)
    np.testing.assert_allclose(frame.distance[valid], np.linalg.norm(frame.xyz, axis=2)[valid], atol=1e-6)
    assert np.all(frame.distance[valid] > frame.xyz[..., 2][valid] - 1e-7)
    # projected back through the distorted lens model, every point lands on its pixel centre
    vv, uu = np.nonzero(valid)
    uv = project(frame.intrinsics, frame.xyz[valid].astype(np.float64))
    np.testing.assert_allclose(uv[:, 0], uu, atol=2e-4)
    np.testing.assert_allclose(uv[:, 1], vv, atol=2e-4)
    # the distortion really matters at the corner: a pinhole model would put it elsewhere
    pinhole = Intrinsics(W, H, frame.intrinsics.fx, frame.intrinsics.fy, frame.intrinsics.cx, frame.intrinsics.cy)
    corner = project(pinhole, frame.xyz[0, 0].astype(np.float64))
    assert np.hypot(*(corner[0] - [0, 0])) > 0.5


def test_rvc4_pairs_the_image_align_output_with_the_colour_image(oak: FakeOak) -> None:
    oak.device.getPlatform.return_value = dai.Platform.RVC4
    with connected() as cam:
        (stereo,) = oak.nodes_of(dai.node.StereoDepth)
        (align,) = oak.nodes_of(dai.node.ImageAlign)
        (sync,) = oak.nodes_of(dai.node.Sync)
        color_out = oak.nodes_of(dai.node.Camera)[-1].requestOutput.return_value
        stereo.depth.link.assert_called_once_with(align.input)
        assert color_out.link.call_args_list == [mock.call(align.inputAlignTo), mock.call(sync.inputs["image"])]
        align.outputAligned.link.assert_called_once_with(sync.inputs["depth"])
        luma = np.tile(np.arange(W, dtype=np.uint8) * 3, (H, 1))
        oak.send_depth(depth_message(np.full((H, W), 800, np.uint16), seq=2))
        oak.send_image(image_message("NV12", luma, seq=900))
        frame = cam.capture(timeout=1.0)
    np.testing.assert_array_equal(frame.amplitude, luma.astype(np.float32))


def test_empty_depth_queue_times_out(camera: OakCamera) -> None:
    with pytest.raises(DeviceTimeoutError, match=r"no depth \+ image pair within 0\.05 s"):
        camera.capture(timeout=0.05)


def test_depth_without_its_image_times_out_bounded(camera: OakCamera, oak: FakeOak) -> None:
    oak.send_depth(depth_message(np.full((H, W), 900, np.uint16), seq=3))
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeoutError, match=r"no depth \+ image pair within 0\.2 s"):
        camera.capture(timeout=0.2)
    assert 0.15 < time.monotonic() - t0 < 3.0  # its 0.2 s (with room for a busy machine)


def test_colour_image_captured_too_far_apart_is_refused(camera: OakCamera, oak: FakeOak) -> None:
    depth = depth_message(np.full((H, W), 900, np.uint16), seq=3)
    image = image_message("NV12", np.zeros((H, W), np.uint8), seq=3)
    image.setTimestamp(depth.getTimestamp() + datetime.timedelta(seconds=0.06))   # threshold: 33.3 ms
    group = dai.MessageGroup()                          # a group the device's Sync should never have sent
    group["depth"], group["image"] = depth, image
    oak.queue.send(group)
    with pytest.raises(FrameSyncError, match=r"60\.0 ms apart \(more than 33\.3 ms"):
        camera.capture(timeout=0.5)


def test_old_queued_frame_is_not_returned(camera: OakCamera, oak: FakeOak) -> None:
    old = depth_message(np.full((H, W), 1000, np.uint16), seq=1)
    old_image = image_message("NV12", np.zeros((H, W), np.uint8), seq=1)
    for m in (old, old_image):
        m.setTimestamp(dai.Clock.now() - datetime.timedelta(seconds=10))
    oak.send_depth(old)
    oak.send_image(old_image)
    with pytest.raises(DeviceTimeoutError):
        camera.capture(timeout=0.05)


def test_device_that_disappears(camera: OakCamera, oak: FakeOak) -> None:
    oak.queue.close()                                   # depthai closes the queues on device loss
    with pytest.raises(DeviceConnectionError, match="disconnected"):
        camera.capture(timeout=0.5)
    oak.device.isClosed.return_value = True
    with pytest.raises(DeviceConnectionError, match="disconnected"):
        camera.capture(timeout=0.5)


def test_wrong_frame_size_is_a_protocol_error(camera: OakCamera, oak: FakeOak) -> None:
    oak.send_depth(depth_message(np.ones((H + 2, W), np.uint16), seq=2))
    oak.send_image(image_message("NV12", np.zeros((H, W), np.uint8), seq=2))
    with pytest.raises(ProtocolError, match="expected uint16"):
        camera.capture(timeout=0.5)
    oak.send_depth(depth_message(np.ones((H, W), np.uint16), seq=3))
    oak.send_image(image_message("NV12", np.zeros((H, W - 2), np.uint8), seq=3))
    with pytest.raises(ProtocolError, match=rf"image frame is {W - 2} x {H}, expected {W} x {H}"):
        camera.capture(timeout=0.5)
    oak.send_depth(depth_message(np.ones((H, W), np.uint16), seq=4))
    bgr = image_message("GRAY8", np.zeros((H, W), np.uint8), seq=4)
    bgr.setType(dai.ImgFrame.Type.BGR888i)
    oak.send_image(bgr)
    with pytest.raises(ProtocolError, match="BGR888i carries no grey image"):
        camera.capture(timeout=0.5)


@pytest.mark.parametrize(("kind", "dtype"), [("RAW16", np.uint16), ("GRAYF16", np.float16), ("GRAY8", np.uint8)])
def test_grey_image_reads_each_type_past_row_padding(kind: str, dtype: Any) -> None:
    pixels = (np.arange(H * W).reshape(H, W) % 251 * 97).astype(dtype)
    msg = image_message(kind, pixels, seq=1, stride=W * pixels.itemsize + 24)
    grey = grey_image(msg, (H, W))
    assert grey.dtype == np.float32
    np.testing.assert_array_equal(grey, pixels.astype(np.float32))
    short = image_message(kind, pixels, seq=1)
    short.setData(np.zeros(W * pixels.itemsize * H - 1, np.uint8))
    with pytest.raises(ProtocolError, match=r"too short"):
        grey_image(short, (H, W))


# ---------------------------------------------------------------- mono socket: rectified image
@pytest.mark.parametrize(("socket", "rectified", "align"), [("CAM_B", "rectifiedLeft", "RECTIFIED_LEFT"),
                                                            ("CAM_C", "rectifiedRight", "RECTIFIED_RIGHT")])
def test_mono_socket_gives_its_rectified_image_resized(oak: FakeOak, socket: str, rectified: str,
                                                       align: str) -> None:
    with connected(align_socket=socket) as cam:
        (stereo,) = oak.nodes_of(dai.node.StereoDepth)
        (manip,) = oak.nodes_of(dai.node.ImageManip)
        (sync,) = oak.nodes_of(dai.node.Sync)
        stereo.setDepthAlign.assert_called_once_with(getattr(dai.StereoDepthConfig.AlgorithmControl.DepthAlign,
                                                             align))
        stereo.setOutputSize.assert_called_once_with(W, H)
        # the matching rectified view, resized on the device as the depth is, then paired with it
        getattr(stereo, rectified).link.assert_called_once_with(manip.inputImage)
        other = "rectifiedRight" if rectified == "rectifiedLeft" else "rectifiedLeft"
        getattr(stereo, other).link.assert_not_called()
        manip.initialConfig.setOutputSize.assert_called_once_with(W, H, dai.ImageManipConfig.ResizeMode.CENTER_CROP)
        manip.setMaxOutputFrameSize.assert_called_once_with(W * H)
        manip.out.link.assert_called_once_with(sync.inputs["image"])
        stereo.depth.link.assert_called_once_with(sync.inputs["depth"])
        assert len(oak.nodes_of(dai.node.Camera)) == 2          # no colour camera
        # rectified view: the stereo right camera's matrix at the output size, no distortion
        intr = cam.intrinsics
        assert intr.fx == pytest.approx(790.0 * W / 1280, rel=1e-6) and intr.fy == pytest.approx(791.0 * W / 1280,
                                                                                                  rel=1e-6)
        assert not intr.has_distortion
        grey = np.arange(H * W, dtype=np.uint32).reshape(H, W).astype(np.uint8)
        oak.send_depth(depth_message(np.full((H, W), 750, np.uint16), seq=12))
        oak.send_image(image_message("RAW8", grey, seq=12))
        frame = cam.capture(timeout=1.0)
    assert frame.sequence == 12 and frame.amplitude.dtype == np.float32
    np.testing.assert_array_equal(frame.amplitude, grey.astype(np.float32))
    np.testing.assert_allclose(frame.xyz[..., 2], 0.75, atol=1e-6)


def test_sequence_mismatch_is_a_frame_sync_error(oak: FakeOak) -> None:
    with connected(align_socket="CAM_B") as cam:
        depth = depth_message(np.full((H, W), 750, np.uint16), seq=12)
        image = image_message("GRAY8", np.zeros((H, W), np.uint8), seq=13)
        image.setTimestamp(depth.getTimestamp())           # same time, yet not the same frame
        oak.send_depth(depth)
        oak.send_image(image)
        with pytest.raises(FrameSyncError, match=r"depth frame 12 came with image frame 13"):
            cam.capture(timeout=0.5)


# ---------------------------------------------------------------- ToF
def test_tof_board_pairs_depth_with_the_amplitude_output_undistorted(oak: FakeOak) -> None:
    cam = OakCamera.from_config({"depth_source": "tof", "align_socket": "CAM_A", "width": W, "height": H,
                                 "distortion": "none"})
    with cam:
        (tof,) = oak.nodes_of(dai.node.ToF)
        (sync,) = oak.nodes_of(dai.node.Sync)
        tof.build.assert_called_once_with(dai.CameraBoardSocket.CAM_A, fps=15.0)
        tof.setOutputUndistortion.assert_called_once_with(True)
        tof.depth.link.assert_called_once_with(sync.inputs["depth"])
        tof.amplitude.link.assert_called_once_with(sync.inputs["image"])
        assert not cam.intrinsics.has_distortion
        amplitude = np.linspace(0, 65535, H * W).astype(np.uint16).reshape(H, W)   # raw amplitude counts
        oak.send_depth(depth_message(np.full((H, W), 1500, np.uint16), seq=5))
        oak.send_image(image_message("RAW16", amplitude, seq=5))
        frame = cam.capture(timeout=1.0)
    assert oak.opened_with == [()]                      # no id: first device
    assert frame.amplitude.dtype == np.float32 and frame.amplitude.max() == 65535.0
    np.testing.assert_array_equal(frame.amplitude, amplitude.astype(np.float32))


# ---------------------------------------------------------------- amplitude = "none"
@pytest.mark.parametrize("config", [{}, {"align_socket": "CAM_B"}, {"depth_source": "tof"}])
def test_amplitude_none_streams_depth_only(oak: FakeOak, config: dict[str, str]) -> None:
    with connected(amplitude="none", **config) as cam:
        assert not oak.nodes_of(dai.node.Sync) and not oak.nodes_of(dai.node.ImageManip)
        for node in oak.nodes_of(dai.node.StereoDepth):
            node.rectifiedLeft.link.assert_not_called()
            node.rectifiedRight.link.assert_not_called()
            node.depth.createOutputQueue.assert_called_once_with(maxSize=4, blocking=False)
        for node in oak.nodes_of(dai.node.ToF):
            node.amplitude.link.assert_not_called()
            node.depth.createOutputQueue.assert_called_once_with(maxSize=4, blocking=False)
        cameras = oak.nodes_of(dai.node.Camera)
        if len(cameras) == 3:                               # colour socket: linked for the alignment only
            cameras[-1].requestOutput.return_value.link.assert_called_once_with(
                oak.nodes_of(dai.node.StereoDepth)[0].inputAlignTo)
        oak.send_depth(depth_message(np.full((H, W), 1000, np.uint16), seq=9))
        frame = cam.capture(timeout=1.0)
        assert frame.sequence == 9
        np.testing.assert_array_equal(frame.amplitude, np.zeros((H, W), np.float32))
        with pytest.raises(DeviceTimeoutError, match=r"no depth frame within 0\.05 s"):
            cam.capture(timeout=0.05)


def test_connect_timeout_bounded_and_late_device_closed(oak: FakeOak, mocker: Any) -> None:
    release = threading.Event()

    def slow_open(*args: Any) -> Any:
        release.wait(5.0)
        return oak.device

    mocker.patch.object(dai, "Device", side_effect=slow_open)
    cam = OakCamera.from_config({"device_id": DEVICE_ID})
    cam._caller.join = lambda timeout: None
    with pytest.raises(DeviceTimeoutError, match="did not finish within"):
        cam.connect(timeout=0.2)
    release.set()
    for t in threading.enumerate():
        if t.name.startswith("oak "):
            t.join(5.0)
    oak.device.close.assert_called_once_with()


def test_missing_extra_names_it(mocker: Any) -> None:
    mocker.patch.dict(sys.modules, {"depthai": None})
    cam = OakCamera.from_config({})
    with pytest.raises(MissingDependencyError, match=r"cellcal\[oak\]"):
        cam.connect(timeout=1.0)


# ---------------------------------------------------------------- discovery
def test_discover_lists_depthai_devices(mocker: Any) -> None:
    info = dai.DeviceInfo("1.3", DEVICE_ID, dai.XLinkDeviceState.X_LINK_UNBOOTED,
                          dai.XLinkProtocol.X_LINK_USB_VSC, dai.XLinkPlatform.X_LINK_MYRIAD_X,
                          dai.XLinkError_t.X_LINK_SUCCESS)
    mocker.patch.object(dai.Device, "getAllAvailableDevices", return_value=[info])
    (dev,) = OakCamera.discover(timeout=1.0)
    assert dev.serial == DEVICE_ID and dev.model == "X_LINK_MYRIAD_X"
    assert dev.extra["state"] == "X_LINK_UNBOOTED" and dev.extra["source"] == "depthai"


def _usb_device(product_id: int, bus: int, ports: tuple[int, ...]) -> Any:
    import usb.core

    d = mock_usb = strict_autospec(usb.core.Device)
    mock_usb.idVendor, mock_usb.idProduct, mock_usb.bus, mock_usb.address = 0x03E7, product_id, bus, 7
    mock_usb.port_numbers = ports
    return d


def test_discover_falls_back_to_usb_with_boot_states(mocker: Any) -> None:
    import usb.core

    mocker.patch.object(dai.Device, "getAllAvailableDevices", return_value=[])
    find = mocker.patch.object(usb.core, "find", return_value=iter([
        _usb_device(0x2485, 1, (3,)), _usb_device(0xF63B, 2, (1, 4)), _usb_device(0xF63C, 2, (2,)),
        _usb_device(0xF63D, 3, ()), _usb_device(0x1234, 3, ())]))
    devices = OakCamera.discover(timeout=1.0)
    find.assert_called_once_with(find_all=True, idVendor=0x03E7)
    assert [d.extra["state"] for d in devices] == ["unbooted", "booted", "bootloader", "flash-booted", "unknown"]
    assert devices[1].serial == "usb 2-1.4" and devices[1].model == "USB 03e7:f63b"


def test_discover_without_any_backend_says_so(mocker: Any) -> None:
    import usb.core

    mocker.patch.dict(sys.modules, {"depthai": None})
    mocker.patch.object(usb.core, "find", side_effect=usb.core.NoBackendError("No backend available"))
    with pytest.raises(MissingDependencyError, match=r"libusb-1\.0"):
        OakCamera.discover(timeout=1.0)
    with pytest.raises(usb_scan.UsbBackendMissingError, match=r"apt-get install libusb-1\.0-0"):
        usb_scan.find_usb_devices()


def test_discover_depthai_absent_usb_works(mocker: Any) -> None:
    import usb.core

    mocker.patch.dict(sys.modules, {"depthai": None})
    mocker.patch.object(usb.core, "find", return_value=iter([_usb_device(0x2485, 1, (2,))]))
    (dev,) = OakCamera.discover(timeout=1.0)
    assert dev.extra == {"state": "unbooted", "bus": 1, "address": 7, "source": "pyusb"}


# ---------------------------------------------------------------- config
def test_config_validation() -> None:
    with pytest.raises(ConfigError, match="align_socket"):
        OakCamera.from_config({"align_socket": "CAM_Z"})
    with pytest.raises(ConfigError, match="CAM_D"):
        OakCamera.from_config({"align_socket": "CAM_D"})       # stereo cannot align there
    with pytest.raises(ConfigError, match="width"):
        OakCamera.from_config({"width": 0})
    with pytest.raises(ConfigError, match="amplitude"):
        OakCamera.from_config({"amplitude": "ir"})
    assert OakCamera.from_config({}).config.amplitude == "image"


def test_registry_builds_unconnected_without_vendor_import(mocker: Any) -> None:
    mocker.patch.dict(sys.modules, {"depthai": None, "usb": None, "usb.core": None})
    cam = default_registry().create("camera", {"backend": "oak", "device_id": DEVICE_ID},
                                    BackendContext(section="camera"))
    assert isinstance(cam, OakCamera) and not cam.connected
