"""An xArm controller on a pseudo-terminal, backed by a simulated arm.

Anything that opens the printed slave path as a serial port (cellcal's ``xarm`` driver
or UFACTORY's ``xarm-python-sdk``) talks to it as to a real controller::

    path = XArmEmulator(SimArm().connect()).start()   # e.g. "/dev/pts/7"
"""

from __future__ import annotations

import contextlib
import math
import os
import select
import struct
import threading
import tty
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal, Protocol

import numpy as np
from scipy.spatial.transform import Rotation

from cellcal.devices.errors import CellcalError
from cellcal.devices.geometry.vendor_poses import pose_from_xarm, pose_to_xarm
from cellcal.devices.pose import Pose
from cellcal.sims.arm import ERROR_OUT_OF_REACH

from .tcp_wire import ReportValues
from .wire import (
    EVERY_JOINT,
    EXTENDED_LINE_REPLY_BYTES,
    FLAG_ERROR,
    FLAG_INVALID,
    FLAG_NOT_READY,
    FLAG_WARNING,
    JOINT_REPLY_FLOATS,
    TEXT_REPLY_BYTES,
    Command,
    LineMove,
    Register,
    RequestReader,
    RobotState,
    StateCommand,
    floats,
    read_line_move,
    reply_frame,
    text_field,
)

FaultKind = Literal["corrupt_crc", "drop", "truncate", "stall", "lag", "stale_id"]


class ArmModel(Protocol):
    """What the emulator needs from the simulated arm (``SimArm`` provides it).

    ``true_flange_pose`` is the noise-free pose the emulator plans with; ``get_pose``
    (with the arm's read-back noise) is what GET_TCP_POSE reports.
    """

    def begin_move_linear(self, pose: Pose, speed_m_s: float, acceleration_m_s2: float) -> None: ...

    def is_moving(self) -> bool: ...

    def current_error(self) -> tuple[int, int]: ...

    def set_error(self, code: int, warning: int = 0) -> None: ...

    def true_flange_pose(self) -> Pose: ...

    def get_pose(self, timeout: float | None = None) -> Pose: ...

    def joint_positions(self, timeout: float | None = None) -> np.ndarray: ...

    def stop(self, timeout: float | None = None) -> None: ...


@dataclass
class InjectedFault:
    """One fault queued by :meth:`XArmEmulator.inject`."""

    kind: FaultKind
    register: int | None
    stall_s: float


@dataclass
class _ScheduledError:
    code: int
    after_polls: int
    armed: bool = False
    polls: int = 0


