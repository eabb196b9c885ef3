"""Universal Robots arm over the ``ur_rtde`` library (registered as ``ur``).

Poses are flange poses in the base frame (metres, radians). ``ur_rtde`` is imported
only in :meth:`URArm._connect`; every False it returns becomes a typed error
(:meth:`URArm._raise_failure`). This module holds the links (connect, a fresh receive
interface, bounded commands, recovery); the wait for a move is :class:`~.motion.URMotion`'s,
what the arm's state says :mod:`.status`'s. Design: docs/adr/0015-vendor-drivers.md; what the real
conversation with ur_rtde 1.6.5 taught (GIL, script start, reconnects): docs/adr/0017-ur-emulator.md.
"""

from __future__ import annotations

import contextlib
import logging
import time
import traceback
from collections.abc import Callable, Mapping, Sequence
from typing import Any, ClassVar

import numpy as np
from numpy.typing import NDArray

from cellcal.devices.arm_model import ArmModel
from cellcal.devices.base import BackendContext
from cellcal.devices.discovery import HostScan
from cellcal.devices.errors import (
    CellcalError,
    DeviceConnectionError,
    DeviceTimeoutError,
    ProtocolError,
    VendorError,
)
from cellcal.devices.geometry.vendor_poses import pose_from_ur
from cellcal.devices.isolation import InlineHost, NativeHost
from cellcal.devices.pose import Pose
from cellcal.devices.types import ArmStatus, DeviceInfo

from . import availability, discover
from .codes import FLAG_NO_WAIT, ROBOT_MODE_RUNNING, ROBOT_MODES, RUNTIME_STATES, SAFETY_OK, name
from .config import URConfig
from .dashboard import DashboardLink, stop_program
from .fd_capture import captured_output
from .limits import checked_tcp
from .motion import URMotion
from .rtde_probe import probe_stream
from .status import (
    arm_status,
    not_ready_reason,
    program_running,
    ready_for_program,
    robot_mode,
    runtime_state,
    safety_mode,
)

log = logging.getLogger(__name__)

#: Seconds the dashboard gets to stop the program after ur_rtde's worker process died.
CRASH_STOP_TIMEOUT_S = 1.0


#: What a Universal Robots e-Series arm is worth (issue #39, ADR 0055): repeatability ±0.03 mm (UR3e, UR5e)
#: to ±0.05 mm (UR10e, UR16e; the larger is stated, the backend does not know the model before it connects);
#: absolute accuracy about 1-2 mm (UR ships each arm with its own kinematic calibration but states no absolute
#: accuracy): 1.5 mm and 3 mrad (RMS over the workspace). ``[arm.model]`` overrides it.
UR_MODEL = ArmModel(repeatability_m=5e-5, accuracy_m=1.5e-3, accuracy_rad=3e-3, source="backend")


class URArm(URMotion):
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

    def _arm_model(self) -> ArmModel:
        """Universal Robots' e-Series figures (:data:`UR_MODEL`)."""
        return UR_MODEL
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
                        self.config.host, not_ready_reason(self._receive))

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
        return arm_status(self._fresh_receive(self._clock() + timeout))

    # ------------------------------------------------------------ motion (the wait: URMotion)
    def _stop(self, timeout: float) -> None:
        decel = self.config.stop_deceleration_m_s2
        self._command(lambda c: c.stopL(decel), self._clock() + timeout, "stopL")

    # ------------------------------------------------------------ recovery
    def _clear_errors(self, timeout: float) -> None:
        deadline = self._clock() + timeout
        receive = self._fresh_receive(deadline)
        if receive.isEmergencyStopped():
            self._raise_failure("clear_errors")  # an e-stop is released by hand, never remotely
        if receive.isProtectiveStopped() or safety_mode(receive) not in SAFETY_OK \
                or robot_mode(receive) != ROBOT_MODE_RUNNING:
            dash = self._dash.open(self._remaining(deadline), required=True)
            self._dash.call("closeSafetyPopup", "close safety popup")
            self._unlock_protective_stop(dash, deadline)
            self._power_up(deadline, timeout)
        if not program_running(self._fresh_receive(deadline)):
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
                raise VendorError("ur", safety_mode(self._fresh_receive(deadline)), (
                    f"clear_errors could not unlock the protective stop in time ({refusal or 'still stopped'})"))
            self._sleep(max(self.config.poll_interval_s, 0.05))

    def _power_up(self, deadline: float, timeout: float) -> None:
        receive = self._fresh_receive(deadline)
        robot = robot_mode(receive)
        if robot == ROBOT_MODE_RUNNING:
            return
        if not self.config.allow_power_on:
            raise VendorError("ur", robot, (
                f"robot mode {name(ROBOT_MODES, robot)}: power on and release the brakes on the pendant, "
                "or set allow_power_on = true"))
        self._dash.call("powerOn", "power on")
        self._dash.call("brakeRelease", "brake release")
        while robot_mode(receive) != ROBOT_MODE_RUNNING:
            if self._clock() >= deadline:
                raise DeviceTimeoutError(f"ur: arm not RUNNING within {timeout:g} s after power on "
                                         f"(robot mode {name(ROBOT_MODES, robot_mode(receive))})")
            self._sleep(max(self.config.poll_interval_s, 0.05))
            receive = self._fresh_receive(deadline)

    def _start_script(self, deadline: float) -> None:
        """Upload ur_rtde's control script, wait (bounded) until it runs, then zero the TCP offset."""
        if not self._command(lambda c: c.reuploadScript(), deadline, "reuploadScript"):
            self._raise_failure("start the control script (reuploadScript)")
        receive = self._fresh_receive(deadline)
        # Both links must see it: ur_rtde refuses commands while its own stream says STOPPED.
        while not (program_running(receive) and self._control.isProgramRunning()):
            if self._clock() >= deadline:
                state = runtime_state(receive)
                raise DeviceTimeoutError(
                    f"ur {self.config.host}: the control script did not start in time (program state "
                    f"{name(RUNTIME_STATES, state)}; {not_ready_reason(receive) or 'arm ready'})"
                    f"{self._dash.remote_control_hint()}")
            self._sleep(self.config.poll_interval_s)
            receive = self._fresh_receive(deadline)
        if self.config.set_tcp_to_flange and not self._command(lambda c: c.setTcp([0.0] * 6), deadline, "setTcp"):
            self._raise_failure("setTcp (TCP offset to the flange)")

    # ------------------------------------------------------------ state helpers
    #: Whether the arm can run the control script (:func:`.status.ready_for_program`).
    _ready_for_program = staticmethod(ready_for_program)

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
