"""The motion half of the UR driver: a moveL sent, waited for, checked at its end (:class:`URMotion`).

``moveL`` runs asynchronously on the controller; its completion is polled against the
motion timeout through ur_rtde's async operation register, every lost link on the way is
one "contact lost during moveL", and the received pose is read until it settles at the
target. A command that returns False is explained from the arm's state (:mod:`.status`).
The links themselves (connect, fresh receive interface, bounded commands) are
:class:`~cellcal.drivers.ur.arm.URArm`'s. Poses: flange in the base frame, metres, radians.
"""

from __future__ import annotations

import math
from abc import abstractmethod
from collections.abc import Callable
from typing import Any, NoReturn

import numpy as np
from numpy.typing import NDArray

from cellcal.devices.arm import RobotArm
from cellcal.devices.errors import (
    CellcalError,
    DeviceConnectionError,
    DeviceTimeoutError,
    MotionError,
    NativeCrashError,
    ProtocolError,
    SafetyError,
    VendorError,
)
from cellcal.devices.geometry.vendor_poses import pose_from_ur, pose_to_ur
from cellcal.devices.pose import Pose

from .config import UR_MAX_TOOL_ACCELERATION_M_S2, UR_MAX_TOOL_SPEED_M_S, URConfig
from .dashboard import DashboardLink
from .status import not_ready_reason, raise_known_cause

__all__ = ["SETTLE_PACKAGES", "SETTLE_S", "URMotion"]

#: After a move, a pose short of the target is read again until this many newer receive
#: packages arrived (or for at most SETTLE_S seconds).
SETTLE_PACKAGES = 3
SETTLE_S = 0.2