class XArmEmulator:
    """Serve the xArm serial protocol on a pty, driven by a simulated arm.

    Opens a pty pair (``os.openpty``) and answers UFACTORY's serial register protocol
    on the master side. Motion, workspace and errors come from the simulated arm
    (:class:`ArmModel`, satisfied by ``cellcal.sims.arm.SimArm``); the emulator adds the
    controller's state machine (motion enable, mode, state, error/warning latching,
    command counter). Its framing, CRC and register layouts are its own
    (:mod:`cellcal.sims.xarm.wire`), not the driver's.

    Fault injection (tests): :meth:`inject` corrupts the CRC of, drops, truncates,
    stalls or delays by one request ("lag") upcoming replies; a dropped or corrupted
    reply to MOVE_LINE (``register=21``) is the lost confirmation of a motion command
    that did take effect. :meth:`fail_next_move` raises a controller error in the
    middle of the next motion. An arm that stops short or whose pose read-back jumps
    is the simulated arm's (``SimArm.faults``), served as is.

    Args:
        arm: The simulated arm (connected).
        axes: Axis count reported in the version string (5, 6 or 7).
        firmware: Firmware version reported, ``(major, minor, revision)``; from
            1.11.100 on the SDK sends the extended MOVE_LINE layout.
        robot_sn: Robot serial number reported.
        box_sn: Control-box serial number reported.
        start_ready: Start enabled in mode 0, state 0 (a real arm starts stopped and
            needs motion enable + set state 0).

    Attributes:
        path: The slave device path clients open (e.g. ``/dev/pts/5``), once started.
        requests: Count of well-formed requests served, by register number.
        bad_requests: Count of frames that failed to decode (bad CRC, ...).
        stop_requests: Count of stop commands (SET_STATE 3/4) received and executed.
        last_reported_pose: The last GET_TCP_POSE reply, ``[x, y, z]`` mm and
            ``[roll, pitch, yaw]`` rad as float32 values on the wire.
        last_move: The last well-formed MOVE_LINE request (either layout).
    """

    def __init__(self, arm: ArmModel, *, axes: int = 5, firmware: tuple[int, int, int] = (2, 5, 0),
                 robot_sn: str = "XS1305EMU0001", box_sn: str = "AC1305EMU0001", start_ready: bool = False):
        if axes not in (5, 6, 7):
            raise CellcalError(f"xarm emulator: axes must be 5, 6 or 7, got {axes}")
        self.arm = arm
        self.axes = axes
        self.firmware = firmware
        self.robot_sn = robot_sn
        self.box_sn = box_sn
        self.version_text = f"{axes},{axes},{robot_sn},{box_sn},v{firmware[0]}.{firmware[1]}.{firmware[2]}"
        serials = f"{robot_sn}\0{box_sn}"
        if len(self.version_text) >= TEXT_REPLY_BYTES or len(serials) >= TEXT_REPLY_BYTES:
            raise CellcalError(f"xarm emulator: version string too long: {self.version_text!r}")
        self._version_reply = text_field(self.version_text)
        self._serials_reply = text_field(serials)
        self.path = ""
        self.requests: dict[int, int] = {}
        self.bad_requests = 0
        self.stop_requests = 0
        self.last_reported_pose: tuple[float, ...] | None = None
        self.last_move: LineMove | None = None
        self._lock = threading.RLock()
        self._enabled = start_ready
        self._ready = start_ready
        self._mode = 0
        self._faults: deque[InjectedFault] = deque()
        self._held: bytes | None = None  # a reply held back by a "lag" fault
        self._scheduled: _ScheduledError | None = None
        self._master = -1
        self._slave = -1
        self._wake_r = -1
        self._wake_w = -1
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._handlers: dict[int, Callable[[bytes], tuple[int, bytes]]] = {
            Register.GET_VERSION: self._get_version,
            Register.GET_ROBOT_SN: self._get_robot_sn,
            Register.MOTION_EN: self._motion_en,
            Register.SET_STATE: self._set_state,
            Register.GET_STATE: self._get_state,
            Register.GET_CMDNUM: self._get_cmdnum,
            Register.GET_ERROR: self._get_error,
            Register.CLEAN_ERR: self._clean_err,
            Register.CLEAN_WAR: self._clean_war,
            Register.SET_MODE: self._set_mode,
            Register.MOVE_LINE: self._move_line,
            Register.GET_TCP_POSE: self._get_tcp_pose,
            Register.GET_JOINT_POS: self._get_joint_pos,
            Register.GET_TCP_POSE_AA: self._get_tcp_pose_aa,
            Register.SET_FEEDBACK_TYPE: self._set_feedback_type,
        }
        self.feedback_type = 0
        """Last SET_FEEDBACK_TYPE value (the SDK asks for motion-finish feedback; none is sent)."""

    # ------------------------------------------------------------------ life cycle
    def start(self) -> str:
        """Open the pty and start serving; returns the slave path."""
        if self._thread is not None:
            return self.path
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        self.path = os.ttyname(self._slave)
        self._wake_r, self._wake_w = os.pipe()
        self._stop.clear()
        self._thread = threading.Thread(target=self._serve, name="xarm-emulator", daemon=True)
        self._thread.start()
        return self.path

    def close(self) -> None:
        """Stop serving, join the thread and close every fd; safe to call twice."""
        thread, self._thread = self._thread, None
        if thread is not None:
            self._stop.set()
            with contextlib.suppress(OSError):
                os.write(self._wake_w, b"x")
            thread.join(timeout=5.0)
        for name in ("_master", "_slave", "_wake_r", "_wake_w"):
            fd = getattr(self, name)
            if fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(fd)
                setattr(self, name, -1)

    def __enter__(self) -> XArmEmulator:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def running(self) -> bool:
        """Whether the serving thread is alive."""
        return self._thread is not None and self._thread.is_alive()

    # ------------------------------------------------------------------ fault injection
    def inject(self, kind: FaultKind, *, count: int = 1, register: int | None = None, stall_s: float = 1.0) -> None:
        """Spoil the next ``count`` replies (to ``register`` only, if given).

        Kinds: ``corrupt_crc`` flips the CRC; ``drop`` sends nothing (the command
        still takes effect, as when a reply is lost on the line); ``truncate`` sends
        half the frame; ``stall`` delays the reply by ``stall_s`` seconds; ``lag``
        holds the reply back and sends it in answer to the next request instead of that
        one's, which is held in turn (replies one request behind, as long as lag faults
        last; the first reply after them goes out right behind the held one). Over TCP only:
        ``stale_id`` sends the reply with the previous request's transaction id (the reply
        the client waits for never comes); ``corrupt_crc`` garbles the protocol id.
        """
        with self._lock:
            for _ in range(count):
                self._faults.append(InjectedFault(kind, None if register is None else int(register), float(stall_s)))

    def take_fault(self, register: int) -> InjectedFault | None:
        """The next injected fault that applies to a reply to ``register`` (removed from the queue)."""
        return self._next_fault(register)

    def pending_faults(self) -> int:
        """Injected faults not yet applied."""
        with self._lock:
            return len(self._faults)

    def fail_next_move(self, code: int, *, after_polls: int = 2) -> None:
        """Raise controller error ``code`` during the next MOVE_LINE, after ``after_polls``
        GET_STATE requests have seen it moving."""
        with self._lock:
            self._scheduled = _ScheduledError(int(code), int(after_polls))

    # ------------------------------------------------------------------ state
    def _errors(self) -> tuple[int, int]:
        code, warn = self.arm.current_error()
        return int(code), int(warn)

    def _state_value(self) -> int:
        code, _ = self._errors()
        if code or not self._ready:
            return int(RobotState.STOPPED)
        return int(RobotState.MOVING if self.arm.is_moving() else RobotState.SLEEPING)

    def _state_byte(self) -> int:
        code, warn = self._errors()
        flags = 0
        if code:
            flags |= FLAG_ERROR
        if warn:
            flags |= FLAG_WARNING
        if code or not self._ready or not self._enabled:
            flags |= FLAG_NOT_READY
        return flags

    def _halt(self) -> None:
        if self.arm.is_moving():
            with contextlib.suppress(CellcalError):
                self.arm.stop()

    def controller_state(self) -> dict[str, int | bool]:
        """The emulated controller's state (for tests and logs)."""
        with self._lock:
            code, warn = self._errors()
            return {"state": self._state_value(), "mode": self._mode, "enabled": self._enabled,
                    "ready": self._ready, "error": code, "warn": warn}

    # ------------------------------------------------------------------ handlers: (flags, data)
    def _get_version(self, _p: bytes) -> tuple[int, bytes]:
        return 0, self._version_reply

    def _get_robot_sn(self, _p: bytes) -> tuple[int, bytes]:
        return 0, self._serials_reply

    def _motion_en(self, p: bytes) -> tuple[int, bytes]:
        if len(p) != 2 or not (1 <= p[0] <= EVERY_JOINT):
            return FLAG_INVALID, b""
        if p[1]:
            self._enabled = True
        else:
            self._halt()
            self._enabled = False
            self._ready = False
        return 0, b""

    def _set_state(self, p: bytes) -> tuple[int, bytes]:
        if len(p) != 1:
            return FLAG_INVALID, b""
        value = p[0]
        if value == StateCommand.RUN:
            code, _ = self._errors()
            if self._enabled and code == 0:
                self._ready = True
            return 0, b""
        if value in (StateCommand.STOP, StateCommand.DECELERATE_STOP):
            self.stop_requests += 1
            self._halt()
            self._ready = False
            return 0, b""
        return FLAG_INVALID, b""

    def _get_state(self, _p: bytes) -> tuple[int, bytes]:
        sched = self._scheduled
        if sched is not None and sched.armed and self.arm.is_moving():
            sched.polls += 1
            if sched.polls >= sched.after_polls:
                self.arm.set_error(sched.code)
                self._halt()
                self._scheduled = None
        return 0, bytes([self._state_value()])

    def _get_cmdnum(self, _p: bytes) -> tuple[int, bytes]:
        return 0, struct.pack(">H", 1 if self.arm.is_moving() and self._ready else 0)

    def _get_error(self, _p: bytes) -> tuple[int, bytes]:
        code, warn = self._errors()
        return 0, bytes([code & 0xFF, warn & 0xFF])

    def _clean_err(self, _p: bytes) -> tuple[int, bytes]:
        _code, warn = self.arm.current_error()
        self.arm.set_error(0, warn)
        self._ready = False
        return 0, b""

    def _clean_war(self, _p: bytes) -> tuple[int, bytes]:
        code, warn = self.arm.current_error()
        if warn:
            self.arm.set_error(code, 0)
        return 0, b""

    def _set_mode(self, p: bytes) -> tuple[int, bytes]:
        if len(p) not in (1, 2):
            return FLAG_INVALID, b""
        self._halt()
        self._mode = p[0]
        self._ready = False
        return 0, b""

    def _target_pose(self, cmd: LineMove) -> Pose:
        current = np.asarray(pose_to_xarm(self.arm.true_flange_pose()), dtype=np.float64)
        values = [c if math.isinf(v) else v for v, c in zip(cmd.pose, current, strict=True)]
        if cmd.axis_angle:
            rotvec = np.asarray(values[3:], dtype=np.float64)
            if any(math.isinf(v) for v in cmd.pose[3:]):
                rotvec = Rotation.from_euler("xyz", current[3:]).as_rotvec()
            return Pose(Rotation.from_rotvec(rotvec), np.asarray(values[:3]) / 1000.0)
        return pose_from_xarm(np.asarray(values, dtype=np.float64))

    def _move_line(self, p: bytes) -> tuple[int, bytes]:
        cmd = read_line_move(p)
        if cmd is None:
            return FLAG_INVALID, b""
        self.last_move = cmd
        extra = bytes(EXTENDED_LINE_REPLY_BYTES) if cmd.common else b""
        code, _ = self._errors()
        if code:
            return 0, extra
        if not self._ready or not self._enabled or self._mode != 0:
            return 0, extra
        if cmd.coord != 0 or any(math.isnan(v) for v in cmd.pose) \
                or not (cmd.speed_mm_s > 0 and cmd.acc_mm_s2 > 0) \
                or not (math.isfinite(cmd.speed_mm_s) and math.isfinite(cmd.acc_mm_s2)):
            return FLAG_INVALID, extra
        target = self._target_pose(cmd)
        if cmd.only_check:
            return 0, extra
        try:
            self.arm.begin_move_linear(target, cmd.speed_mm_s / 1000.0, cmd.acc_mm_s2 / 1000.0)
        except CellcalError:
            # Refused by the model: the controller latches an error.
            if not self._errors()[0]:
                self.arm.set_error(ERROR_OUT_OF_REACH)
        if self._errors()[0]:
            # The sim arm latches error 21 for a target outside its workspace and does not move.
            self._ready = False
            return 0, extra
        sched = self._scheduled
        if sched is not None:
            sched.armed = True
        return 0, extra

    def _set_feedback_type(self, p: bytes) -> tuple[int, bytes]:
        if len(p) != 1:
            return FLAG_INVALID, b""
        self.feedback_type = p[0]
        return 0, b""

    def report_values(self) -> ReportValues:
        """What the controller's report says now (noise-free pose: reports do not draw read-back noise)."""
        with self._lock:
            code, warn = self._errors()
            pose = np.asarray(pose_to_xarm(self.arm.true_flange_pose()), dtype=np.float64)
            joints = np.asarray(self.arm.joint_positions(), dtype=np.float64).ravel()[:JOINT_REPLY_FLOATS]
            moving = self.arm.is_moving()
            return ReportValues(state=self._state_value(), mode=self._mode,
                                cmdnum=1 if moving and self._ready else 0, joints=tuple(float(v) for v in joints),
                                pose=tuple(float(v) for v in pose), error=code, warning=warn,
                                enabled=self._enabled, axes=self.axes, arm_type=self.axes)

    def _get_tcp_pose(self, _p: bytes) -> tuple[int, bytes]:
        values = np.asarray(pose_to_xarm(self.arm.get_pose()), dtype=np.float64)
        self.last_reported_pose = tuple(float(v) for v in values.astype(np.float32))
        return 0, floats(list(values))

    def _get_tcp_pose_aa(self, _p: bytes) -> tuple[int, bytes]:
        pose = self.arm.get_pose()
        return 0, floats([*(pose.translation * 1000.0), *pose.rotation.as_rotvec()])

    def _get_joint_pos(self, _p: bytes) -> tuple[int, bytes]:
        joints = np.zeros(JOINT_REPLY_FLOATS)
        q = np.asarray(self.arm.joint_positions(), dtype=np.float64).ravel()[:JOINT_REPLY_FLOATS]
        joints[: q.size] = q
        return 0, floats(list(joints))

    # ------------------------------------------------------------------ serving
    def execute(self, request: Command) -> tuple[int, bytes]:
        """Execute one request; returns the reply's STATE flags and data (any transport)."""
        with self._lock:
            self.requests[request.register] = self.requests.get(request.register, 0) + 1
            handler = self._handlers.get(request.register)
            if handler is None:
                flags, data = FLAG_INVALID, b""
            else:
                flags, data = handler(request.params)
            return self._state_byte() | flags, data

    def handle(self, request: Command) -> bytes:
        """Execute one request and return the serial reply frame (before fault injection)."""
        return reply_frame(*self.execute(request))

    def _next_fault(self, register: int) -> InjectedFault | None:
        with self._lock:
            for i, fault in enumerate(self._faults):
                if fault.register is None or fault.register == register:
                    del self._faults[i]
                    return fault
        return None

    def _send(self, frame: bytes, register: int) -> None:
        fault = self._next_fault(register)
        held, self._held = self._held, None
        if fault is not None and fault.kind == "lag":
            self._held = frame
            if held is not None:
                self._write_all(held)
            return
        if held is not None:
            frame = held + frame  # the end of a lag: the late reply, then this one
        if fault is not None:
            if fault.kind == "drop":
                return
            if fault.kind == "corrupt_crc":
                frame = frame[:-2] + bytes([frame[-2] ^ 0xFF, frame[-1] ^ 0x5A])
            elif fault.kind == "truncate":
                frame = frame[: max(1, len(frame) // 2)]
            elif fault.kind == "stall" and self._stop.wait(fault.stall_s):
                return
        self._write_all(frame)

    def _write_all(self, frame: bytes) -> None:
        view = memoryview(frame)
        while view and not self._stop.is_set():
            try:
                n = os.write(self._master, view)
            except BlockingIOError:
                select.select([], [self._master], [], 0.05)
                continue
            except OSError:
                return
            view = view[n:]

    def _serve(self) -> None:
        reader = RequestReader()
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([self._master, self._wake_r], [], [], 0.5)
            except (OSError, ValueError):
                return
            if self._wake_r in ready or self._stop.is_set():
                return
            if self._master not in ready:
                continue
            try:
                data = os.read(self._master, 4096)
            except OSError:
                continue
            dropped = reader.bad_frames
            requests = reader.feed(data)
            self.bad_requests += reader.bad_frames - dropped
            for request in requests:
                try:
                    reply = self.handle(request)
                except Exception:
                    self.bad_requests += 1
                    reply = reply_frame(FLAG_INVALID)
                self._send(reply, request.register)
