"""The OAK backend when the device misbehaves: no depth frame or no pair within the timeout, a colour image
captured too far from its depth, a stale queued frame, a device that disappears, frames of the wrong size or
type, a device that opens too slowly (closed when it comes late), depthai not installed.

The device is the fake of test_oak.py (real depthai queues and messages, autospecced device and nodes).
"""

from __future__ import annotations

import datetime
import sys
import threading
import time
from typing import Any

import numpy as np
import pytest

dai = pytest.importorskip("depthai")
from test_oak import DEVICE_ID, FakeOak, H, W, connected, depth_message, image_message, patched_oak  # noqa: E402

from cellcal.devices.errors import (  # noqa: E402
    DeviceConnectionError,
    DeviceTimeoutError,
    FrameSyncError,
    MissingDependencyError,
    ProtocolError,
)
from cellcal.drivers.oak.camera import OakCamera  # noqa: E402


@pytest.fixture
def oak(mocker: Any) -> FakeOak:
    return patched_oak(mocker)


@pytest.fixture
def camera(oak: FakeOak) -> Any:
    cam = connected()
    yield cam
    cam.close()


# ---------------------------------------------------------------- no frame, or frames out of step
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


# ---------------------------------------------------------------- a lost device, a malformed frame
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


# ---------------------------------------------------------------- connecting
def test_connect_timeout_bounded_and_late_device_closed(oak: FakeOak, mocker: Any) -> None:
    release, entered = threading.Event(), threading.Event()

    def slow_open(*args: Any) -> Any:
        entered.set()
        release.wait(30.0)
        return oak.device

    mocker.patch.object(dai, "Device", side_effect=slow_open)
    cam = OakCamera.from_config({"device_id": DEVICE_ID, "isolate": False})
    cam._caller.join = lambda timeout: None
    with pytest.raises(DeviceTimeoutError, match="did not finish within"):
        cam.connect(timeout=1.0)   # room for a loaded machine to reach the open before the budget ends
    assert entered.is_set()
    release.set()
    for t in threading.enumerate():
        if t.name.startswith("oak "):
            t.join(5.0)
    oak.device.close.assert_called_once_with()


def test_missing_extra_names_it(mocker: Any) -> None:
    mocker.patch.dict(sys.modules, {"depthai": None})
    cam = OakCamera.from_config({"isolate": False})
    with pytest.raises(MissingDependencyError, match=r"cellcal\[oak\]"):
        cam.connect(timeout=1.0)
