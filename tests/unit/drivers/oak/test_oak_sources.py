"""The OAK's other depth sources and images: a mono socket's rectified image (resized on the device as the depth
is, paired with it by sequence number), the ToF board's amplitude, depth alone (``amplitude = "none"``), and the
grey image read from each ImgFrame type past its row padding.

The device is the fake of test_oak.py (real depthai queues and messages, autospecced device and nodes).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

dai = pytest.importorskip("depthai")
from test_oak import FakeOak, H, W, connected, depth_message, image_message, patched_oak  # noqa: E402

from cellcal.devices.errors import DeviceTimeoutError, FrameSyncError, ProtocolError  # noqa: E402
from cellcal.drivers.oak.camera import OakCamera  # noqa: E402
from cellcal.drivers.oak.grey import grey_image  # noqa: E402


@pytest.fixture
def oak(mocker: Any) -> FakeOak:
    return patched_oak(mocker)


# ---------------------------------------------------------------- grey images of each type
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
                                 "distortion": "none", "isolate": False})
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
