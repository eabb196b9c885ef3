"""The OAK's measurement model, read from the device: baseline, focal length, subpixel bits, filters.

Stereo depth is ``Z = f·B / d``: ``B`` the baseline depthai converts disparity with (the
board's design translation between the stereo cameras, depthai's default), ``f`` the focal
length of the rectified stereo right camera *at the resolution the disparity is matched at*
(the mono sensors' full resolution: ``requestFullResolutionOutput``), ``d`` rounded to
``2^-subpixelFractionalBits`` px with subpixel on, to 1 px without. The depth output's own
size and alignment do not change the levels ``Z`` takes, so ``focal_px`` is the matching
resolution's, not the output's. Values are checked before use; rationale in
docs/adr/0032-model-in-recordings-and-kit.md.
"""

from __future__ import annotations

import math
from typing import Any

from cellcal.devices.errors import DeviceError
from cellcal.devices.measurement import MeasurementModel

#: Plausible stereo baselines, metres (OAK boards: 20 mm OAK-D SR to 150 mm OAK-D LR).
BASELINE_RANGE_M = (0.005, 0.5)
#: Plausible focal lengths of a stereo camera at its matching resolution, pixels.
FOCAL_RANGE_PX = (10.0, 20000.0)
#: Fractional disparity bits depthai accepts with subpixel on.
SUBPIXEL_BITS = (3, 4, 5)
#: The depth output's unit: uint16 millimetres (depthai's default ``DepthUnit.MILLIMETER``).
DEPTH_UNIT_M = 0.001


def tof_model() -> MeasurementModel:
    """The OAK ToF's model: ToF range, rounded to the 1 mm depth unit; no noise figure stated."""
    return MeasurementModel(kind="tof", range_step_m=DEPTH_UNIT_M, source="backend",
                            settings={"depth_source": "tof", "depth_unit_m": DEPTH_UNIT_M})


def stereo_model(device: Any, calib: Any, stereo_config: Any, preset: str, who: str) -> MeasurementModel:
    """The stereo model of a connected OAK (``source = "device"``), its filters in ``settings``.

    Args:
        device: The open ``dai.Device``.
        calib: Its ``CalibrationHandler`` (``device.readCalibration()``).
        stereo_config: The StereoDepth node's ``initialConfig`` after ``build`` (the preset applied).
        preset: The ``StereoDepth.PresetMode`` name, for ``settings``.
        who: The device, for messages.

    Raises:
        DeviceError: One line naming the value the device reported (a baseline of 0, NaN or
            an absurd size; a focal length, resolution or bit count out of range).
    """
    right, left = calib.getStereoRightCameraId(), calib.getStereoLeftCameraId()
    baseline_m, baseline_from = _baseline_m(calib, right, left, who)
    width, height = _matching_size(device, right, who)
    try:
        focal_px = float(calib.getCameraIntrinsics(right, width, height)[0][0])
    except RuntimeError as exc:
        raise DeviceError(f"oak {who}: no intrinsics for the stereo right camera {right.name}: {exc}") from None
    _check(focal_px, FOCAL_RANGE_PX, f"focal length of the stereo right camera {right.name} at {width}x{height}",
           1.0, "px", who)
    subpixel = bool(stereo_config.getSubpixel())
    bits = int(stereo_config.getSubpixelFractionalBits()) if subpixel else 0
    if subpixel and bits not in SUBPIXEL_BITS:
        raise DeviceError(f"oak {who}: the stereo config has subpixel on with {bits} fractional bits "
                          f"(depthai uses {', '.join(map(str, SUBPIXEL_BITS))})")
    post = stereo_config.postProcessing
    settings = {
        "depth_source": "stereo", "preset": preset, "subpixel": subpixel, "subpixel_fractional_bits": bits,
        "median": stereo_config.getMedianFilter().name, "left_right_check": bool(stereo_config.getLeftRightCheck()),
        "extended_disparity": bool(stereo_config.getExtendedDisparity()),
        "confidence_threshold": int(stereo_config.getConfidenceThreshold()),
        "spatial_filter": bool(post.spatialFilter.enable), "temporal_filter": bool(post.temporalFilter.enable),
        "speckle_filter": bool(post.speckleFilter.enable),
        "decimation_factor": int(post.decimationFilter.decimationFactor),
        "matching_size_px": [width, height], "baseline_from": baseline_from,
        "stereo_sockets": [left.name, right.name], "depth_unit_m": DEPTH_UNIT_M,
    }
    return MeasurementModel(kind="stereo", baseline_m=baseline_m, focal_px=focal_px, subpixel_bits=bits,
                            source="device", settings=settings)


def _baseline_m(calib: Any, right: Any, left: Any, who: str) -> tuple[float, str]:
    """The baseline depthai converts disparity with, metres, and where it came from.

    ``getBaselineDistance`` returns centimetres (depthai 2.x and 3.x default). depthai takes the
    design ("spec") translation by default (``setDisparityToDepthUseSpecTranslation``); a board
    without one has only the calibrated translation.
    """
    try:
        cm, origin = float(calib.getBaselineDistance(right, left, True)), "design"
    except RuntimeError:
        try:
            cm, origin = float(calib.getBaselineDistance(right, left, False)), "calibration"
        except RuntimeError as exc:
            raise DeviceError(f"oak {who}: the calibration holds no stereo baseline between {left.name} and "
                              f"{right.name}: {exc}") from None
    baseline_m = abs(cm) * 0.01
    _check(baseline_m, BASELINE_RANGE_M, f"stereo baseline ({origin} translation {left.name}-{right.name})",
           1000.0, "mm", who)
    return baseline_m, origin


def _matching_size(device: Any, socket: Any, who: str) -> tuple[int, int]:
    """The full resolution of the stereo camera on ``socket`` (what the disparity is matched at), px."""
    for features in device.getConnectedCameraFeatures():
        if features.socket == socket:
            w, h = int(features.width), int(features.height)
            if not (16 <= w <= 16384 and 16 <= h <= 16384):
                raise DeviceError(f"oak {who}: the stereo camera {socket.name} reports a {w}x{h} px sensor")
            return w, h
    raise DeviceError(f"oak {who}: the stereo camera {socket.name} is not among the connected cameras")


def _check(value: float, bounds: tuple[float, float], what: str, scale: float, unit: str, who: str) -> None:
    """Raise a one-line DeviceError unless ``value`` is finite and within ``bounds`` (shown × ``scale`` in ``unit``)."""
    lo, hi = bounds
    if not (math.isfinite(value) and lo <= value <= hi):
        raise DeviceError(f"oak {who}: the device reports a {what} of {value * scale:.6g} {unit}, not within "
                          f"{lo * scale:g}..{hi * scale:g} {unit}; its calibration cannot give depth (state the "
                          "model in [camera.model] to use it anyway)")
