"""Conformance checks for :class:`~cellcal.devices.camera.Camera3D` backends.

Every check takes a *factory* — a zero-argument callable that returns a new,
unconnected camera (typically ``lambda: MyCamera.from_config({...})``) — and
:class:`CameraOptions` describing what the backend declares (its distance range).
The checks need a scene the camera sees something in: at least
``min_valid_fraction`` valid pixels per frame.
"""

from __future__ import annotations

import functools
import itertools
import json
import math
from collections.abc import Callable, Iterable

import cv2
import numpy as np

from cellcal.devices.camera import Camera3D
from cellcal.devices.errors import DeviceTimeoutError
from cellcal.devices.measurement import MeasurementModel
from cellcal.devices.types import Frame, Intrinsics

from ._runner import (
    Check,
    ConformanceReport,
    Violation,
    check_bad_connect_timeouts,
    check_bad_timeouts,
    check_stalled,
    connected,
    expect,
    run_checks,
    timed,
)
from .camera_options import CameraOptions
from .lifecycle import lifecycle_checks
from .readiness import calibrate_checks

Factory = Callable[[], Camera3D]


# ---------------------------------------------------------------- intrinsics and frames
def _intrinsics(factory: Factory, o: CameraOptions) -> None:
    with connected(factory, Camera3D, o.connect_timeout_s) as cam:
        intr = cam.intrinsics
        again = cam.intrinsics
    expect(isinstance(intr, Intrinsics), f"intrinsics is {type(intr).__name__}, not Intrinsics")
    expect(intr == again, "intrinsics changed between two reads without a capture")
    w, h = intr.width, intr.height
    expect(-0.5 <= intr.cx <= w - 0.5 and -0.5 <= intr.cy <= h - 0.5,
           f"principal point ({intr.cx:g}, {intr.cy:g}) px lies outside the {w}x{h} image")
    fov_x = math.degrees(2 * math.atan(w / 2 / intr.fx))
    fov_y = math.degrees(2 * math.atan(h / 2 / intr.fy))
    expect(1.0 <= fov_x <= 179.0 and 1.0 <= fov_y <= 179.0,
           f"field of view {fov_x:.3g} x {fov_y:.3g} deg from fx={intr.fx:g}, fy={intr.fy:g} px is not plausible "
           "(focal lengths must be in pixels)")
    expect(0.5 <= intr.fx / intr.fy <= 2.0, f"fx/fy = {intr.fx / intr.fy:.3g}: pixels this far from square are "
                                            "implausible (focal lengths in different units?)")


def _capture_frames(cam: Camera3D, o: CameraOptions, n: int) -> list[Frame]:
    frames = []
    for i in range(n):
        f = cam.capture(o.capture_timeout_s)
        expect(isinstance(f, Frame), f"capture() #{i} returned {type(f).__name__}, not Frame")
        expect(f.valid_fraction >= o.min_valid_fraction,
               f"frame #{i} has {f.valid_fraction:.2%} valid pixels (< {o.min_valid_fraction:.2%}); "
               "point the camera at the test scene")
        frames.append(f)
    return frames


def _frame_layout(factory: Factory, o: CameraOptions) -> None:
    with connected(factory, Camera3D, o.connect_timeout_s) as cam:
        (f,) = _capture_frames(cam, o, 1)
        intr = cam.intrinsics
    h, w = intr.height, intr.width
    expect(f.shape == (h, w), f"frame is {f.shape[0]}x{f.shape[1]} (rows x cols), intrinsics say {h}x{w}")
    layout = (("distance", f.distance, (h, w), np.float32), ("xyz", f.xyz, (h, w, 3), np.float32),
              ("amplitude", f.amplitude, (h, w), np.float32), ("valid", f.valid, (h, w), np.bool_))
    for name, arr, shape, dtype in layout:
        expect(arr.shape == shape and arr.dtype == dtype,
               f"Frame.{name} is {arr.dtype} {arr.shape}, expected {np.dtype(dtype).name} {shape}")
    expect(np.allclose(f.intrinsics.camera_matrix, intr.camera_matrix, rtol=1e-6, atol=1e-6)
           and np.allclose(f.intrinsics.distortion, intr.distortion, rtol=1e-6, atol=1e-9),
           "the frame's intrinsics differ from the camera's intrinsics")


