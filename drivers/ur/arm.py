"""Universal Robots arm over the ``ur_rtde`` library (registered as ``ur``).

Poses are flange poses in the base frame (metres, radians). ``ur_rtde`` is imported
only in :meth:`URArm._connect`; every False it returns becomes a typed error
(:meth:`URArm._raise_failure`). Design: docs/adr/0015-vendor-drivers.md; what the real
conversation with ur_rtde 1.6.5 taught (GIL, script start, reconnects): docs/adr/0017-ur-emulator.md.
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
import traceback
from collections.abc import Callable, Mapping, Sequence
from typing import Any, ClassVar, NoReturn

import numpy as np
from numpy.typing import NDArray

from cellcal.devices.arm import RobotArm
from cellcal.devices.base import BackendContext
from cellcal.devices.discovery import HostScan
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
from cellcal.devices.isolation import InlineHost, NativeHost
from cellcal.devices.pose import Pose
from cellcal.devices.types import ArmStatus, DeviceInfo

from . import availability, discover
from .codes import (
    FLAG_NO_WAIT,
    ROBOT_MODE_RUNNING,
    ROBOT_MODES,
    RUNTIME_STATES,
    SAFETY_MODES,
    SAFETY_OK,
    SAFETY_REDUCED,
    STATUS_PROGRAM_RUNNING,
    name,
)
from .config import UR_MAX_TOOL_ACCELERATION_M_S2, UR_MAX_TOOL_SPEED_M_S, URConfig
from .dashboard import DashboardLink, stop_program
from .fd_capture import captured_output
from .limits import checked_mode, checked_tcp
from .rtde_probe import probe_stream

log = logging.getLogger(__name__)

#: Seconds the dashboard gets to stop the program after ur_rtde's worker process died.
CRASH_STOP_TIMEOUT_S = 1.0
#: After a move, a pose short of the target is read again until this many newer receive
#: packages arrived (or for at most SETTLE_S seconds).
SETTLE_PACKAGES = 3
SETTLE_S = 0.2


def _safety(receive: Any) -> int:
    """The receive interface's safety mode, checked against the documented set."""
    return checked_mode(receive.getSafetyMode(), SAFETY_MODES, "getSafetyMode")


def _robot(receive: Any) -> int:
    """The receive interface's robot mode, checked against the documented set."""
    return checked_mode(receive.getRobotMode(), ROBOT_MODES, "getRobotMode")


def _runtime(receive: Any) -> int:
    """The receive interface's program state, checked against the documented set."""
    return checked_mode(receive.getRuntimeState(), RUNTIME_STATES, "getRuntimeState")


