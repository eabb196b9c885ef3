"""UFACTORY xArm 5/6/7 as a :class:`RobotArm`, over RS-485/USB serial or Ethernet (TCP).

SI units on the API; millimetres and radians only on the wire (converted through
:mod:`cellcal.devices.geometry.vendor_poses`). Poses are of the tool flange: the
controller's TCP offset is assumed to be zero. A motion command is sent once and never
again; what happens when its reply is missing or foreign is ADR 0016, the TCP transport
and its report stream ADR 0019.
"""

from __future__ import annotations

import logging
import math
import struct
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import ClassVar, Literal

import numpy as np
from numpy.typing import NDArray

from cellcal.devices.arm import RobotArm
from cellcal.devices.arm_model import ArmModel
from cellcal.devices.arrival import format_pose
from cellcal.devices.base import BackendContext
from cellcal.devices.discovery import HostScan
from cellcal.devices.errors import (
    CellcalError,
    ConfigError,
    DeviceConnectionError,
    DeviceTimeoutError,
    MotionError,
    ProtocolError,
    SafetyError,
    VendorError,
)
from cellcal.devices.geometry.vendor_poses import pose_from_xarm, pose_to_xarm
from cellcal.devices.pose import Pose
from cellcal.devices.types import ArmStatus, DeviceInfo

from . import codes, discover
from .protocol import Reply
from .registers import (
    ALL_AXES,
    JOINT_FLOATS,
    MOVE_LINE_COMMON_REPLY,
    VERSION_LEN,
    ArmState,
    Reg,
    SetState,
    VersionInfo,
    decode_serials,
    decode_text,
    encode_move_line,
    parse_version,
    unpack_floats,
)
from .report import ArmReport, ReportStream
from .tcp_transport import TcpTransport
from .transport import SerialTransport

log = logging.getLogger(__name__)

_MM = 1000.0
#: Largest |coordinate| of a TCP pose reply taken as real, mm (no xArm reaches 10 m).
MAX_POSE_MM = 10_000.0
#: Largest |angle| of a pose or joint reply taken as real, rad.
MAX_ANGLE_RAD = 4.0 * math.pi
#: A request failed on the link (over TCP a lost connection too): the arm's state is unknown.
_LINK_ERRORS = (ProtocolError, DeviceTimeoutError, DeviceConnectionError)
#: Serial port used when neither ``port`` nor ``host`` is given.
DEFAULT_SERIAL_PORT = "/dev/ttyUSB0"
_TCP_PORT_RANGE = {"ge": 1, "le": 65535}
#: What a UFACTORY xArm 5/6/7 is worth (issue #39, ADR 0055): UFACTORY states a repeatability of ±0.1 mm
#: for all three; it states no absolute accuracy, so an uncalibrated industrial arm's is assumed:
#: 1.5 mm and 3 mrad (RMS over the workspace; ISO 9283 AP/AO of uncalibrated arms are 0.2-2 mm and up to a
#: few mrad). A cell that measured its arm says so in ``[arm.model]``.
XARM_MODEL = ArmModel(repeatability_m=1e-4, accuracy_m=1.5e-3, accuracy_rad=3e-3, source="backend")