def _frame_units(factory: Factory, o: CameraOptions) -> None:
    with connected(factory, Camera3D, o.connect_timeout_s) as cam:
        (f,) = _capture_frames(cam, o, 1)
    v = f.valid
    d = f.distance[v]
    expect(np.all(np.isfinite(d)), f"{np.count_nonzero(~np.isfinite(d))} valid pixels have a non-finite distance")
    lo, hi = o.distance_range_m
    outside = (d < lo) | (d > hi)
    expect(not outside.any(), f"{np.count_nonzero(outside)} valid pixels have a distance outside the declared "
                              f"{lo:g}..{hi:g} m (min {d.min():.6g}, max {d.max():.6g}; metres expected)")
    expect(np.all(np.isnan(f.distance[~v])), "invalid pixels must have distance NaN")
    expect(np.all(np.isnan(f.xyz[~v])), "invalid pixels must have xyz NaN")
    p = f.xyz[v].astype(np.float64)
    expect(np.all(np.isfinite(p)), "valid pixels must have finite xyz")
    err = np.abs(np.linalg.norm(p, axis=1) - d)
    expect(err.max(initial=0.0) <= o.xyz_tolerance_m + 1e-6 * d.max(initial=0.0),
           f"|xyz| differs from distance by up to {err.max():.3g} m (tolerance {o.xyz_tolerance_m:g} m); "
           "distance must be radial and both in metres")
    expect(np.all(p[:, 2] > 0), "valid points must have z > 0 (camera frame: z forward along the optical axis)")
    expect(np.all(np.isfinite(f.amplitude[v])), "amplitude must be finite on valid pixels")


def _frame_geometry(factory: Factory, o: CameraOptions) -> None:
    if o.reprojection_tolerance_px is None:
        return
    with connected(factory, Camera3D, o.connect_timeout_s) as cam:
        (f,) = _capture_frames(cam, o, 1)
    intr = f.intrinsics
    rows, cols = np.nonzero(f.valid)
    pts = f.xyz[rows, cols].astype(np.float64).reshape(-1, 1, 3)
    uv, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), intr.camera_matrix, intr.distortion)
    err = np.hypot(uv[:, 0, 0] - cols, uv[:, 0, 1] - rows)
    p95 = float(np.percentile(err, 95))
    expect(p95 <= o.reprojection_tolerance_px,
           f"valid points projected through the intrinsics land {p95:.3g} px (95th percentile) from their pixel "
           f"(tolerance {o.reprojection_tolerance_px:g} px); xyz must be in the OpenCV camera frame "
           "(x right, y down, z forward), pixel centres at integer (u=column, v=row)")


def _sequence(factory: Factory, o: CameraOptions) -> None:
    with connected(factory, Camera3D, o.connect_timeout_s) as cam:
        frames = _capture_frames(cam, o, o.frames)
    ts = [f.timestamp for f in frames]
    seq = [f.sequence for f in frames]
    expect(all(isinstance(t, float) and 1e9 < t < 1e10 for t in ts),
           f"timestamps {ts} are not seconds since the Unix epoch")
    expect(all(b > a for a, b in itertools.pairwise(ts)),
           f"timestamps of consecutive captures must increase, got {ts}")
    expect(all(isinstance(s, (int, np.integer)) and not isinstance(s, bool) for s in seq),
           f"sequence numbers must be integers, got {seq}")
    expect(all(b > a for a, b in itertools.pairwise(seq)),
           f"sequence numbers of consecutive captures must increase (a new frame each time), got {seq}")


#: What a vendor is told when the camera states no measurement model.
HOW_TO_STATE_A_MODEL = (
    "override Camera3D._measurement_model() to return a MeasurementModel: kind 'tof' with sigma_at_1m_m "
    "(and distance_exponent), or 'stereo' / 'structured_light' with baseline_m, focal_px and subpixel_bits, "
    "read from the device where it can tell them (source 'device') or the backend's own figures (source "
    "'backend'); see docs/extending.md, 'Stating how the camera measures'. A camera that cannot tell opts out "
    "with CameraOptions(model_unknown_reason='why')")


def _measurement_model(factory: Factory, o: CameraOptions) -> None:
    with connected(factory, Camera3D, o.connect_timeout_s) as cam:
        own = cam._measurement_model()       # the backend's own statement, not a [camera.model] override
        expect(isinstance(own, MeasurementModel),
               f"_measurement_model() returned {type(own).__name__}, not a MeasurementModel")
        if not own.known:
            expect(o.model_unknown_reason is not None, f"the camera states no measurement model (kind 'unknown'); "
                                                       f"{HOW_TO_STATE_A_MODEL}")
        else:
            expect(own.source != "unstated", f"the {own.kind} model names no source; set source='device' (read "
                                             "from the device) or 'backend' (the backend's own figures)")
        try:
            text = json.dumps(own.to_dict(), allow_nan=False)
            back = MeasurementModel.from_dict(json.loads(text), where="measurement_model")
        except (TypeError, ValueError) as exc:   # ConfigError is a ValueError
            raise Violation(f"the measurement model does not survive a recording (to_dict, JSON, from_dict): "
                            f"{exc}") from None
        expect(back == own and back.settings == own.settings,
               "the measurement model changes through to_dict / from_dict (settings must be plain JSON data)")
        for i, frame in enumerate(_capture_frames(cam, o, 2)):
            stated = cam.measurement_model
            expect(frame.measurement == stated,
                   f"frame #{i} carries the model {frame.measurement.describe()!r}, the camera states "
                   f"{stated.describe()!r}; a frame must carry the camera's model")


