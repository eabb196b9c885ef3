"""The recording wrappers: forward every call to the wrapped device and log it to a :class:`SessionLog` (a recorder)."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator, Mapping
from functools import partial
from typing import Any, Protocol, TypeVar

import numpy as np
from numpy.typing import NDArray

from cellcal.devices.arm import RobotArm
from cellcal.devices.camera import Camera3D
from cellcal.devices.errors import CellcalError
from cellcal.devices.forwarding import ForwardingArm, ForwardingCamera
from cellcal.devices.pose import Pose
from cellcal.devices.types import ArmStatus, Frame

from .codec import encode_error, encode_frame, encode_info, encode_model, encode_pose, encode_result
from .foxglove import camera_calibration, depth_image, pose_in_frame, stamp
from .schema import (
    TOPIC_ARM_CALL,
    TOPIC_ARM_INFO,
    TOPIC_CAMERA_CALIBRATION,
    TOPIC_CAMERA_INFO,
    TOPIC_CAPTURE,
    TOPIC_DEPTH,
    TOPIC_FLANGE_POSE,
)

T = TypeVar("T")


class SessionLog(Protocol):
    """What the wrappers log into: :class:`~cellcal.devices.recording.writer.SessionRecorder`
    is one (the writer builds the wrappers; the wrappers do not know the writer)."""

    def next_event(self) -> int:
        """Reserve the next session-wide event number (the replay order)."""
        ...

    def log(self, topic: str, payload: Mapping[str, Any], *, event: int | None = None,
            publish_time_s: float | None = None) -> None:
        """Write one JSON message on ``topic``."""
        ...


@contextlib.contextmanager
def _unless_interrupted(exc: BaseException) -> Iterator[None]:
    """Logging a failed call: its own failure propagates, unless a Ctrl-C is on its way already."""
    if not isinstance(exc, KeyboardInterrupt):
        yield
        return
    with contextlib.suppress(Exception):
        yield


class RecordingCamera(ForwardingCamera):
    """A :class:`Camera3D` that forwards to ``inner`` and logs identity, intrinsics, model and every capture.

    ``/camera/info`` holds the camera's measurement model as stated at connect (its
    ``[camera.model]`` override included); every recorded frame holds the model it carries.

    Args:
        inner: The camera to record; its life cycle is driven through this wrapper.
        recorder: Where to log.
    """

    def __init__(self, inner: Camera3D, recorder: SessionLog) -> None:
        super().__init__(inner)
        self.recorder = recorder
        self._captures = 0

    def _connect(self, timeout: float) -> None:
        super()._connect(timeout)
        info, intr = self.inner.info(), self.inner.intrinsics
        self.recorder.log(TOPIC_CAMERA_INFO, {**encode_info(info), "intrinsics": intr.to_dict(),
                                              "measurement_model": encode_model(self.inner.measurement_model),
                                              "default_timeout_s": self.inner.default_timeout_s})
        self.recorder.log(TOPIC_CAMERA_CALIBRATION, camera_calibration(intr, stamp(time.time())))

    def _capture(self, timeout: float) -> Frame:
        index, started = self._captures, time.perf_counter()
        self._captures += 1
        record: dict[str, Any] = {"capture": index, "timeout_s": timeout}
        event = self.recorder.next_event()  # the capture's place in the replay order is when it was asked for
        try:
            frame = super()._capture(timeout)
        except (CellcalError, KeyboardInterrupt) as exc:
            with _unless_interrupted(exc):
                self.recorder.log(TOPIC_CAPTURE, {**record, "duration_s": time.perf_counter() - started,
                                                  "frame": None, "error": encode_error(exc)}, event=event)
            raise
        self.recorder.log(TOPIC_CAPTURE, {**record, "duration_s": time.perf_counter() - started,
                                          "frame": encode_frame(frame), "error": None},
                          event=event, publish_time_s=frame.timestamp)
        self.recorder.log(TOPIC_DEPTH, depth_image(frame), publish_time_s=frame.timestamp)
        return frame


class RecordingArm(ForwardingArm):
    """A :class:`RobotArm` that forwards to ``inner`` and logs every call with arguments and result.

    Wrap the *backend* arm with it and put the :class:`~cellcal.devices.safety.SafeArm`
    around the wrapper, so the recording holds exactly what the backend was asked.

    Args:
        inner: The arm to record; its life cycle is driven through this wrapper.
        recorder: Where to log.
    """

    def __init__(self, inner: RobotArm, recorder: SessionLog) -> None:
        super().__init__(inner)
        self.recorder = recorder
        self._calls = 0

    def _call(self, method: str, args: dict[str, Any], fn: Callable[[], T]) -> T:
        """Run the forwarded call ``fn`` and log it on ``/arm/call`` (a pose read also on ``/arm/flange_pose``)."""
        index, started = self._calls, time.perf_counter()
        self._calls += 1
        event = self.recorder.next_event()
        record: dict[str, Any] = {"call": index, "method": method, "args": args}
        try:
            result = fn()
        except (CellcalError, KeyboardInterrupt) as exc:  # a move cut short by Ctrl-C was still sent: log it
            with _unless_interrupted(exc):
                self.recorder.log(TOPIC_ARM_CALL, {**record, "result": None, "error": encode_error(exc),
                                                   "duration_s": time.perf_counter() - started}, event=event)
            raise
        self.recorder.log(TOPIC_ARM_CALL, {**record, "result": encode_result(result), "error": None,
                                           "duration_s": time.perf_counter() - started}, event=event)
        if isinstance(result, Pose):
            self.recorder.log(TOPIC_FLANGE_POSE, pose_in_frame(result, time.time()))
        return result

    def _connect(self, timeout: float) -> None:
        super()._connect(timeout)
        self.recorder.log(TOPIC_ARM_INFO, {**encode_info(self.inner.info()), "intrinsics": None,
                                           "default_timeout_s": self.inner.default_timeout_s,
                                           "arm_model": self.inner.arm_model().to_dict()})

    def _get_pose(self, timeout: float) -> Pose:
        return self._call("get_pose", {"timeout_s": timeout}, partial(super()._get_pose, timeout))

    def _move_linear(self, pose: Pose, speed: float, acceleration: float, timeout: float) -> None:
        args = {"target": encode_pose(pose), "speed_m_s": speed, "acceleration_m_s2": acceleration,
                "timeout_s": timeout}
        self._call("move_linear", args, partial(super()._move_linear, pose, speed, acceleration, timeout))

    def _stop(self, timeout: float) -> None:
        self._call("stop", {"timeout_s": timeout}, partial(super()._stop, timeout))

    def _joint_positions(self, timeout: float) -> NDArray[np.float64]:
        return self._call("joint_positions", {"timeout_s": timeout}, partial(super()._joint_positions, timeout))

    def _status(self, timeout: float) -> ArmStatus:
        return self._call("status", {"timeout_s": timeout}, partial(super()._status, timeout))

    def _clear_errors(self, timeout: float) -> None:
        self._call("clear_errors", {"timeout_s": timeout}, partial(super()._clear_errors, timeout))
