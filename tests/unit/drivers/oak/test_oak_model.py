"""The OAK states its stereo model from the device: baseline, focal length, subpixel bits, filters.

The device is the fake of test_oak.py: a real ``dai.CalibrationHandler`` (baseline from its
extrinsics, focal length scaled by depthai itself), real ``dai.CameraFeatures`` and the real
``dai.StereoDepthConfig`` message the StereoDepth node's preset fills in.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
import pytest

dai = pytest.importorskip("depthai")
from test_oak import (  # noqa: E402
    DEVICE_ID,
    RIGHT_K,
    FakeOak,
    H,
    W,
    calibration,
    camera_features,
    connected,
    depth_message,
)

from cellcal.devices.errors import DeviceError  # noqa: E402
from cellcal.drivers.oak.camera import OakCamera  # noqa: E402

#: A 400P stereo pair: the right camera's focal length 440 px at 640 x 400.
K_440 = [[440.0, 0.0, 319.5], [0.0, 440.0, 199.5], [0.0, 0.0, 1.0]]


@pytest.fixture
def oak(mocker: Any) -> FakeOak:
    fake = FakeOak()
    mocker.patch.object(dai, "Device", side_effect=fake.open)
    mocker.patch.object(dai, "Pipeline", side_effect=fake.make_pipeline)
    return fake


def lite(oak: FakeOak, **calib: Any) -> None:
    """Make the fake a 400P stereo board: 75 mm baseline, 440 px at 640 x 400."""
    oak.device.readCalibration.return_value = calibration(**{"right_k": K_440, "size": (640, 400), **calib})
    oak.device.getConnectedCameraFeatures.return_value = camera_features((640, 400))


def test_75_mm_and_440_px_give_fb_33_and_the_depth_step_of_the_subpixel_bits(oak: FakeOak) -> None:
    lite(oak)
    oak.stereo_settings = lambda c: c.setSubpixel(False)
    with connected(amplitude="none") as cam:
        integer = cam.measurement_model
    assert integer.kind == "stereo" and integer.source == "device"
    assert integer.baseline_m == pytest.approx(0.075) and integer.focal_px == pytest.approx(440.0)
    assert integer.fb_px_m == pytest.approx(33.0) and integer.subpixel_bits == 0
    assert integer.depth_step_m(0.7) == pytest.approx(0.49 / 33.0)           # 14.8 mm: the level spacing
    oak.stereo_settings = None                                               # the DEFAULT preset: subpixel, 3 bits
    with connected(amplitude="none") as cam:
        subpixel = cam.measurement_model
    assert subpixel.subpixel_bits == 3 and subpixel.depth_step_m(0.7) == pytest.approx(0.49 / 33.0 / 8.0)
    assert subpixel.settings == {
        "depth_source": "stereo", "preset": "DEFAULT", "subpixel": True, "subpixel_fractional_bits": 3,
        "median": "KERNEL_7x7", "left_right_check": True, "extended_disparity": False,
        "confidence_threshold": subpixel.settings["confidence_threshold"], "spatial_filter": False,
        "temporal_filter": False, "speckle_filter": False, "decimation_factor": 1, "matching_size_px": [640, 400],
        "baseline_from": "design", "stereo_sockets": ["CAM_B", "CAM_C"], "depth_unit_m": 0.001}


def test_the_focal_length_is_the_matching_resolutions_not_the_outputs(oak: FakeOak) -> None:
    # OAK-D: 1280 x 800 mono sensors (790 px), depth given at W x H aligned to the colour camera
    with connected() as cam:
        model = cam.measurement_model
        output_fx = cam.intrinsics.fx
    assert model.focal_px == pytest.approx(RIGHT_K[0][0]) and output_fx == pytest.approx(800.0 * W / 1280)
    assert model.fb_px_m == pytest.approx(790.0 * 0.075) and model.settings["matching_size_px"] == [1280, 800]
    with connected(align_socket="CAM_C") as cam:               # the rectified right view: same disparity, same model
        assert cam.measurement_model == model and cam.intrinsics.fx == pytest.approx(790.0 * W / 1280)


def test_a_preset_s_bits_and_filters_reach_the_model(oak: FakeOak) -> None:
    with connected(stereo_preset="HIGH_DETAIL") as cam:
        model = cam.measurement_model
    assert model.subpixel_bits == 5 and model.settings["extended_disparity"] is True
    assert model.settings["median"] == "MEDIAN_OFF" and model.settings["preset"] == "HIGH_DETAIL"
    oak.stereo_settings = lambda c: (c.setSubpixelFractionalBits(4), c.setLeftRightCheck(False))
    with connected() as cam:
        model = cam.measurement_model
    assert model.subpixel_bits == 4 and model.settings["left_right_check"] is False


def test_before_connect_stereo_is_unknown_and_tof_is_stated(oak: FakeOak) -> None:
    stereo = OakCamera.from_config({"device_id": DEVICE_ID})
    assert stereo.measurement_model.kind == "unknown"
    tof = OakCamera.from_config({"depth_source": "tof"})
    assert tof.measurement_model.kind == "tof" and tof.measurement_model.range_step_m == 0.001
    assert tof.measurement_model.source == "backend" and tof.measurement_model.sigma_at_1m_m is None


def test_frames_carry_the_device_s_model(oak: FakeOak) -> None:
    lite(oak)
    with connected(amplitude="none") as cam:
        oak.send_depth(depth_message(np.full((H, W), 700, np.uint16), seq=3))
        frame = cam.capture(timeout=1.0)
        assert frame.measurement == cam.measurement_model and frame.measurement.fb_px_m == pytest.approx(33.0)


def test_a_design_translation_of_zero_falls_back_to_the_calibrated_one(oak: FakeOak) -> None:
    lite(oak, spec_cm=0.0, measured_cm=7.46)                # depthai refuses a zero design translation
    with connected(amplitude="none") as cam:
        model = cam.measurement_model
    assert model.baseline_m == pytest.approx(0.0746) and model.settings["baseline_from"] == "calibration"


@pytest.mark.parametrize(("calib", "said"), [
    ({"spec_cm": 0.0, "measured_cm": 0.0}, "stereo baseline (calibration translation CAM_B-CAM_C) of 0 mm"),
    ({"spec_cm": float("nan")}, "stereo baseline (design translation CAM_B-CAM_C) of nan mm"),
    ({"spec_cm": 200.0}, "stereo baseline (design translation CAM_B-CAM_C) of 2000 mm, not within 5..500 mm"),
    ({"right_k": [[1e6, 0.0, 319.5], [0.0, 1e6, 199.5], [0.0, 0.0, 1.0]]},
     "focal length of the stereo right camera CAM_C at 640x400 of 1e+06 px"),
])
def test_absurd_device_values_fail_connect_in_one_line(oak: FakeOak, calib: dict[str, Any], said: str) -> None:
    lite(oak, **calib)
    with pytest.raises(DeviceError) as err:
        connected(amplitude="none")
    message = str(err.value)
    assert "\n" not in message and said in message and message.startswith(f"oak {DEVICE_ID}: the device reports")
    assert "[camera.model]" in message
    oak.device.close.assert_called()                           # the failed connect released the device


def test_missing_stereo_calibration_and_cameras_are_named(oak: FakeOak) -> None:
    calib = calibration()
    bare = dai.CalibrationHandler()
    for socket in ("CAM_A", "CAM_B", "CAM_C"):
        s = getattr(dai.CameraBoardSocket, socket)
        bare.setCameraIntrinsics(s, calib.getCameraIntrinsics(s), 1280, 800)
    bare.setStereoLeft(dai.CameraBoardSocket.CAM_B, np.eye(3).tolist())
    bare.setStereoRight(dai.CameraBoardSocket.CAM_C, np.eye(3).tolist())
    oak.device.readCalibration.return_value = bare
    with pytest.raises(DeviceError, match=r"calibration holds no stereo baseline between CAM_B and CAM_C"):
        connected(amplitude="none")
    oak.device.readCalibration.return_value = calibration()
    oak.device.getConnectedCameraFeatures.return_value = camera_features()[:2]
    with pytest.raises(DeviceError, match=r"stereo camera CAM_C is not among the connected cameras"):
        connected(amplitude="none")


def test_a_config_model_lets_a_bad_calibration_connect(oak: FakeOak, caplog: pytest.LogCaptureFixture) -> None:
    lite(oak, spec_cm=0.0, measured_cm=0.0)
    table = {"kind": "stereo", "baseline_m": 0.075, "focal_px": 440.0, "subpixel_bits": 3}
    with caplog.at_level(logging.WARNING, "cellcal.drivers.oak.camera"), connected(amplitude="none",
                                                                                    model=table) as cam:
        oak.send_depth(depth_message(np.full((H, W), 700, np.uint16), seq=4))
        frame = cam.capture(timeout=1.0)
        assert cam.measurement_model.source == "config" and cam.measurement_model.fb_px_m == pytest.approx(33.0)
    assert frame.measurement == cam.measurement_model
    assert "stereo baseline (calibration translation CAM_B-CAM_C) of 0 mm" in caplog.text