class XArmArm(RobotArm):
    """xArm over a serial line or TCP (backend ``"xarm"``; ``host`` selects TCP).

    A motion is one MOVE_LINE followed by state polling (GET_STATE, GET_CMDNUM,
    GET_ERROR) until the arm reports it is idle with an empty queue; the base class then
    checks the arrival (ADR 0016). MOVE_LINE is sent once: right before it go a pose read
    and an error read, whose reply lengths (24 and 2 bytes) differ from its own (0 or 3),
    so a reply lagging one request behind cannot pass for its confirmation. Without a
    valid reply the driver reads the state and pose, stops the arm unless it is idle, and
    raises :class:`MotionError`. Errors are never cleared silently: :meth:`recover`
    (= :meth:`clear_errors`) is the one place that runs the vendor's recovery sequence.

    Args:
        config: Validated :class:`XArmArm.Config`.
        context: Backend context (unused; accepted for the registry).
    """

    backend_name = "xarm"

    def _arm_model(self) -> ArmModel:
        """UFACTORY's repeatability (0.1 mm) and an assumed uncalibrated accuracy (:data:`XARM_MODEL`)."""
        return XARM_MODEL

    @dataclass(frozen=True)
    class Config:
        """The ``[arm]`` section for ``backend = "xarm"``; every quantity in the range a real xArm cell has."""

        port: str | None = field(default=None, metadata={
            "doc": f"serial device path or pyserial URL (default {DEFAULT_SERIAL_PORT} unless host is given)"})
        host: str | None = field(default=None, metadata={"max_len": 253,
                                                         "doc": "controller address; selects TCP instead of serial"})
        tcp_port: int = field(default=502, metadata={**_TCP_PORT_RANGE, "doc": "TCP control port (with host)"})
        report_port: int = field(default=30002, metadata={
            "ge": 0, "le": 65535, "doc": "TCP port of the rich report stream (with host); 0 = do not read it"})
        report_stale_s: float = field(default=1.0, metadata={
            "ge": 0.05, "le": 10, "doc": "report silence after which it is stalled and the registers are read, s"})
        baudrate: int = field(default=2_000_000, metadata={"ge": 1200, "le": 12_000_000,
                                                           "doc": "line speed, baud (8N1)"})
        axes: Literal[5, 6, 7] = field(default=6, metadata={"doc": "axis count of the arm"})
        reply_timeout_s: float = field(default=0.5, metadata={"ge": 0.001, "le": 10,
                                                              "doc": "wait for one reply, s (a read's per attempt)"})
        retries: int = field(default=2, metadata={"ge": 0, "le": 10,
                                                  "doc": "extra attempts of a read on a bad/missing reply "
                                                         "(other commands are never resent)"})
        enable_timeout_s: float = field(default=5.0, metadata={"ge": 0.01, "le": 30, "doc": "MOTION_EN timeout, s"})
        poll_interval_s: float = field(default=0.02, metadata={"ge": 0.001, "le": 1, "doc": "state polling period, s"})
        stop_timeout_s: float = field(default=2.0, metadata={"ge": 0.01, "le": 30,
                                                             "doc": "time to confirm a stop (and, after an "
                                                                    "unconfirmed motion, to find out and stop), s"})
        default_speed_m_s: float = field(default=0.1, metadata={"ge": 1e-4, "le": 1.0,
                                                                "doc": "default tool speed, m/s"})
        default_acceleration_m_s2: float = field(default=1.0, metadata={"ge": 1e-3, "le": 50.0,
                                                                          "doc": "default tool acceleration, m/s²"})
        max_speed_m_s: float = field(default=1.0, metadata={"ge": 1e-4, "le": 1.0,
                                                            "doc": "largest accepted speed, m/s"})
        max_acceleration_m_s2: float = field(default=50.0, metadata={"ge": 1e-3, "le": 50.0,
                                                                      "doc": "largest accepted acceleration, m/s²"})
        move_line_layout: Literal["auto", "legacy", "common"] = field(
            default="auto", metadata={"doc": "MOVE_LINE parameter layout; auto picks by firmware version"})
        enable_on_connect: bool = field(default=True, metadata={
            "doc": "run motion enable, mode 0, state 0 on connect when no error is pending"})

        def __post_init__(self) -> None:
            if self.port is not None and self.host is not None:
                raise ConfigError(f"both port ({self.port!r}, serial) and host ({self.host!r}, TCP) are given; "
                                  "keep one of them")
            if self.host is not None and not self.host.strip():
                raise ConfigError("host is empty; give the controller's address (or use port for serial)", key="host")
            if self.report_port == self.tcp_port:
                raise ConfigError(f"report_port {self.report_port} is the control port tcp_port; the rich report is "
                                  "on 30002 (0 = do not read it)", key="report_port")
            if self.default_speed_m_s > self.max_speed_m_s:
                raise ConfigError(f"default_speed_m_s {self.default_speed_m_s} exceeds max_speed_m_s "
                                  f"{self.max_speed_m_s}")
            if self.default_acceleration_m_s2 > self.max_acceleration_m_s2:
                raise ConfigError(f"default_acceleration_m_s2 {self.default_acceleration_m_s2} exceeds "
                                  f"max_acceleration_m_s2 {self.max_acceleration_m_s2}")

    # ------------------------------------------------------------ network discovery
    #: Standard ports by service name (``cellcal devices --scan --ports NAME=PORT``).
    scan_ports: ClassVar[Mapping[str, int]] = discover.PORTS
    #: Where a scan without ``--hosts`` / ``--subnet`` looks (``--factory``).
    factory_hosts: ClassVar[tuple[str, ...]] = discover.FACTORY_HOSTS

    @classmethod
    def scan_hosts(cls, hosts: Sequence[str] | None, timeout: float,
                   ports: Mapping[str, int] | None = None) -> HostScan:
        """xArm controllers among ``hosts`` (None: :attr:`factory_hosts`) within ``timeout`` s (:mod:`.discover`)."""
        return discover.scan_hosts(hosts, timeout, ports)

    def __init__(self, config: XArmArm.Config | None = None, context: BackendContext | None = None):
        super().__init__()
        self.config = config or XArmArm.Config()
        self.context = context
        self._transport: SerialTransport | TcpTransport | None = None
        self._report: ReportStream | None = None
        self._version: VersionInfo | None = None
        self._robot_sn = ""
        self._box_sn = ""

    # ------------------------------------------------------------------ wire helpers
    @property
    def transport(self) -> SerialTransport | TcpTransport:
        """The open transport (for diagnostics and tests)."""
        if self._transport is None:
            raise DeviceConnectionError("xarm: transport is not open")
        return self._transport

    @property
    def version(self) -> VersionInfo | None:
        """What the controller said on GET_VERSION at connect."""
        return self._version

    def _call(self, reg: Reg, params: bytes = b"", *, expect_len: int | None = 0,
              timeout: float | None = None) -> Reply:
        return self.transport.transact(int(reg), params, expect_len=expect_len, timeout=timeout)

    def _read_error(self, timeout: float | None = None) -> tuple[int, int]:
        reply = self._call(Reg.GET_ERROR, expect_len=2, timeout=timeout)
        return reply.data[0], reply.data[1]

    def _read_state(self, timeout: float | None = None) -> int:
        state = self._call(Reg.GET_STATE, expect_len=1, timeout=timeout).data[0]
        if state not in tuple(ArmState):
            raise ProtocolError(f"xarm: GET_STATE replied {state}, not a state of the controller (1-5)")
        return state

    def _read_cmdnum(self, timeout: float | None = None) -> int:
        return int(struct.unpack(">H", self._call(Reg.GET_CMDNUM, expect_len=2, timeout=timeout).data)[0])

    def _read_pose(self, timeout: float | None = None) -> Pose:
        values = np.asarray(unpack_floats(self._call(Reg.GET_TCP_POSE, expect_len=24, timeout=timeout).data, 6),
                            dtype=np.float64)
        if not (np.all(np.isfinite(values)) and np.all(np.abs(values[:3]) <= MAX_POSE_MM)
                and np.all(np.abs(values[3:]) <= MAX_ANGLE_RAD)):
            raise ProtocolError(f"xarm: GET_TCP_POSE replied {values.tolist()}, not a pose (mm, rad) of an xArm")
        return pose_from_xarm(values)

    def _raise_error(self, code: int) -> None:
        raise VendorError("xarm", code, codes.error_meaning(code))

    def _set_state(self, value: SetState, timeout: float | None = None) -> Reply:
        return self._call(Reg.SET_STATE, bytes([int(value)]), timeout=timeout)

    def _bounded(self, deadline: float) -> float:
        """Timeout of one read before ``deadline``, never less than one reply's wait."""
        return max(deadline - time.monotonic(), self.config.reply_timeout_s)

    # ------------------------------------------------------------------ life cycle
    @property
    def where(self) -> str:
        """The serial port, or ``host:tcp_port``."""
        cfg = self.config
        return f"{cfg.host}:{cfg.tcp_port}" if cfg.host is not None else (cfg.port or DEFAULT_SERIAL_PORT)

    def latest_report(self) -> ArmReport | None:
        """The newest checked report of the TCP report stream, if it is healthy and fresh."""
        report = self._report
        return report.latest(self.config.report_stale_s) if report is not None else None

    def _open_transport(self, timeout: float) -> None:
        cfg = self.config
        reply_timeout = min(cfg.reply_timeout_s, timeout)
        if cfg.host is None:
            self._transport = SerialTransport(self.where, cfg.baudrate, reply_timeout_s=reply_timeout,
                                              retries=cfg.retries)
            self._transport.open()
            return
        self._transport = TcpTransport(cfg.host, cfg.tcp_port, reply_timeout_s=reply_timeout, retries=cfg.retries,
                                       connect_timeout_s=timeout)
        self._transport.open(timeout)

    def _start_report(self, deadline: float) -> None:
        """Read the report stream (TCP only); without a first good report the registers are polled."""
        cfg = self.config
        if cfg.host is None or not cfg.report_port:
            return
        self._report = ReportStream(cfg.host, cfg.report_port, stale_after_s=cfg.report_stale_s,
                                    connect_timeout_s=max(0.05, min(2.0, deadline - time.monotonic())))
        self._report.start()
        try:
            self._report.wait_newer(0, deadline)
        except CellcalError as exc:
            log.warning("xarm: report stream not available, state is polled (it keeps trying): %s", exc)

    def _connect(self, timeout: float) -> None:
        cfg = self.config
        deadline = time.monotonic() + timeout
        self._open_transport(timeout)
        reply = self._call(Reg.GET_VERSION, expect_len=VERSION_LEN, timeout=timeout)
        self._version = parse_version(decode_text(reply.data))
        if self._version.axes is not None and self._version.axes != cfg.axes:
            raise DeviceConnectionError(f"xarm: configured for {cfg.axes} axes but the arm at {self.where!r} reports "
                                        f"{self._version.axes} ({self._version.text!r})")
        try:
            sn = self._call(Reg.GET_ROBOT_SN, expect_len=VERSION_LEN)
            self._robot_sn, self._box_sn = decode_serials(sn.data)
        except _LINK_ERRORS:
            self._robot_sn, self._box_sn = self._version.robot_sn, self._version.box_sn
        if cfg.enable_on_connect:
            error, _warn = self._read_error()
            if error == 0:
                self._enable_sequence()
        self._start_report(max(deadline, time.monotonic() + cfg.reply_timeout_s))

    def _close(self) -> None:
        transport, self._transport = self._transport, None
        report, self._report = self._report, None
        if report is not None:
            report.close()
        if transport is not None:
            transport.close()

    def _info(self) -> DeviceInfo:
        v = self._version
        fw = ".".join(str(x) for x in v.firmware) if v is not None and v.firmware else ""
        return DeviceInfo(backend=self.backend_name, vendor="UFACTORY", model=f"xArm {self.config.axes}",
                          serial=self._robot_sn, firmware=fw,
                          extra={"version": v.text if v else "", "control_box_sn": self._box_sn,
                                 "port": self.where, "transport": "serial" if self.config.host is None else "tcp",
                                 "move_line_layout": self._layout()})

    def _layout(self) -> str:
        if self.config.move_line_layout != "auto":
            return self.config.move_line_layout
        return "common" if self._version is not None and self._version.uses_common_move_line else "legacy"

    # ------------------------------------------------------------------ recovery
    def _enable_sequence(self) -> None:
        self._call(Reg.MOTION_EN, bytes([ALL_AXES, 1]), timeout=self.config.enable_timeout_s)
        self._call(Reg.SET_MODE, bytes([0]))
        self._set_state(SetState.RUN)

    def recover(self, timeout: float | None = None) -> None:
        """The xArm recovery sequence: clean warning, clean error, motion enable, mode 0, state 0.

        Same as :meth:`clear_errors`.

        Raises:
            VendorError: If an error is still pending afterwards (e.g. an emergency stop).
        """
        self.clear_errors(timeout)

    def _clear_errors(self, timeout: float) -> None:
        self._call(Reg.CLEAN_WAR)
        self._call(Reg.CLEAN_ERR)
        self._enable_sequence()
        error, _warn = self._read_error()
        if error:
            self._raise_error(error)

    # ------------------------------------------------------------------ reads
    def _get_pose(self, timeout: float) -> Pose:
        return self._read_pose(timeout)

    def _joint_positions(self, timeout: float) -> NDArray[np.float64]:
        reply = self._call(Reg.GET_JOINT_POS, expect_len=4 * JOINT_FLOATS, timeout=timeout)
        q = np.asarray(unpack_floats(reply.data, JOINT_FLOATS)[: self.config.axes], dtype=np.float64)
        if not (np.all(np.isfinite(q)) and np.all(np.abs(q) <= MAX_ANGLE_RAD)):
            raise ProtocolError(f"xarm: GET_JOINT_POS replied {q.tolist()}, not joint angles in radians")
        return q

    def _status(self, timeout: float) -> ArmStatus:
        report = self.latest_report()
        if report is not None and report.state in tuple(ArmState):  # pushed, checked and fresh: no polling
            error, warn, state = report.error, report.warning, report.state
        else:
            error, warn = self._read_error()
            state = self._read_state()
        not_ready = state in (ArmState.STOPPED, ArmState.STOPPING)
        if error:
            message = codes.error_meaning(error)
        elif warn:
            message = codes.warning_meaning(warn)
        elif not_ready:
            message = f"not ready to move (state {state}); call clear_errors()"
        else:
            message = ""
        return ArmStatus(error_code=error, warning_code=warn, message=message,
                         can_move=error == 0 and not not_ready)

    # ------------------------------------------------------------------ motion
    def _check_ready(self, reply: Reply, what: str) -> None:
        if reply.error_pending:
            error, _warn = self._read_error()
            if error:
                self._raise_error(error)
        if reply.not_ready:
            state = self._read_state()
            raise VendorError("xarm", codes.NOT_READY,
                              f"not ready to move ({what}, state {state}); call clear_errors()")
        if reply.invalid:
            raise VendorError("xarm", codes.NOT_READY, f"{what} rejected by the controller (invalid command)")

    def _move_linear(self, pose: Pose, speed: float, acceleration: float, timeout: float) -> None:
        cfg = self.config
        if speed > cfg.max_speed_m_s:
            raise SafetyError(f"xarm: speed {speed} m/s exceeds max_speed_m_s {cfg.max_speed_m_s}")
        if acceleration > cfg.max_acceleration_m_s2:
            raise SafetyError(f"xarm: acceleration {acceleration} m/s^2 exceeds max_acceleration_m_s2 "
                              f"{cfg.max_acceleration_m_s2}")
        deadline = time.monotonic() + timeout
        common = self._layout() == "common"
        params = encode_move_line(pose_to_xarm(pose), speed * _MM, acceleration * _MM, common=common)
        # The last two requests before MOVE_LINE answer with 24 and 2 bytes, MOVE_LINE with 0 or 3:
        # a reply one request late shows up as a wrong length, never as MOVE_LINE's confirmation.
        start = self._read_pose(self._bounded(deadline))
        error, _warn = self._read_error(self._bounded(deadline))
        if error:
            self._raise_error(error)
        try:
            reply = self._call(Reg.MOVE_LINE, params, expect_len=MOVE_LINE_COMMON_REPLY if common else 0,
                               timeout=cfg.reply_timeout_s)
        except _LINK_ERRORS as exc:
            raise self._unconfirmed(f"MOVE_LINE to {format_pose(pose)} was not confirmed ({exc})",
                                    pose, start) from None
        self._check_ready(reply, "MOVE_LINE")
        self._wait_idle(deadline, timeout, pose, start)

    def _wait_idle(self, deadline: float, timeout: float, target: Pose, start: Pose) -> None:
        """Poll until the arm is idle with an empty queue; stop it and raise on timeout or lost contact."""
        idle_seen = 0
        seq = 0
        while True:
            if idle_seen == 0:
                seq = self._follow_report(seq, deadline)
            try:
                error, _warn = self._read_error(self._bounded(deadline))
                state = self._read_state(self._bounded(deadline)) if not error else 0
                idle = state == ArmState.SLEEPING and self._read_cmdnum(self._bounded(deadline)) == 0
            except _LINK_ERRORS as exc:
                raise self._unconfirmed(f"contact lost during the motion to {format_pose(target)} ({exc})",
                                        target, start) from None
            if error:
                self._raise_error(error)
            if state in (ArmState.STOPPED, ArmState.STOPPING):
                error, _warn = self._read_error()  # the error may have latched after the read above
                if error:
                    self._raise_error(error)
                raise VendorError("xarm", codes.NOT_READY,
                                  f"arm stopped during the motion (state {state}); call clear_errors()")
            idle_seen = idle_seen + 1 if idle else 0
            if idle_seen >= 2:
                return
            if time.monotonic() >= deadline:
                raise DeviceTimeoutError(f"xarm: motion not finished within {timeout:.3g} s; "
                                         f"{self._stop_quietly(time.monotonic() + self.config.stop_timeout_s)}")
            time.sleep(min(self.config.poll_interval_s, max(0.0, deadline - time.monotonic())))

    def _follow_report(self, seq: int, deadline: float) -> int:
        """While the report stream shows the arm moving, wait on it instead of polling registers.

        Returns when a report says the arm is not moving (the registers then confirm the
        end), the stream fails or stalls (the registers take over), or ``deadline`` passes.
        Returns the sequence number of the last report seen.
        """
        stream = self._report
        if stream is None:
            return seq
        while time.monotonic() < deadline:
            try:
                report = stream.wait_newer(seq, min(deadline, time.monotonic() + self.config.report_stale_s))
            except CellcalError:
                return seq
            seq = report.seq
            if not report.moving:
                return seq
        return seq

    def _unconfirmed(self, reason: str, target: Pose, start: Pose) -> MotionError:
        """After a motion command without a valid reply: find out what the arm does, stop it unless idle.

        Takes at most ``stop_timeout_s``: half to read the state and pose, the rest to stop.
        """
        budget = self.config.stop_timeout_s
        end = time.monotonic() + budget
        findings, unsure = self._assess(target, start, end - budget / 2)
        stopped = self._stop_quietly(end) if unsure else "it is idle, so it was not stopped"
        return MotionError(f"xarm: {reason}; the command was not sent again; {findings}; {stopped}")

    def _assess(self, target: Pose, start: Pose, until: float) -> tuple[str, bool]:
        """What the arm is doing after an unconfirmed motion; ``(description, unsure)``."""
        try:
            error, _warn = self._read_error(self._bounded(until))
            state = self._read_state(self._bounded(until))
            queued = self._read_cmdnum(self._bounded(until))
            pose = self._read_pose(self._bounded(until))
        except _LINK_ERRORS as exc:
            return f"its state could not be read back ({exc})", True
        where = (f"the flange is {pose.distance_to(start) * _MM:.1f} mm from where it started and "
                 f"{pose.distance_to(target) * _MM:.1f} mm from the target")
        idle = state in (ArmState.SLEEPING, ArmState.STOPPED) and queued == 0
        return f"state {state}, {queued} queued, error {error}: {where}", not idle

    def _stop_quietly(self, until: float) -> str:
        """Stop the arm, bounded by ``until``; says what happened, for messages (never raises a device error)."""
        try:
            self._stop(max(until - time.monotonic(), self.config.reply_timeout_s))
        except CellcalError as exc:
            return f"stopping the arm failed: {exc}"
        return "the arm was stopped (clear_errors() before the next move)"

    def _stop(self, timeout: float) -> None:
        """Emergency-style stop: SET_STATE 4 until the state reads 4 (the arm then needs recovery).

        Each round sends SET_STATE 4 once and reads the state; a lost or garbled reply only
        makes another round (a stop never moves the arm, so repeating it is the vendor's way).
        """
        cfg = self.config
        deadline = time.monotonic() + timeout
        last: CellcalError | None = None
        while True:
            try:
                self._set_state(SetState.STOP, cfg.reply_timeout_s)
                if self._read_state(min(self._bounded(deadline), 2 * cfg.reply_timeout_s)) == ArmState.STOPPED:
                    return
            except _LINK_ERRORS as exc:
                last = exc
            if time.monotonic() >= deadline:
                why = f" (last: {last})" if last is not None else ""
                raise DeviceTimeoutError(f"xarm: arm did not report stopped within {timeout:.3g} s{why}")
            time.sleep(cfg.poll_interval_s)