class URArm(RobotArm):
    """A Universal Robots arm (CB3 / e-Series / UR Series) over ``ur_rtde`` 1.6.

    Three ``ur_rtde`` interfaces are used, all imported only inside :meth:`_connect`:

    * ``rtde_receive.RTDEReceiveInterface``: pose, joints, timestamp, safety, robot
      mode, program state (``getRobotStatus``) — every state the driver decides on;
    * ``rtde_control.RTDEControlInterface``, opened with ``FLAG_NO_WAIT`` and no script
      upload: the driver uploads the control script itself (``reuploadScript``) and
      waits for it with its own deadline; commands ``moveL``, ``stopL``, ``setTcp``;
      the async operation register (``getAsyncOperationProgressEx``);
    * ``dashboard_client.DashboardClient`` (optional): identity, remote-control check,
      recovery in :meth:`clear_errors`.

    Timeouts: ur_rtde's Python constructors hold the GIL, so no thread can time them
    out; the driver keeps them short instead (no script wait in the control
    constructor, a plain-socket probe of the stream before a receive interface is
    rebuilt). Commands run in a :class:`~cellcal.drivers._blocking.BoundedCaller`
    worker (a control interface that lost its link can block forever in them), and
    none is sent once the control link reports itself disconnected. ``moveL`` is
    asynchronous, its completion polled against the motion timeout; on timeout the arm
    is told to ``stopL``.

    Poses are of the flange: with ``set_tcp_to_flange = true`` (default) the TCP offset
    is set to zero whenever the control script starts.

    Attributes:
        receive_rebuilds: How many times a stale receive interface was rebuilt.
    """

    backend_name: ClassVar[str] = "ur"
    #: ur_rtde is C++: it runs in a worker process unless ``isolate = false`` (ADR 0038).
    wraps_native_code: ClassVar[bool] = True
    Config: ClassVar[type[URConfig]] = URConfig

    # ------------------------------------------------------------ network discovery
    #: Standard ports by service name (``cellcal devices --scan --ports NAME=PORT``).
    scan_ports: ClassVar[Mapping[str, int]] = discover.PORTS
    #: Where a scan without ``--hosts`` / ``--subnet`` looks (``--factory``): nowhere, UR ships with DHCP.
    factory_hosts: ClassVar[tuple[str, ...]] = discover.FACTORY_HOSTS

    @classmethod
    def scan_hosts(cls, hosts: Sequence[str] | None, timeout: float,
                   ports: Mapping[str, int] | None = None) -> HostScan:
        """UR controllers among ``hosts`` within ``timeout`` seconds (:mod:`.discover`; no ur_rtde)."""
        return discover.scan_hosts(hosts, timeout, ports)

    def __init__(self, config: URConfig, context: BackendContext | None = None):
        super().__init__()
        self.config = config
        self.context = context or BackendContext()
        self.default_timeout_s = config.timeout_s
        self.receive_rebuilds = 0
        self._clock: Callable[[], float] = time.monotonic
        self._sleep: Callable[[float], None] = time.sleep
        self._probe: Callable[[str, float], float] = probe_stream
        self._host: NativeHost | InlineHost = self._new_host()
        self._crash_stop = ""
        self._rtde_control: Any = None
        self._rtde_receive: Any = None
        self._control: Any = None
        self._receive: Any = None
        self._dash = DashboardLink(config.host, config.dashboard_port, load=self._load)
        self._last_ts: float | None = None
        self._last_change = 0.0
        #: The controller turned a new connection away: treat every link to it as down.
        self._link_down = False

    @classmethod
    def unavailable_reason(cls) -> str | None:
        """Why ur_rtde cannot be used here (not installed, no wheel for this Python), or None."""
        return availability.unavailable_reason()

    # ------------------------------------------------------------ life cycle
    def _new_host(self) -> NativeHost | InlineHost:
        """Where ur_rtde runs: a worker process (``isolate = true``) or this process."""
        name = f"ur {self.config.host}"
        if not self.config.isolate:
            return InlineHost(name, library="ur_rtde", backend="ur")
        return NativeHost(name, library="ur_rtde", backend="ur", default_timeout_s=self.config.timeout_s,
                          on_crash=self._stop_after_crash)

    def _load(self, module: str) -> Any:
        """Import one of ur_rtde's modules where ur_rtde runs (MissingDependencyError if it is not installed)."""
        try:
            return self._host.module(module)
        except ImportError:
            raise availability.missing_error() from None

    def _stop_after_crash(self) -> str:
        """ur_rtde's worker died: tell the arm to stop over the dashboard, a plain socket (never raises)."""
        try:
            stop_program(self.config.host, self.config.dashboard_port, CRASH_STOP_TIMEOUT_S)
        except CellcalError as exc:
            self._crash_stop = f"the arm could not be told to stop ({exc})"
        else:
            self._crash_stop = f"the arm was told to stop (dashboard 'stop', port {self.config.dashboard_port})"
        return self._crash_stop

    def _connect(self, timeout: float) -> None:
        deadline = self._clock() + timeout
        if self.unavailable_reason() is not None:  # said here, before a worker is started for nothing
            raise availability.missing_error()
        # A plain-socket RTDE exchange first: one clear error for a refused port, an unreachable host or a
        # silent stream, within the deadline (ur_rtde's constructors would hold the GIL for 2.5 s, and
        # its dashboard client says "Timeout" for a refused port); no worker is started for nothing.
        self._probe(self.config.host, self._remaining(deadline))
        if self._host.isolated:
            self._host = self._new_host()  # a fresh worker for every connection
            self._crash_stop = ""
        self._host.start(self._remaining(deadline))
        self._rtde_control, self._rtde_receive = self._load("rtde_control"), self._load("rtde_receive")
        try:
            self._open_interfaces(deadline)
        except BaseException as exc:
            # The traceback's frames hold the ur_rtde objects: free them, so that close() (next, in
            # connect) destroys them once (~0.5 s each) instead of disconnecting and leaving them alive.
            traceback.clear_frames(exc.__traceback__)
            raise

    def _open_interfaces(self, deadline: float) -> None:
        if self.config.use_dashboard:
            self._dash.open(self._remaining(deadline), required=False)
            self._dash.require_remote_control()
        self._receive = self._new_receive(deadline)
        self._await_stream(self._receive, deadline)
        rtde_control = self._rtde_control
        self._control = self._bounded(lambda: rtde_control.RTDEControlInterface(self.config.host, flags=FLAG_NO_WAIT),
                                      deadline, "open the RTDE control interface")
        if self._ready_for_program(self._receive):
            self._start_script(deadline)
        else:  # status() says why; clear_errors() starts the script once the arm can run it
            log.warning("ur %s: the arm cannot run programs yet (%s); control script not started",
                        self.config.host, self._not_ready_reason(self._receive))

    def _close(self) -> None:
        handles = [h for h in (self._control, self._receive) if h is not None]
        self._control = self._receive = None
        self._last_ts = None
        self._link_down = False
        self._dash.close()
        for handle in handles:  # freed in order; their destructors disconnect
            self._host.drop(handle, disconnect=False)
        del handles
        self._host.close()

    def _info(self) -> DeviceInfo:
        return DeviceInfo(
            backend="ur", vendor="Universal Robots", model=self._dash.identity.get("model", "UR"),
            serial=self._dash.identity.get("serial", ""), firmware=self._dash.identity.get("polyscope", ""),
            extra={"host": self.config.host, "receive_rebuilds": self.receive_rebuilds},
        )

    # ------------------------------------------------------------ reads
    def _get_pose(self, timeout: float) -> Pose:
        receive = self._fresh_receive(self._clock() + timeout)
        return pose_from_ur(self._tcp_pose(receive))

    def _joint_positions(self, timeout: float) -> NDArray[np.float64]:
        receive = self._fresh_receive(self._clock() + timeout)
        return self._vector(receive.getActualQ(), 6, "getActualQ")

    def _status(self, timeout: float) -> ArmStatus:
        receive = self._fresh_receive(self._clock() + timeout)
        safety = _safety(receive)
        if safety not in SAFETY_OK:
            return ArmStatus(error_code=safety, message=f"safety mode {name(SAFETY_MODES, safety)}",
                             can_move=False)
        warning = safety if safety == SAFETY_REDUCED else 0
        reason = self._not_ready_reason(receive)
        if reason:
            return ArmStatus(warning_code=warning, can_move=False, message=reason)
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
        receive = self._fresh_receive(deadline)
        if self._not_ready_reason(receive):
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
            if self._not_ready_reason(receive):
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
        if self._not_ready_reason(receive):
            self._raise_failure("moveL")
        raise VendorError("ur", 0, (
            f"moveL ended {actual.distance_to(pose) * 1000:.1f} mm / {math.degrees(actual.angle_to(pose)):.2f} deg "
            "from the target without a safety stop (stopped by another program?)"))

    def _stop(self, timeout: float) -> None:
        decel = self.config.stop_deceleration_m_s2
        self._command(lambda c: c.stopL(decel), self._clock() + timeout, "stopL")

    # ------------------------------------------------------------ recovery
    def _clear_errors(self, timeout: float) -> None:
        deadline = self._clock() + timeout
        receive = self._fresh_receive(deadline)
        if receive.isEmergencyStopped():
            self._raise_failure("clear_errors")  # an e-stop is released by hand, never remotely
        if receive.isProtectiveStopped() or _safety(receive) not in SAFETY_OK \
                or _robot(receive) != ROBOT_MODE_RUNNING:
            dash = self._dash.open(self._remaining(deadline), required=True)
            self._dash.call("closeSafetyPopup", "close safety popup")
            self._unlock_protective_stop(dash, deadline)
            self._power_up(deadline, timeout)
        if not self._program_running(self._fresh_receive(deadline)):
            self._start_script(deadline)
        status = self._status(self._remaining(deadline))
        if not status.ok:
            raise VendorError("ur", status.error_code, f"clear_errors left the arm unable to move: {status.message}")

    def _unlock_protective_stop(self, dash: Any, deadline: float) -> None:
        """Unlock a protective stop; UR refuses within 5 s of it, so retry until ``deadline``."""
        refusal = ""
        while self._fresh_receive(deadline).isProtectiveStopped():
            try:
                dash.unlockProtectiveStop()
            except RuntimeError as exc:  # ur_rtde raises when the controller refuses
                refusal = str(exc)
            if self._clock() >= deadline:
                raise VendorError("ur", _safety(self._fresh_receive(deadline)), (
                    f"clear_errors could not unlock the protective stop in time ({refusal or 'still stopped'})"))
            self._sleep(max(self.config.poll_interval_s, 0.05))

    def _power_up(self, deadline: float, timeout: float) -> None:
        receive = self._fresh_receive(deadline)
        robot = _robot(receive)
        if robot == ROBOT_MODE_RUNNING:
            return
        if not self.config.allow_power_on:
            raise VendorError("ur", robot, (
                f"robot mode {name(ROBOT_MODES, robot)}: power on and release the brakes on the pendant, "
                "or set allow_power_on = true"))
        self._dash.call("powerOn", "power on")
        self._dash.call("brakeRelease", "brake release")
        while _robot(receive) != ROBOT_MODE_RUNNING:
            if self._clock() >= deadline:
                raise DeviceTimeoutError(f"ur: arm not RUNNING within {timeout:g} s after power on "
                                         f"(robot mode {name(ROBOT_MODES, _robot(receive))})")
            self._sleep(max(self.config.poll_interval_s, 0.05))
            receive = self._fresh_receive(deadline)

    def _start_script(self, deadline: float) -> None:
        """Upload ur_rtde's control script, wait (bounded) until it runs, then zero the TCP offset."""
        if not self._command(lambda c: c.reuploadScript(), deadline, "reuploadScript"):
            self._raise_failure("start the control script (reuploadScript)")
        receive = self._fresh_receive(deadline)
        # Both links must see it: ur_rtde refuses commands while its own stream says STOPPED.
        while not (self._program_running(receive) and self._control.isProgramRunning()):
            if self._clock() >= deadline:
                state = _runtime(receive)
                raise DeviceTimeoutError(
                    f"ur {self.config.host}: the control script did not start in time (program state "
                    f"{name(RUNTIME_STATES, state)}; {self._not_ready_reason(receive) or 'arm ready'})"
                    f"{self._dash.remote_control_hint()}")
            self._sleep(self.config.poll_interval_s)
            receive = self._fresh_receive(deadline)
        if self.config.set_tcp_to_flange and not self._command(lambda c: c.setTcp([0.0] * 6), deadline, "setTcp"):
            self._raise_failure("setTcp (TCP offset to the flange)")

    # ------------------------------------------------------------ state helpers
    @staticmethod
    def _program_running(receive: Any) -> bool:
        return bool(int(receive.getRobotStatus()) & STATUS_PROGRAM_RUNNING)

    @staticmethod
    def _ready_for_program(receive: Any) -> bool:
        return _safety(receive) in SAFETY_OK and _robot(receive) == ROBOT_MODE_RUNNING

    def _not_ready_reason(self, receive: Any) -> str:
        """Why the arm cannot move now ("" when it can): safety, power, or the control script."""
        safety = _safety(receive)
        if safety not in SAFETY_OK:
            return f"safety mode {name(SAFETY_MODES, safety)}"
        robot = _robot(receive)
        if robot != ROBOT_MODE_RUNNING:
            return f"robot mode {name(ROBOT_MODES, robot)} (needs power on, brakes released)"
        if not self._program_running(receive):
            return "the RTDE control script is not running on the controller"
        return ""

    def _async_status(self) -> Any:
        self._require_control_link("read the motion state")
        return self._control.getAsyncOperationProgressEx()

    # ------------------------------------------------------------ vendor calls
    def _remaining(self, deadline: float) -> float:
        return max(0.05, deadline - self._clock())

    def _bounded(self, fn: Callable[[], Any], deadline: float, what: str) -> Any:
        remaining = deadline - self._clock()
        if remaining <= 0:
            raise DeviceTimeoutError(f"ur {self.config.host}: no time left to {what}")
        try:
            # ur_rtde's constructors print their own lines from C++: to the debug log, not the terminal
            quiet = captured_output(f"ur {self.config.host}: {what}") if not self._host.isolated \
                else contextlib.nullcontext()  # a worker's own output goes to the debug log already
            with quiet:
                return self._host.bounded(fn, remaining, what, on_late=lambda h: h.disconnect())
        except RuntimeError as exc:  # ur_rtde reports constructor failures as RuntimeError
            text = str(exc)
            hint = " (switch the pendant to Remote Control)" if "remote control" in text.lower() else ""
            raise DeviceConnectionError(f"ur {self.config.host}: cannot {what}: {text}{hint}") from None

    def _require_control_link(self, what: str) -> None:
        control = self._control
        if control is None or not control.isConnected():
            raise DeviceConnectionError(f"ur {self.config.host}: {what}: the RTDE control connection is lost")
        if self._link_down:
            raise DeviceConnectionError(f"ur {self.config.host}: {what}: the controller refuses new RTDE "
                                        "connections (its links are gone; no command is sent)")

    def _command(self, fn: Callable[[Any], Any], deadline: float, what: str) -> Any:
        """Run a control-interface command in a bounded worker; never on a control link known to be down."""
        self._require_control_link(what)
        control = self._control
        remaining = min(self._remaining(deadline), self.config.timeout_s)
        return self._host.bounded(lambda: fn(control), remaining, what)

    def _stop_quietly(self) -> str:
        """Tell the arm to stop, ignoring errors; says what happened, for messages."""
        if self._crash_stop:  # ur_rtde's worker died and the dashboard was asked already
            return self._crash_stop
        try:
            self._stop(self.config.timeout_s)
        except CellcalError as exc:
            return f"the arm could not be told to stop ({exc})"
        return "the arm was told to stop"

    def _new_receive(self, deadline: float) -> Any:
        rtde_receive = self._rtde_receive
        return self._bounded(lambda: rtde_receive.RTDEReceiveInterface(self.config.host), deadline,
                             "open the RTDE receive interface")

    def _await_stream(self, receive: Any, deadline: float) -> None:
        """Wait until a new receive interface reports an advancing controller timestamp."""
        first = float(receive.getTimestamp())
        until = min(deadline, self._clock() + max(4 * self.config.stale_after_s, 0.5))
        while True:
            ts = float(receive.getTimestamp())
            if receive.isConnected() and ts > 0.0 and ts != first:
                self._mark_fresh(ts)
                return
            if self._clock() >= until:
                with contextlib.suppress(Exception):
                    receive.disconnect()
                raise DeviceConnectionError(f"ur {self.config.host}: the RTDE receive stream does not advance "
                                            f"(timestamp {ts:.3f} s, connected={bool(receive.isConnected())})")
            self._sleep(min(self.config.poll_interval_s, 0.01))

    def _mark_fresh(self, ts: float) -> None:
        self._last_ts = ts
        self._last_change = self._clock()

    def _fresh_receive(self, deadline: float) -> Any:
        """The receive interface, rebuilt first if it is disconnected or its timestamp stopped advancing.

        ``isConnected()`` can stay True on a receive interface whose stream has died (values
        frozen). ``getTimestamp()`` is controller time, advancing at 125-500 Hz; a value
        unchanged for longer than ``stale_after_s`` means a stale stream.
        """
        receive = self._receive
        if receive is None:
            return self._rebuild_receive(deadline, "no receive interface (the last one was stale)")
        if not receive.isConnected():
            return self._rebuild_receive(deadline, "the receive interface reports a lost connection")
        ts = float(receive.getTimestamp())
        now = self._clock()
        if ts != self._last_ts:
            self._last_ts, self._last_change = ts, now
            return receive
        if now - self._last_change <= self.config.stale_after_s:
            return receive
        return self._rebuild_receive(deadline, f"receive timestamp frozen at {ts:.3f} s for "
                                               f"{now - self._last_change:.3f} s")

    def _rebuild_receive(self, deadline: float, why: str) -> Any:
        """Replace the receive interface, after checking with a plain socket that the controller streams."""
        log.warning("ur %s: %s; rebuilding the receive interface", self.config.host, why)
        old, self._receive = self._receive, None
        if old is not None:
            # A stale interface can take ur_rtde's 2.5 s read timeout to disconnect. In a worker it is
            # handed to the worker's reaper, which alone holds it from then on; in-process it is
            # disconnected here, on this thread. No other thread ever touches it.
            self._host.drop(old)
        del old
        # A controller that streams sends its first package within a few ms: no need to wait out the deadline.
        probe_s = min(self._remaining(deadline), max(0.5, 4 * self.config.stale_after_s))
        try:
            self._probe(self.config.host, probe_s)
        except CellcalError as exc:
            # Refused, reset or closed: the controller's links are gone, the control link's too,
            # even before it notices (ur_rtde would then block for ever in any command).
            self._link_down = isinstance(exc, DeviceConnectionError)
            raise DeviceConnectionError(f"ur {self.config.host}: {why}, and a new RTDE stream fails: {exc}") from None
        self._link_down = False
        receive = self._new_receive(deadline)
        self._await_stream(receive, deadline)
        self._receive = receive
        self.receive_rebuilds += 1
        return receive

    def _tcp_pose(self, receive: Any) -> NDArray[np.float64]:
        """The reported TCP pose ``[x, y, z, rx, ry, rz]`` (m, rad), checked against the model's reach."""
        values = self._vector(receive.getActualTCPPose(), 6, "getActualTCPPose")
        return checked_tcp(values, str(self._dash.identity.get("model", "")), "getActualTCPPose")

    def _vector(self, values: Any, n: int, what: str) -> NDArray[np.float64]:
        try:
            arr = np.asarray(values, dtype=np.float64)
        except (TypeError, ValueError):
            raise ProtocolError(f"ur: {what} returned {values!r}, not numbers") from None
        if arr.shape != (n,) or not np.all(np.isfinite(arr)):
            raise ProtocolError(f"ur: {what} returned {arr.tolist()!r}, expected {n} finite numbers")
        return arr

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
            self._raise_known_cause(receive, operation)
            if fresh >= SETTLE_PACKAGES or self._clock() >= until:
                break
            self._sleep(0.002)
            ts = float(receive.getTimestamp())
            fresh, last = (fresh + 1, ts) if ts != last else (fresh, last)
        raise VendorError("ur", 0, f"{operation} returned False with the arm in normal mode "
                                   "(ur_rtde internal timeout?)")

    def _raise_known_cause(self, receive: Any, operation: str) -> None:
        """Raise the typed error for the state the receive interface reports, if any."""
        safety = _safety(receive)
        if receive.isEmergencyStopped():
            raise VendorError("ur", safety, (
                f"{operation} failed: emergency stop engaged (safety mode {name(SAFETY_MODES, safety)}); "
                "release the e-stop by hand, then call clear_errors()"))
        if receive.isProtectiveStopped():
            raise VendorError("ur", safety, (
                f"{operation} failed: protective stop (safety mode {name(SAFETY_MODES, safety)}); "
                "remove the cause, then call clear_errors()"))
        if safety not in SAFETY_OK:
            raise VendorError("ur", safety, f"{operation} failed: safety mode {name(SAFETY_MODES, safety)}")
        robot = _robot(receive)
        if robot != ROBOT_MODE_RUNNING:
            raise VendorError("ur", robot, (
                f"{operation} failed: robot mode {name(ROBOT_MODES, robot)} (power on and release the brakes)"))
        if not self._program_running(receive):
            state = _runtime(receive)
            raise VendorError("ur", state, (
                f"{operation} failed: the RTDE control script is not running (program state "
                f"{name(RUNTIME_STATES, state)}){self._dash.remote_control_hint()}; clear_errors() restarts it"))