# ---------------------------------------------------------------- timeouts and resources
def _timeout_validation(factory: Factory, o: CameraOptions) -> None:
    with connected(factory, Camera3D, o.connect_timeout_s) as cam:
        check_bad_timeouts({"capture": cam.capture})
        cam.capture(o.capture_timeout_s)  # a rejected timeout leaves the camera usable
    check_bad_connect_timeouts(factory, Camera3D, "camera")


def _timeout_bounded(factory: Factory, o: CameraOptions) -> None:
    with connected(factory, Camera3D, o.connect_timeout_s) as cam:
        for i in range(2):
            elapsed, _, exc = timed(lambda: cam.capture(o.short_timeout_s))
            expect(exc is None or isinstance(exc, DeviceTimeoutError),
                   f"capture(timeout={o.short_timeout_s:g}) raised {type(exc).__name__} ({exc}), expected a "
                   "frame or DeviceTimeoutError")
            limit = o.short_timeout_s + o.timing_slack_s
            expect(elapsed <= limit, f"capture(timeout={o.short_timeout_s:g}) #{i} took {elapsed:.3g} s "
                                     f"(more than timeout + {o.timing_slack_s:g} s slack)")
    check_stalled(o, Camera3D, lambda cam: {f"capture() #{i}": functools.partial(cam.capture, o.short_timeout_s)
                                            for i in (1, 2)})


def _refusals(cam: Camera3D) -> dict[str, Callable[[], object]]:
    return {"capture()": lambda: cam.capture(1.0), "intrinsics": lambda: cam.intrinsics, "info()": cam.info}


def _use(cam: Camera3D, o: CameraOptions) -> None:
    cam.capture(o.capture_timeout_s)


_FIRST, _LAST = lifecycle_checks("camera", Camera3D, _refusals, _use)

CAMERA_CHECKS: tuple[Check[Camera3D, CameraOptions], ...] = (
    *_FIRST,
    Check("camera.intrinsics", "intrinsics are stable and plausible (pixels, principal point in the image)",
          _intrinsics),
    Check("camera.frame-layout", "frame arrays have the intrinsics' shape and the documented dtypes",
          _frame_layout),
    Check("camera.frame-units", "distance is radial metres within the declared range; NaN where invalid; "
                                "|xyz| == distance", _frame_units),
    Check("camera.frame-geometry", "xyz lies on its pixel's ray in the OpenCV camera frame", _frame_geometry),
    Check("camera.sequence", "consecutive captures give new frames with increasing epoch timestamps", _sequence),
    Check("camera.measurement-model", "the camera states how it measures (a MeasurementModel with its source) "
                                      "and every frame carries it", _measurement_model),
    *calibrate_checks(),
    Check("camera.timeout-validation", "a non-positive, NaN, infinite or non-number timeout is a clear CellcalError",
          _timeout_validation),
    Check("camera.timeout-bounded", "capture(timeout) returns a frame or raises DeviceTimeoutError in bounded time",
          _timeout_bounded),
    _LAST,
)

#: The camera contract rules, in the order they run.
CAMERA_RULES: tuple[str, ...] = tuple(c.rule for c in CAMERA_CHECKS)


def check_camera(factory: Factory, options: CameraOptions | None = None, *, only: Iterable[str] | None = None,
                 raise_on_failure: bool = True, quiet: bool = False) -> ConformanceReport:
    """Run the camera contract checks against one backend.

    Args:
        factory: Zero-argument callable returning a new, unconnected camera each call.
        options: What the backend declares (distance range, tolerances); defaults apply if None.
        only: Run only these rules (see :data:`CAMERA_RULES`).
        raise_on_failure: Raise :class:`ConformanceError` listing every failed rule.
        quiet: Do not print each rule's name to stderr as it starts.

    Returns:
        The report (all checks passed when ``raise_on_failure`` is true).

    Raises:
        ConformanceError: If a check failed and ``raise_on_failure`` is true.
        CellcalError: If ``factory`` is not callable or ``only`` names an unknown rule.
    """
    return run_checks("camera", CAMERA_CHECKS, factory, options or CameraOptions(), Camera3D, only,
                      raise_on_failure, quiet)
