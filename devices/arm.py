"""The robot arm interface."""

from __future__ import annotations

import math
from abc import abstractmethod

import numpy as np
from numpy.typing import NDArray

from .base import Device
from .errors import CellcalError
from .pose import Pose
from .types import ArmStatus


def _positive(value: float, what: str, unit: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        raise CellcalError(f"{what} must be a positive finite number of {unit}, got {value!r}")
    return float(value)


class RobotArm(Device):
    """A robot arm commanded in Cartesian space.

    Poses are of the tool flange (no TCP offset) in the robot base frame, metres and
    scipy rotations. The camera hangs off the flange through the hand-eye transform,
    which belongs to the cell configuration, not to the arm.

    Attributes:
        default_motion_timeout_s: Timeout for :meth:`move_linear` when given None.
    """

    default_motion_timeout_s: float = 60.0

    def get_pose(self, timeout: float | None = None) -> Pose:
        """Current flange pose in the base frame.

        Raises:
            NotConnectedError, DeviceTimeoutError, DeviceConnectionError, ProtocolError.
        """
        self._require_connected("read the pose")
        return self._get_pose(self._resolve_timeout(timeout))

    def move_linear(self, pose: Pose, *, speed: float, acceleration: float,
                    timeout: float | None = None) -> None:
        """Move the flange in a straight line to ``pose`` and return when it has arrived.

        Args:
            pose: Target flange pose in the base frame.
            speed: Tool speed, m/s.
            acceleration: Tool acceleration, m/s².
            timeout: Seconds to wait for the motion to finish; None uses
                :attr:`default_motion_timeout_s`.

        Raises:
            NotConnectedError: If the arm is not connected.
            DeviceTimeoutError: If the motion has not finished within ``timeout``
                (the arm is told to stop first).
            VendorError: If the controller reports an error during the motion.
            SafetyError: If a safety wrapper rejects the command (nothing moved).
        """
        self._require_connected("move")
        if not isinstance(pose, Pose):
            raise CellcalError(f"move_linear needs a Pose, got {type(pose).__name__}")
        speed = _positive(speed, "speed", "m/s")
        acceleration = _positive(acceleration, "acceleration", "m/s^2")
        t = self.default_motion_timeout_s if timeout is None else self._resolve_timeout(timeout)
        self._move_linear(pose, speed, acceleration, float(t))

    def stop(self, timeout: float | None = None) -> None:
        """Stop any motion now (controlled stop); safe to call when idle."""
        self._require_connected("stop")
        self._stop(self._resolve_timeout(timeout))

    def joint_positions(self, timeout: float | None = None) -> NDArray[np.float64]:
        """Joint positions, radians, one per axis."""
        self._require_connected("read joint positions")
        return np.asarray(self._joint_positions(self._resolve_timeout(timeout)), dtype=np.float64)

    def status(self, timeout: float | None = None) -> ArmStatus:
        """Error / warning state of the arm."""
        self._require_connected("read the status")
        return self._status(self._resolve_timeout(timeout))

    def clear_errors(self, timeout: float | None = None) -> None:
        """Explicit recovery: clear errors and warnings and make the arm ready to move."""
        self._require_connected("clear errors")
        self._clear_errors(self._resolve_timeout(timeout))

    @abstractmethod
    def _get_pose(self, timeout: float) -> Pose: ...

    @abstractmethod
    def _move_linear(self, pose: Pose, speed: float, acceleration: float, timeout: float) -> None: ...

    @abstractmethod
    def _stop(self, timeout: float) -> None: ...

    @abstractmethod
    def _joint_positions(self, timeout: float) -> NDArray[np.float64]: ...

    @abstractmethod
    def _status(self, timeout: float) -> ArmStatus: ...

    @abstractmethod
    def _clear_errors(self, timeout: float) -> None: ...
