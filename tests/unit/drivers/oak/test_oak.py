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
from typing import Any

import numpy as np
import pytest

dai = pytest.importorskip("depthai")
from _vendor_autospec import strict_autospec  # noqa: E402

from cellcal.devices.base import BackendContext  # noqa: E402
from cellcal.devices.errors import (  # noqa: E402
    ConfigError,
    DeviceConnectionError,
    DeviceTimeoutError,
    MissingDependencyError,
)
from cellcal.devices.geometry.camera_model import project  # noqa: E402
from cellcal.devices.registry import default_registry  # noqa: E402
from cellcal.devices.types import Intrinsics  # noqa: E402
from cellcal.drivers.oak import usb_scan  # noqa: E402
from cellcal.drivers.oak.camera import OakCamera  # noqa: E402

REAL_DEVICE = dai.Device
REAL_PIPELINE = dai.Pipeline
DEVICE_ID = "14442C10D13EABCE00"
W, H = 64, 40
CAL_K = [[800.0, 0.0, 639.5], [0.0, 802.0, 401.0], [0.0, 0.0, 1.0]]   # at 1280 x 800
CAL_D = [0.12, -0.21, 0.0012, -0.0008, 0.05, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]


def calibration() -> Any:
    calib = dai.CalibrationHandler()
    calib.setCameraIntrinsics(dai.CameraBoardSocket.CAM_A, CAL_K, 1280, 800)
    calib.setDistortionCoefficients(dai.CameraBoardSocket.CAM_A, CAL_D)
    return calib


def depth_message(depth_mm: np.ndarray, seq: int) -> Any:
    f = dai.ImgFrame()
    f.setType(dai.ImgFrame.Type.RAW16)
    f.setWidth(depth_mm.shape[1])
    f.setHeight(depth_mm.shape[0])
    f.setFrame(depth_mm)
    f.setSequenceNum(seq)
    f.setTimestamp(dai.Clock.now())
    return f


class FakeOak:
    """Device + pipeline graph; the depth output queue is a real host MessageQueue."""

    def __init__(self) -> None:
        self.queue = dai.MessageQueue("depth", 4, False)
        self.device = strict_autospec(REAL_DEVICE)
        self.device.getDeviceId.return_value = DEVICE_ID
        self.device.getPlatformAsString.return_value = "RVC2"
        self.device.getProductName.return_value = "OAK-D-PRO"
        self.device.getPlatform.return_value = dai.Platform.RVC2
        self.device.isClosed.return_value = False
        self.device.readCalibration.return_value = calibration()
        self.opened_with: list[Any] = []
        self.nodes: list[Any] = []
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
        out.createOutputQueue.return_value = self.queue
        return out

    def create(self, node_cls: Any, *args: Any, **kwargs: Any) -> Any:
        node = strict_autospec(node_cls)
        node.build.return_value = node
        if node_cls is dai.node.Camera:
            node.requestOutput.return_value = strict_autospec(dai.Node.Output)
            node.requestFullResolutionOutput.return_value = strict_autospec(dai.Node.Output)
        if node_cls is dai.node.StereoDepth:
            node.depth = self.output()
            node.inputAlignTo = strict_autospec(dai.Node.Input)
        self.nodes.append(node)
        return node


@pytest.fixture
def oak(mocker: Any) -> FakeOak:
    fake = FakeOak()
    mocker.patch.object(dai, "Device", side_effect=fake.open)
    mocker.patch.object(dai, "Pipeline", side_effect=fake.make_pipeline)
    return fake


@pytest.fixture
def camera(oak: FakeOak) -> Any:
    cam = OakCamera.from_config({"backend": "oak", "device_id": DEVICE_ID, "width": W, "height": H})
    cam.connect(timeout=5.0)
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
    stereo = next(n for n in oak.nodes if hasattr(n, "setDepthAlign"))
    color = oak.nodes[-1]
    color.build.assert_called_once_with(dai.CameraBoardSocket.CAM_A)
    color.requestOutput.return_value.link.assert_called_once_with(stereo.inputAlignTo)
    assert camera.info().serial == DEVICE_ID


def test_depth_image_to_xyz_agrees_with_core_camera_model(camera: OakCamera, oak: FakeOak) -> None:
    rng = np.random.default_rng(3)
    depth = rng.integers(300, 4000, size=(H, W)).astype(np.uint16)
    depth[5, 7] = depth[20, 33] = 0                     # invalid pixels
    oak.queue.send(depth_message(depth, seq=41))
    frame = camera.capture(timeout=1.0)
    assert frame.sequence == 41 and frame.shape == (H, W)
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


def test_empty_depth_queue_times_out(camera: OakCamera) -> None:
    with pytest.raises(DeviceTimeoutError, match=r"no depth frame within 0\.05 s"):
        camera.capture(timeout=0.05)


def test_old_queued_frame_is_not_returned(camera: OakCamera, oak: FakeOak) -> None:
    old = depth_message(np.full((H, W), 1000, np.uint16), seq=1)
    old.setTimestamp(dai.Clock.now() - datetime.timedelta(seconds=10))
    oak.queue.send(old)
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
    from cellcal.devices.errors import ProtocolError

    oak.queue.send(depth_message(np.ones((H + 2, W), np.uint16), seq=2))
    with pytest.raises(ProtocolError, match="expected uint16"):
        camera.capture(timeout=0.5)


def test_tof_board_uses_the_tof_node_undistorted(oak: FakeOak) -> None:
    oak.output_for_tof = oak.output()
    original = oak.create

    def create(node_cls: Any, *args: Any, **kwargs: Any) -> Any:
        node = original(node_cls, *args, **kwargs)
        if node_cls is dai.node.ToF:
            node.depth = oak.output_for_tof
        return node

    oak.pipeline.create.side_effect = create
    cam = OakCamera.from_config({"depth_source": "tof", "align_socket": "CAM_A", "width": W, "height": H,
                                 "distortion": "none"})
    with cam:
        (tof,) = oak.nodes
        tof.build.assert_called_once_with(dai.CameraBoardSocket.CAM_A, fps=15.0)
        tof.setOutputUndistortion.assert_called_once_with(True)
        assert not cam.intrinsics.has_distortion
    assert oak.opened_with == [()]                      # no id: first device


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


def test_registry_builds_unconnected_without_vendor_import(mocker: Any) -> None:
    mocker.patch.dict(sys.modules, {"depthai": None, "usb": None, "usb.core": None})
    cam = default_registry().create("camera", {"backend": "oak", "device_id": DEVICE_ID},
                                    BackendContext(section="camera"))
    assert isinstance(cam, OakCamera) and not cam.connected
