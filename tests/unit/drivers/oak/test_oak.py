"""OAK backend over depthai v3, mocked at the library boundary: the fake device, and the default pipeline.

Real depthai objects are used where they work without hardware: the host-side
``dai.MessageQueue`` the backend reads (with its real timeout and close semantics),
``dai.ImgFrame`` depth messages, ``dai.CalibrationHandler`` (its own intrinsics
scaling) and ``dai.DeviceInfo``. The device, pipeline and nodes are strict autospecs
of the real classes (signatures parsed from the pybind11 docstrings).

The fake (``FakeOak``, ``patched_oak``, the message builders, ``connected``) lives here; the other OAK
tests import it: test_oak_sources.py (mono socket, ToF, depth only), test_oak_failures.py (timeouts,
frames out of step, lost device), test_oak_discovery.py (discovery and config), test_oak_model.py, and
the conformance kit's run in tests/integration/devices/test_device_contract.py. The tests here pin the
default pipeline: stereo depth aligned to the colour camera, its intrinsics, its frames in metres, RVC4.
"""

from __future__ import annotations

import datetime
from typing import Any
from unittest import mock

import numpy as np
import pytest

dai = pytest.importorskip("depthai")
from _vendor_autospec import strict_autospec  # noqa: E402

from cellcal.devices.geometry.camera_model import project  # noqa: E402
from cellcal.devices.types import Intrinsics  # noqa: E402
from cellcal.drivers.oak.camera import OakCamera  # noqa: E402

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


def patched_oak(mocker: Any) -> FakeOak:
    """A fresh :class:`FakeOak` that ``dai.Device`` and ``dai.Pipeline`` open for the test's duration."""
    fake = FakeOak()
    mocker.patch.object(dai, "Device", side_effect=fake.open)
    mocker.patch.object(dai, "Pipeline", side_effect=fake.make_pipeline)
    return fake


@pytest.fixture
def oak(mocker: Any) -> FakeOak:
    return patched_oak(mocker)


def connected(**config: Any) -> Any:
    cam = OakCamera.from_config({"backend": "oak", "device_id": DEVICE_ID, "width": W, "height": H,
                                 "isolate": False, **config})  # the mocked depthai is in this process
    cam.connect(timeout=5.0)
    return cam


@pytest.fixture
def camera(oak: FakeOak) -> Any:
    cam = connected()
    yield cam
    cam.close()


# ---------------------------------------------------------------- the default pipeline: depth aligned to colour
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
