"""The robot arm interface, with the arrival check every backend inherits (ADR 0016)."""

from __future__ import annotations

import math
from abc import abstractmethod
from collections.abc import Mapping
from typing import Any, Self

import numpy as np
from numpy.typing import NDArray

from .arm_model import UNSTATED_ARM_MODEL, ArmModel
from .arrival import ArrivalTolerance, arrival_problem, format_pose
from .base import BackendContext, Device
from .errors import CellcalError, ConfigError, MotionError, NativeCrashError
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

    A move counts as done only once the arm has arrived: after the backend reports the
    motion finished, :meth:`move_linear` reads the pose back :attr:`arrival_tolerance`
    ``.reads`` times; the reads must agree with each other and lie within the tolerance
    of the target, or the arm is told to stop and :class:`MotionError` is raised.

    Attributes:
        default_motion_timeout_s: Timeout for :meth:`move_linear` when given None.
        verifies_arrival: Whether :meth:`move_linear` checks the arrival itself; false
            only for arms that delegate every move to another arm which checks it (the
            forwarding wrappers) or that never move anything (a replay).
        model_override: The config's ``[arm.model]`` table over the backend's statement
            (:meth:`arm_model`), or None (issue #39, ADR 0055).
    """

    default_motion_timeout_s: float = 60.0
    verifies_arrival: bool = True
    _arrival_override: ArrivalTolerance | None = None
    model_override: ArmModel | None = None

    @classmethod
    def from_config(cls, section: Mapping[str, Any] | None, context: BackendContext | None = None) -> Self:
        """As :meth:`Device.from_config`; a ``model`` table becomes :attr:`model_override`.

        The table's keys (``repeatability_m``, ``accuracy_m``, ``accuracy_rad``) replace the
        backend's own figures one by one; the others keep the backend's.

        Raises:
            ConfigError: On a bad key or value, naming it (``arm.model.accuracy_m``).
        """
        context = context or BackendContext()
        rest = dict(section or {})
        table = rest.pop("model", None)
        arm = super().from_config(rest, context)
        if table is not None:
            where = f"{context.section or 'arm'}.model"
            if not isinstance(table, Mapping):
                raise ConfigError(f"must be a table, got {type(table).__name__}", source=context.source, key=where)
            arm.model_override = ArmModel.from_dict(table, where=where, source=context.source,
                                                    base=arm._arm_model())
        return arm

    # ------------------------------------------------------------------ what its poses are worth
    def arm_model(self) -> ArmModel:
        """The arm's stated repeatability and absolute accuracy: ``[arm.model]``, else the backend's figures.

        Needs no connection. Every interval that takes this arm's reported poses as known carries them.
        """
        override = self.model_override
        if override is not None:
            return override
        model = self._arm_model()
        if not isinstance(model, ArmModel):  # a backend bug, reported clearly
            raise CellcalError(f"{self.backend_name}: _arm_model returned {type(model).__name__}")
        return model

    def _arm_model(self) -> ArmModel:
        """The backend's statement of its vendor's figures (override; the default states nothing)."""
        return UNSTATED_ARM_MODEL

    # ------------------------------------------------------------------ arrival
    def default_arrival_tolerance(self) -> ArrivalTolerance:
        """The tolerance that fits this arm class (1 mm, 0.1 deg, 2 reads unless a backend says otherwise)."""
        return ArrivalTolerance()

    @property
    def arrival_tolerance(self) -> ArrivalTolerance:
        """The tolerance a finished move is checked against (configured, else the backend's default)."""
        override = self._arrival_override
        return override if override is not None else self.default_arrival_tolerance()

    @arrival_tolerance.setter
    def arrival_tolerance(self, value: ArrivalTolerance) -> None:
        if not isinstance(value, ArrivalTolerance):
            raise CellcalError(f"arrival_tolerance must be an ArrivalTolerance, got {type(value).__name__}")
        self._set_arrival_tolerance(value)

    def _set_arrival_tolerance(self, value: ArrivalTolerance) -> None:
        """Store the configured tolerance (a wrapper also hands it to the arm it wraps)."""
        self._arrival_override = value

    def _confirm_arrival(self, target: Pose) -> None:
        """Read the pose back at rest; stop the arm and raise MotionError unless it is steady at ``target``."""
        tol = self.arrival_tolerance
        try:
            readings = [self._get_pose(self.default_timeout_s) for _ in range(tol.reads)]
        except NativeCrashError:
            raise  # the backend's library died; its message says what became of the arm
        except CellcalError as exc:
            problem = f"the pose could not be read back ({exc})"
        else:
            found = arrival_problem(target, readings, tol)
            if found is None:
                return
            problem = found
        raise MotionError(f"{self.backend_name}: move to {format_pose(target)} reported done, but {problem}; "
                          f"{self._stop_after_failure()}")

    def _stop_after_failure(self) -> str:
        """Tell the arm to stop after a failed move, ignoring errors; says what happened, for messages."""
        try:
            self._stop(self.default_timeout_s)
        except CellcalError as exc:
            return f"stopping the arm failed too: {exc}"
        return "the arm was told to stop"

    def get_pose(self, timeout: float | None = None) -> Pose:
        """Current flange pose in the base frame.

        Raises:
            NotConnectedError: Before ``connect``.
            DeviceTimeoutError: If the read takes longer than ``timeout``.
            DeviceConnectionError: If the link to the arm is lost.
            ProtocolError: If the arm's reply cannot be read.
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
                :attr:`default_motion_timeout_s`. The arrival check's pose reads
                (and a stop after a failure) come on top, each bounded by
                :attr:`default_timeout_s`.

        Raises:
            NotConnectedError: If the arm is not connected.
            DeviceTimeoutError: If the motion has not finished within ``timeout``
                (the arm is told to stop first).
            VendorError: If the controller reports an error during the motion.
            SafetyError: If a safety wrapper rejects the command (nothing moved).
            MotionError: If the motion cannot be confirmed, or it reported done while the
                read-back pose is not at the target or not steady (the arm is told to stop).
        """
        self._require_connected("move")
        if not isinstance(pose, Pose):
            raise CellcalError(f"move_linear needs a Pose, got {type(pose).__name__}")
        speed = _positive(speed, "speed", "m/s")
        acceleration = _positive(acceleration, "acceleration", "m/s^2")
        t = self.default_motion_timeout_s if timeout is None else self._resolve_timeout(timeout)
        self._move_linear(pose, speed, acceleration, float(t))
        if self.verifies_arrival:
            self._confirm_arrival(pose)

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
