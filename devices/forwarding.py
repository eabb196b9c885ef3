"""Wrappers around an inner device: every backend hook forwards to ``self.inner``.

:class:`ForwardingCamera` and :class:`ForwardingArm` are the base of the devices that
add behaviour around another one (the safety envelope, the session recorder); a
subclass overrides only the hooks it changes.
"""

from __future__ import annotations

from typing import Generic, TypeVar

import numpy as np
from numpy.typing import NDArray

from .arm import RobotArm
from .arm_model import ArmModel
from .arrival import ArrivalTolerance
from .base import Device
from .camera import Camera3D
from .measurement import MeasurementModel
from .pose import Pose
from .types import ArmStatus, DeviceInfo, Frame, Intrinsics

D = TypeVar("D", bound=Device)


class ForwardingDevice(Device, Generic[D]):
    """A device that drives the life cycle of ``inner`` and takes over its name and timeouts.

    Args:
        inner: The wrapped device; connect and close it through this wrapper.

    Attributes:
        inner: The wrapped device.
    """

    def __init__(self, inner: D) -> None:
        super().__init__()
        self.inner = inner
        self.backend_name = inner.backend_name  # type: ignore[misc]
        self.default_timeout_s = inner.default_timeout_s

    @property
    def connect_timeout_s(self) -> float:
        """The wrapped device's (it may start an emulator first)."""
        return self.inner.connect_timeout_s

    def _connect(self, timeout: float) -> None:
        self.inner.connect(timeout)

    def _close(self) -> None:
        self.inner.close()

    def _info(self) -> DeviceInfo:
        return self.inner.info()


class ForwardingCamera(ForwardingDevice[Camera3D], Camera3D):
    """A :class:`Camera3D` that forwards every call to the camera ``inner``."""

    def _capture(self, timeout: float) -> Frame:
        return self.inner.capture(timeout)

    def _intrinsics(self) -> Intrinsics:
        return self.inner.intrinsics

    def _configured_intrinsics(self) -> Intrinsics | None:
        return self.inner.configured_intrinsics()

    def _measurement_model(self) -> MeasurementModel:
        return self.inner.measurement_model


class ForwardingArm(ForwardingDevice[RobotArm], RobotArm):
    """A :class:`RobotArm` that forwards every call to the arm ``inner`` (motion timeout included).

    The arrival of a move is checked once, by ``inner`` (its ``move_linear``); a tolerance
    set on the wrapper is handed down to it.
    """

    verifies_arrival = False

    def __init__(self, inner: RobotArm) -> None:
        super().__init__(inner)
        self.default_motion_timeout_s = inner.default_motion_timeout_s

    def default_arrival_tolerance(self) -> ArrivalTolerance:
        return self.inner.arrival_tolerance

    def _set_arrival_tolerance(self, value: ArrivalTolerance) -> None:
        self.inner.arrival_tolerance = value  # the wrapper keeps none of its own: it reads the inner's

    def _arm_model(self) -> ArmModel:
        return self.inner.arm_model()

    def _get_pose(self, timeout: float) -> Pose:
        return self.inner.get_pose(timeout)

    def _move_linear(self, pose: Pose, speed: float, acceleration: float, timeout: float) -> None:
        self.inner.move_linear(pose, speed=speed, acceleration=acceleration, timeout=timeout)

    def _stop(self, timeout: float) -> None:
        self.inner.stop(timeout)

    def _joint_positions(self, timeout: float) -> NDArray[np.float64]:
        return self.inner.joint_positions(timeout)

    def _status(self, timeout: float) -> ArmStatus:
        return self.inner.status(timeout)

    def _clear_errors(self, timeout: float) -> None:
        self.inner.clear_errors(timeout)
