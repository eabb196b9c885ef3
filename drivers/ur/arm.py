"""Universal Robots arm over the ``ur_rtde`` library (registered as ``ur``).

Poses are flange poses in the base frame (metres, radians). ``ur_rtde`` is imported
only in :meth:`URArm._connect`; every False it returns becomes a typed error
(:meth:`URArm._raise_failure`). Design: docs/adr/0015-vendor-drivers.md.
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, ClassVar, NoReturn

import numpy as np
from numpy.typing import NDArray

from cellcal.devices.arm import RobotArm
from cellcal.devices.base import BackendContext
from cellcal.devices.errors import (
    DeviceConnectionError,
    DeviceTimeoutError,
    MissingDependencyError,
    ProtocolError,
    SafetyError,
    VendorError,
)
from cellcal.devices.geometry.vendor_poses import pose_from_ur, pose_to_ur
from cellcal.devices.pose import Pose
from cellcal.devices.types import ArmStatus, DeviceInfo
from cellcal.drivers._blocking import BoundedCaller

log = logging.getLogger(__name__)

#: UR's own limits on Cartesian tool motion (URScript ``movel``).
UR_MAX_TOOL_SPEED_M_S = 3.0
UR_MAX_TOOL_ACCELERATION_M_S2 = 150.0

#: RTDE ``safety_mode`` codes (UR RTDE guide).
SAFETY_MODES: dict[int, str] = {
    1: "NORMAL", 2: "REDUCED", 3: "PROTECTIVE_STOP", 4: "RECOVERY", 5: "SAFEGUARD_STOP",
    6: "SYSTEM_EMERGENCY_STOP", 7: "ROBOT_EMERGENCY_STOP", 8: "VIOLATION", 9: "FAULT",
    10: "VALIDATE_JOINT_ID", 11: "UNDEFINED_SAFETY_MODE", 12: "AUTOMATIC_MODE_SAFEGUARD_STOP",
    13: "SYSTEM_THREE_POSITION_ENABLING_STOP",
}
#: RTDE ``robot_mode`` codes (``RTDEReceiveInterface.getRobotMode`` docstring).
ROBOT_MODES: dict[int, str] = {
    -1: "NO_CONTROLLER", 0: "DISCONNECTED", 1: "CONFIRM_SAFETY", 2: "BOOTING", 3: "POWER_OFF",
    4: "POWER_ON", 5: "IDLE", 6: "BACKDRIVE", 7: "RUNNING", 8: "UPDATING_FIRMWARE",
}
#: RTDE ``runtime_state`` codes (program state).
RUNTIME_STATES: dict[int, str] = {
    0: "STOPPING", 1: "STOPPED", 2: "PLAYING", 3: "PAUSING", 4: "PAUSED", 5: "RESUMING",
}
SAFETY_OK = (1, 2)          # NORMAL, REDUCED
ROBOT_MODE_RUNNING = 7


def _name(table: dict[int, str], code: int) -> str:
    return f"{code} {table.get(code, 'UNKNOWN')}"


@dataclass(frozen=True)
class URConfig:
    """``[arm]`` section for ``backend = "ur"``.

    Attributes:
        host: Controller IP address or host name.
        timeout_s: Default I/O timeout, s (connect uses it too: script upload takes ~1 s).
        stale_after_s: A receive timestamp unchanged this long marks a stale stream, s.
        max_speed_m_s: Highest tool speed this backend accepts (<= UR's 3 m/s).
        max_acceleration_m_s2: Highest tool acceleration accepted (<= UR's 150 m/s²).
        stop_deceleration_m_s2: Deceleration used by :meth:`URArm.stop`, m/s².
        arrival_tolerance_m: A finished move must end this close to the target, m.
        arrival_tolerance_rad: ... and this close in orientation, rad.
        poll_interval_s: Status polling period while a move runs, s.
        set_tcp_to_flange: Zero the TCP offset at connect (cellcal poses are flange poses).
        use_dashboard: Use the dashboard server (port 29999) for identity and recovery.
        dashboard_port: Dashboard server port.
        allow_power_on: Let :meth:`URArm.clear_errors` power the arm on and release brakes.
    """

    host: str
    timeout_s: float = field(default=5.0, metadata={"gt": 0, "doc": "default I/O timeout, s"})
    stale_after_s: float = field(default=0.1, metadata={"gt": 0, "le": 10})
    max_speed_m_s: float = field(default=UR_MAX_TOOL_SPEED_M_S,
                                 metadata={"gt": 0, "le": UR_MAX_TOOL_SPEED_M_S})
    max_acceleration_m_s2: float = field(default=UR_MAX_TOOL_ACCELERATION_M_S2,
                                         metadata={"gt": 0, "le": UR_MAX_TOOL_ACCELERATION_M_S2})
    stop_deceleration_m_s2: float = field(default=10.0, metadata={"gt": 0, "le": UR_MAX_TOOL_ACCELERATION_M_S2})
    arrival_tolerance_m: float = field(default=1e-3, metadata={"gt": 0})
    arrival_tolerance_rad: float = field(default=5e-3, metadata={"gt": 0})
    poll_interval_s: float = field(default=0.01, metadata={"gt": 0, "le": 1})
    set_tcp_to_flange: bool = True
    use_dashboard: bool = True
    dashboard_port: int = field(default=29999, metadata={"gt": 0, "lt": 65536})
    allow_power_on: bool = False

    def __post_init__(self) -> None:
        if not self.host.strip():
            raise ValueError("host must not be empty")


class URArm(RobotArm):
    """A Universal Robots arm (CB3 / e-Series / UR Series) over ``ur_rtde`` 1.6.

    Three ``ur_rtde`` interfaces are used, all imported only inside :meth:`_connect`:

    * ``rtde_receive.RTDEReceiveInterface``: pose, joints, timestamp and the status
      calls (``isProtectiveStopped``, ``isEmergencyStopped``, ``getSafetyMode``,
      ``getRobotMode``, ``getRuntimeState``);
    * ``rtde_control.RTDEControlInterface``: ``moveL``, ``stopL``, ``setTcp``,
      ``isProgramRunning``, ``reuploadScript``;
    * ``dashboard_client.DashboardClient`` (optional): identity (model, serial,
      PolyScope version), remote-control check, and recovery in :meth:`clear_errors`
      (``closeSafetyPopup``, ``unlockProtectiveStop``, optionally ``powerOn`` and
      ``brakeRelease``).

    Timeouts: the two RTDE constructors connect (and upload the control script) with
    no timeout parameter, so they run in a :class:`~cellcal.drivers._blocking.BoundedCaller`
    worker joined with the caller's timeout; a constructor that finishes late is
    disconnected by the worker. The dashboard has its own ``connect(timeout_ms)``.
    ``moveL`` is issued *asynchronously* and its completion polled against the motion
    timeout; on timeout the arm is told to ``stopL``.

    Poses are of the flange: with ``set_tcp_to_flange = true`` (default) the TCP offset
    is set to zero at connect, so ``getActualTCPPose`` and ``moveL`` act on the flange.

    Attributes:
        receive_rebuilds: How many times a stale receive interface was rebuilt.
    """

    backend_name: ClassVar[str] = "ur"
    Config: ClassVar[type[URConfig]] = URConfig

    def __init__(self, config: URConfig, context: BackendContext | None = None):
        super().__init__()
        self.config = config
        self.context = context or BackendContext()
        self.default_timeout_s = config.timeout_s
        self.receive_rebuilds = 0
        self._clock: Callable[[], float] = time.monotonic
        self._sleep: Callable[[float], None] = time.sleep
        self._caller = BoundedCaller(f"ur {config.host}")
        self._rtde_control: Any = None
        self._rtde_receive: Any = None
        self._dashboard_mod: Any = None
        self._control: Any = None
        self._receive: Any = None
        self._dashboard: Any = None
        self._last_ts: float | None = None
        self._last_change = 0.0
        self._identity: dict[str, str] = {}

    # ------------------------------------------------------------ life cycle
    def _connect(self, timeout: float) -> None:
        try:
            import rtde_control
            import rtde_receive
        except ImportError:
            raise MissingDependencyError("ur_rtde", "ur") from None
        self._rtde_control, self._rtde_receive = rtde_control, rtde_receive
        deadline = self._clock() + timeout
        self._receive = self._new_receive(deadline)
        self._control = self._bounded(
            lambda: rtde_control.RTDEControlInterface(self.config.host), deadline,
            "open the RTDE control interface (uploads the control script)")
        self._mark_fresh(float(self._receive.getTimestamp()))
        if self.config.set_tcp_to_flange and not self._control.setTcp([0.0] * 6):
            self._raise_failure("setTcp (TCP offset to the flange)")
        if self.config.use_dashboard:
            self._open_dashboard(max(0.05, deadline - self._clock()), required=False)

    def _close(self) -> None:
        for handle in (self._control, self._receive, self._dashboard):
            if handle is not None:
                with contextlib.suppress(Exception):
                    handle.disconnect()
        self._control = self._receive = self._dashboard = None
        self._last_ts = None
        self._caller.join(1.0)

    def _info(self) -> DeviceInfo:
        return DeviceInfo(
            backend="ur", vendor="Universal Robots", model=self._identity.get("model", "UR"),
            serial=self._identity.get("serial", ""), firmware=self._identity.get("polyscope", ""),
            extra={"host": self.config.host, "receive_rebuilds": self.receive_rebuilds},
        )

    # ------------------------------------------------------------ reads
    def _get_pose(self, timeout: float) -> Pose:
        receive = self._fresh_receive(self._clock() + timeout)
        return pose_from_ur(self._vector(receive.getActualTCPPose(), 6, "getActualTCPPose"))

    def _joint_positions(self, timeout: float) -> NDArray[np.float64]:
        receive = self._fresh_receive(self._clock() + timeout)
        return self._vector(receive.getActualQ(), 6, "getActualQ")

    def _status(self, timeout: float) -> ArmStatus:
        receive = self._fresh_receive(self._clock() + timeout)
        safety = int(receive.getSafetyMode())
        robot = int(receive.getRobotMode())
        running = bool(self._control.isProgramRunning())
        if safety not in SAFETY_OK:
            return ArmStatus(error_code=safety, message=f"safety mode {_name(SAFETY_MODES, safety)}",
                             can_move=False)
        warning = safety if safety == 2 else 0
        if robot != ROBOT_MODE_RUNNING:
            return ArmStatus(warning_code=warning, can_move=False,
                             message=f"robot mode {_name(ROBOT_MODES, robot)} (needs power on, brakes released)")
        if not running:
            return ArmStatus(warning_code=warning, can_move=False,
                             message="the RTDE control script is not running on the controller")
        return ArmStatus(warning_code=warning, message="reduced mode" if warning else "", can_move=True)

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
        self._fresh_receive(deadline)
        if not self._control.moveL(target, speed, acceleration, True):
            self._raise_failure("moveL")
        seen_running = False
        while True:
            receive = self._fresh_receive(deadline)
            if receive.isEmergencyStopped() or receive.isProtectiveStopped() \
                    or int(receive.getSafetyMode()) not in SAFETY_OK:
                self._raise_failure("moveL")
            if not self._control.isProgramRunning():
                self._raise_failure("moveL")
            running = bool(self._control.getAsyncOperationProgressEx().isAsyncOperationRunning())
            seen_running = seen_running or running
            if not running:
                actual = pose_from_ur(self._vector(receive.getActualTCPPose(), 6, "getActualTCPPose"))
                if actual.distance_to(pose) <= cfg.arrival_tolerance_m \
                        and actual.angle_to(pose) <= cfg.arrival_tolerance_rad:
                    return
                # The motion ended short: a safety stop that landed after the status read
                # above is the usual cause, so read the status again before concluding.
                receive = self._fresh_receive(deadline)
                if receive.isEmergencyStopped() or receive.isProtectiveStopped() \
                        or int(receive.getSafetyMode()) not in SAFETY_OK or not self._control.isProgramRunning():
                    self._raise_failure("moveL")
                if seen_running:
                    raise VendorError("ur", 0, (
                        f"moveL ended {actual.distance_to(pose) * 1000:.1f} mm / "
                        f"{math.degrees(actual.angle_to(pose)):.2f} deg from the target "
                        "without a safety stop (stopped by another program?)"))
            if self._clock() >= deadline:
                self._stop_quietly()
                raise DeviceTimeoutError(f"ur: moveL did not finish within {timeout:g} s; arm stopped")
            self._sleep(cfg.poll_interval_s)

    def _stop(self, timeout: float) -> None:
        self._control.stopL(self.config.stop_deceleration_m_s2)

    def _clear_errors(self, timeout: float) -> None:
        deadline = self._clock() + timeout
        receive = self._fresh_receive(deadline)
        if receive.isEmergencyStopped():
            self._raise_failure("clear_errors")  # an e-stop is released by hand, never remotely
        if receive.isProtectiveStopped() or int(receive.getSafetyMode()) not in SAFETY_OK \
                or int(receive.getRobotMode()) != ROBOT_MODE_RUNNING:
            dash = self._open_dashboard(max(0.05, deadline - self._clock()), required=True)
            dash.closeSafetyPopup()
            # UR refuses to unlock a protective stop within 5 s of it: retry until the deadline.
            while receive.isProtectiveStopped():
                dash.unlockProtectiveStop()
                if not receive.isProtectiveStopped():
                    break
                if self._clock() >= deadline:
                    self._raise_failure("clear_errors (unlockProtectiveStop)")
                self._sleep(max(self.config.poll_interval_s, 0.1))
                receive = self._fresh_receive(deadline)
            if int(receive.getRobotMode()) != ROBOT_MODE_RUNNING:
                if not self.config.allow_power_on:
                    raise VendorError("ur", int(receive.getRobotMode()), (
                        f"robot mode {_name(ROBOT_MODES, int(receive.getRobotMode()))}: power on and release "
                        "the brakes on the pendant, or set allow_power_on = true"))
                dash.powerOn()
                dash.brakeRelease()
                while int(receive.getRobotMode()) != ROBOT_MODE_RUNNING:
                    if self._clock() >= deadline:
                        raise DeviceTimeoutError(f"ur: arm not RUNNING within {timeout:g} s after power on "
                                                 f"(robot mode {_name(ROBOT_MODES, int(receive.getRobotMode()))})")
                    self._sleep(max(self.config.poll_interval_s, 0.1))
                    receive = self._fresh_receive(deadline)
        if not self._control.isProgramRunning() and not self._control.reuploadScript():
            self._raise_failure("clear_errors (reuploadScript)")
        status = self._status(max(0.05, deadline - self._clock()))
        if not status.ok:
            raise VendorError("ur", status.error_code, f"clear_errors left the arm unable to move: {status.message}")

    # ------------------------------------------------------------ helpers
    def _bounded(self, fn: Callable[[], Any], deadline: float, what: str) -> Any:
        remaining = deadline - self._clock()
        if remaining <= 0:
            raise DeviceTimeoutError(f"ur {self.config.host}: no time left to {what}")
        try:
            return self._caller.call(fn, remaining, what, on_late=lambda h: h.disconnect())
        except RuntimeError as exc:  # ur_rtde reports constructor failures as RuntimeError
            text = str(exc)
            hint = ""
            if "remote control" in text.lower():
                hint = " (switch the pendant to Remote Control)"
            raise DeviceConnectionError(f"ur {self.config.host}: cannot {what}: {text}{hint}") from None

    def _new_receive(self, deadline: float) -> Any:
        rtde_receive = self._rtde_receive
        return self._bounded(lambda: rtde_receive.RTDEReceiveInterface(self.config.host), deadline,
                             "open the RTDE receive interface")

    def _mark_fresh(self, ts: float) -> None:
        self._last_ts = ts
        self._last_change = self._clock()

    def _fresh_receive(self, deadline: float) -> Any:
        """The receive interface, rebuilt first if its timestamp has stopped advancing.

        ``isConnected()`` can stay True on a receive interface whose stream has died
        (values frozen). ``getTimestamp()`` is controller time, advancing at 125-500 Hz;
        a value unchanged for longer than ``stale_after_s`` means a stale stream, and the
        interface is rebuilt (counted in :attr:`receive_rebuilds`).
        """
        ts = float(self._receive.getTimestamp())
        now = self._clock()
        if ts != self._last_ts:
            self._last_ts, self._last_change = ts, now
            return self._receive
        if now - self._last_change <= self.config.stale_after_s:
            return self._receive
        log.warning("ur %s: receive timestamp frozen at %.3f s for %.3f s; rebuilding the interface",
                    self.config.host, ts, now - self._last_change)
        old, self._receive = self._receive, None
        with contextlib.suppress(Exception):
            old.disconnect()
        self._receive = self._new_receive(deadline)
        self.receive_rebuilds += 1
        fresh = float(self._receive.getTimestamp())
        if fresh == ts:
            raise DeviceConnectionError(
                f"ur {self.config.host}: rebuilt receive interface still reports timestamp {ts:.3f} s")
        self._mark_fresh(fresh)
        return self._receive

    def _vector(self, values: Any, n: int, what: str) -> NDArray[np.float64]:
        try:
            arr = np.asarray(values, dtype=np.float64)
        except (TypeError, ValueError):
            raise ProtocolError(f"ur: {what} returned {values!r}, not numbers") from None
        if arr.shape != (n,) or not np.all(np.isfinite(arr)):
            raise ProtocolError(f"ur: {what} returned {arr.tolist()!r}, expected {n} finite numbers")
        return arr

    def _stop_quietly(self) -> None:
        try:
            self._control.stopL(self.config.stop_deceleration_m_s2)
        except Exception:
            log.exception("ur %s: stopL failed", self.config.host)

    def _open_dashboard(self, timeout: float, *, required: bool) -> Any:
        if self._dashboard is not None and self._dashboard.isConnected():
            return self._dashboard
        try:
            import dashboard_client
        except ImportError:
            raise MissingDependencyError("ur_rtde (dashboard_client)", "ur") from None
        dash = dashboard_client.DashboardClient(self.config.host, self.config.dashboard_port)
        try:
            dash.connect(max(1, int(timeout * 1000)))
            self._identity = {"model": str(dash.getRobotModel()), "serial": str(dash.getSerialNumber()),
                              "polyscope": str(dash.polyscopeVersion())}
        except (RuntimeError, OSError) as exc:
            if required:
                raise DeviceConnectionError(
                    f"ur {self.config.host}: dashboard server port {self.config.dashboard_port}: {exc}") from None
            log.warning("ur %s: dashboard unavailable (%s); identity unknown", self.config.host, exc)
            return None
        self._dashboard = dash
        return dash

    def _remote_control_hint(self) -> str:
        dash = self._dashboard
        try:
            if dash is not None and dash.isConnected() and not dash.isInRemoteControl():
                return "; the pendant is in Local Control (switch it to Remote Control)"
        except Exception:
            pass
        return ""

    def _raise_failure(self, operation: str) -> NoReturn:
        """Explain a False return (or a refused motion) from the status calls and raise.

        * emergency / protective / safeguard stop, violation, fault (the robot's own
          safety system stopped it): :class:`VendorError` ``("ur", safety_mode, meaning)``
          with the UR safety-mode code; not :class:`SafetyError`, which in cellcal means
          *our* envelope rejected a command before anything moved;
        * robot not powered / brakes engaged: :class:`VendorError` with the robot-mode code;
        * control script not running (stopped from the pendant, remote control off):
          :class:`VendorError` with the program runtime-state code;
        * lost link: :class:`DeviceConnectionError`.

        Speed / acceleration beyond UR's limits (3 m/s, 150 m/s²) or the configured ones
        are refused earlier, in :meth:`_move_linear`, with :class:`SafetyError` (nothing moved).
        """
        receive = self._receive
        if receive is None or not receive.isConnected() or self._control is None \
                or not self._control.isConnected():
            raise DeviceConnectionError(f"ur {self.config.host}: {operation} failed: RTDE connection lost")
        safety = int(receive.getSafetyMode())
        if receive.isEmergencyStopped():
            raise VendorError("ur", safety, (
                f"{operation} failed: emergency stop engaged (safety mode {_name(SAFETY_MODES, safety)}); "
                "release the e-stop by hand, then call clear_errors()"))
        if receive.isProtectiveStopped():
            raise VendorError("ur", safety, (
                f"{operation} failed: protective stop (safety mode {_name(SAFETY_MODES, safety)}); "
                "remove the cause, then call clear_errors()"))
        if safety not in SAFETY_OK:
            raise VendorError("ur", safety, f"{operation} failed: safety mode {_name(SAFETY_MODES, safety)}")
        robot = int(receive.getRobotMode())
        if robot != ROBOT_MODE_RUNNING:
            raise VendorError("ur", robot, (
                f"{operation} failed: robot mode {_name(ROBOT_MODES, robot)} (power on and release the brakes)"))
        if not self._control.isProgramRunning():
            state = int(receive.getRuntimeState())
            raise VendorError("ur", state, (
                f"{operation} failed: the RTDE control script is not running (program state "
                f"{_name(RUNTIME_STATES, state)}){self._remote_control_hint()}; clear_errors() re-uploads it"))
        raise VendorError("ur", 0, f"{operation} returned False with the arm in normal mode "
                                   "(ur_rtde internal timeout?)")