class URMotion(RobotArm):
    """A UR arm's moves over ur_rtde: ``moveL`` sent once, its end waited for and checked.

    The links are the subclass's (:class:`~cellcal.drivers.ur.arm.URArm`): it provides the
    attributes annotated here and the abstract link methods below.
    """

    config: URConfig
    _clock: Callable[[], float]
    _sleep: Callable[[float], None]
    #: The receive interface (None while it is being rebuilt or after close).
    _receive: Any
    _dash: DashboardLink
    #: What became of the arm when ur_rtde's worker died ("" while it lives).
    _crash_stop: str

    # ------------------------------------------------------------ the links (URArm's)
    @abstractmethod
    def _fresh_receive(self, deadline: float) -> Any:
        """The receive interface, rebuilt first if it is stale."""

    @abstractmethod
    def _require_control_link(self, what: str) -> None:
        """Raise DeviceConnectionError unless the control link is up."""

    @abstractmethod
    def _async_status(self) -> Any:
        """The control interface's async operation register (``getAsyncOperationProgressEx``)."""

    @abstractmethod
    def _command(self, fn: Callable[[Any], Any], deadline: float, what: str) -> Any:
        """Run a control-interface command, bounded by ``deadline``."""

    @abstractmethod
    def _tcp_pose(self, receive: Any) -> NDArray[np.float64]:
        """The reported TCP pose ``[x, y, z, rx, ry, rz]`` (m, rad)."""

    # ------------------------------------------------------------ motion
    def _move_linear(self, pose: Pose, speed: float, acceleration: float, timeout: float) -> None:
        cfg = self.config
        if speed > cfg.max_speed_m_s:
            raise SafetyError(f"ur: speed {speed:g} m/s exceeds the limit {cfg.max_speed_m_s:g} m/s "
                              f"(UR allows at most {UR_MAX_TOOL_SPEED_M_S:g}); nothing moved")
        if acceleration > cfg.max_acceleration_m_s2:
            raise SafetyError(f"ur: acceleration {acceleration:g} m/s^2 exceeds the limit "
                              f"{cfg.max_acceleration_m_s2:g} m/s^2 (UR allows at most "
                              f"{UR_MAX_TOOL_ACCELERATION_M_S2:g}); nothing moved")
        deadline = self._clock() + timeout
        target = [float(v) for v in pose_to_ur(pose)]
        receive = self._fresh_receive(deadline)
        if not_ready_reason(receive):
            self._raise_failure("moveL")
        before = self._async_status().operationId()
        try:
            accepted = self._command(lambda c: c.moveL(target, speed, acceleration, True), deadline, "moveL")
        except DeviceTimeoutError as exc:
            raise MotionError(f"ur: moveL was not confirmed ({exc}); the command was not sent again; "
                              f"{self._stop_quietly()}") from None
        if not accepted:
            self._raise_failure("moveL")
        self._await_motion(pose, int(before), deadline, timeout)

    def _await_motion(self, pose: Pose, before: int, deadline: float, timeout: float) -> None:
        """Poll until the asynchronous moveL ``before`` was followed by has finished at ``pose``."""
        seen = False
        while True:
            try:  # the link may go at any of these reads: each is the same contact lost during the move
                receive = self._fresh_receive(deadline)
                self._require_control_link("moveL")
                status = self._async_status()
            except NativeCrashError:
                raise  # the worker told the arm to stop on its way out; its message says so
            except (DeviceConnectionError, DeviceTimeoutError, ProtocolError) as exc:
                raise MotionError(f"ur: contact lost during moveL ({exc}); the command was not sent again; "
                                  f"{self._stop_quietly()}") from None
            if not_ready_reason(receive):
                self._raise_failure("moveL")
            running = bool(status.isAsyncOperationRunning())
            seen = seen or running or int(status.operationId()) != before
            if seen and not running:
                self._check_arrival(receive, pose)
                return
            if self._clock() >= deadline:
                raise DeviceTimeoutError(f"ur: moveL did not finish within {timeout:g} s; {self._stop_quietly()}")
            self._sleep(self.config.poll_interval_s)

    def _check_arrival(self, receive: Any, pose: Pose) -> None:
        """After the control script reported the move finished: the received pose must be at ``pose``.

        The receive interface has its own RTDE connection, which can lag the control
        interface's by a package or two; a pose short of the target is read again until
        the receive timestamp has advanced :data:`SETTLE_PACKAGES` times.
        """
        cfg = self.config
        # wait for the read-back to settle within the contract's tolerance (checked next by
        # RobotArm) as well as this driver's own, so that check does not read a lagging package
        contract = self.arrival_tolerance
        tight_m, tight_rad = min(cfg.arrival_tolerance_m, contract.position_m), \
            min(cfg.arrival_tolerance_rad, contract.angle_rad)
        last, fresh = float(receive.getTimestamp()), 0
        until = self._clock() + SETTLE_S
        while True:
            actual = pose_from_ur(self._tcp_pose(receive))
            if actual.distance_to(pose) <= tight_m and actual.angle_to(pose) <= tight_rad:
                return
            if fresh >= SETTLE_PACKAGES or self._clock() >= until:
                break
            self._sleep(0.002)
            receive = self._fresh_receive(until + cfg.timeout_s)
            ts = float(receive.getTimestamp())
            fresh, last = (fresh + 1, ts) if ts != last else (fresh, last)
        if actual.distance_to(pose) <= cfg.arrival_tolerance_m and actual.angle_to(pose) <= cfg.arrival_tolerance_rad:
            return  # within this driver's tolerance: RobotArm's arrival check judges the rest
        # The motion ended short: a safety stop that landed after the status read above is the
        # usual cause, so read the status again before concluding.
        if not_ready_reason(receive):
            self._raise_failure("moveL")
        raise VendorError("ur", 0, (
            f"moveL ended {actual.distance_to(pose) * 1000:.1f} mm / {math.degrees(actual.angle_to(pose)):.2f} deg "
            "from the target without a safety stop (stopped by another program?)"))

    def _stop_quietly(self) -> str:
        """Tell the arm to stop, ignoring errors; says what happened, for messages."""
        if self._crash_stop:  # ur_rtde's worker died and the dashboard was asked already
            return self._crash_stop
        try:
            self._stop(self.config.timeout_s)
        except CellcalError as exc:
            return f"the arm could not be told to stop ({exc})"
        return "the arm was told to stop"

    # ------------------------------------------------------------ failures
    def _raise_failure(self, operation: str) -> NoReturn:
        """Explain a False return (or a refused motion) from the receive interface's state and raise.

        :class:`VendorError` with the safety-mode code (the robot's own safety system stopped
        it: not :class:`SafetyError`, which means *our* envelope refused a command), the
        robot-mode code (not powered, brakes on) or the program-state code (control script
        not running); :class:`DeviceConnectionError` for a lost link (ADR 0015).
        """
        receive = self._receive
        if receive is None or not receive.isConnected():
            raise DeviceConnectionError(f"ur {self.config.host}: {operation} failed: RTDE connection lost")
        self._require_control_link(f"{operation} failed")
        # The control link can see the cause a package or two before the receive link does.
        last, fresh = float(receive.getTimestamp()), 0
        until = self._clock() + SETTLE_S
        while True:
            raise_known_cause(receive, operation, self._dash.remote_control_hint)
            if fresh >= SETTLE_PACKAGES or self._clock() >= until:
                break
            self._sleep(0.002)
            ts = float(receive.getTimestamp())
            fresh, last = (fresh + 1, ts) if ts != last else (fresh, last)
        raise VendorError("ur", 0, f"{operation} returned False with the arm in normal mode "
                                   "(ur_rtde internal timeout?)")
