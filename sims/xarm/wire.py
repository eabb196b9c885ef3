"""The controller's side of UFACTORY's xArm serial protocol ("UX2 hex"), for the emulator.

Pure functions on bytes and a small stream reader; no I/O. Written from the protocol
facts (``shared/spec/protocols.md`` part D) and on purpose independent of the driver's
wire code (docs/adr/0014-simulated-cell.md). Frame layouts: :data:`REQUEST_MAGIC`,
:data:`REPLY_MAGIC`; checksum: :func:`modbus_crc`; numbers: :func:`floats`.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum

REQUEST_MAGIC = b"\xaa\x55"
"""Host id, arm id: the first two bytes of a request.

A request is ``AA 55 LEN REG params... CRC_lo CRC_hi``; LEN counts REG + params.
"""
REPLY_MAGIC = b"\x55\xaa"
"""Arm id, host id: the first two bytes of a reply.

A reply is ``55 AA LEN FLAGS data... CRC_lo CRC_hi``; LEN counts FLAGS + data and stays
below 50 (UFACTORY's SDK drops longer frames). No register echo on the serial line.
"""
MAX_REPLY_DATA = 48
"""Data bytes a reply may carry (LEN = 1 + data <= 49)."""

# FLAGS bits of a reply.
FLAG_ERROR = 0x40  # an error is pending
FLAG_WARNING = 0x20  # a warning is pending
FLAG_NOT_READY = 0x10  # not ready to move
FLAG_INVALID = 0x08  # invalid command / execution failed


class Register(IntEnum):
    """The registers (commands) the emulated controller serves.

    The driver keeps its own table of the same numbers on purpose (see
    docs/adr/0014-simulated-cell.md); tests/integration/xarm/test_xarm_sdk.py checks both against UFACTORY's SDK.
    """

    GET_VERSION = 1
    GET_ROBOT_SN = 2
    MOTION_EN = 11
    SET_STATE = 12
    GET_STATE = 13
    GET_CMDNUM = 14
    GET_ERROR = 15
    CLEAN_ERR = 16
    CLEAN_WAR = 17
    SET_MODE = 19
    MOVE_LINE = 21
    GET_TCP_POSE = 41
    GET_JOINT_POS = 42
    GET_TCP_POSE_AA = 91
    SET_FEEDBACK_TYPE = 254


class RobotState(IntEnum):
    """Values the controller reports in its GET_STATE reply."""

    MOVING = 1
    SLEEPING = 2
    SUSPENDED = 3
    STOPPED = 4


class StateCommand(IntEnum):
    """Arguments of SET_STATE the controller accepts."""

    RUN = 0
    PAUSE = 3
    STOP = 4
    DECELERATE_STOP = 6


EVERY_JOINT = 8
"""MOTION_EN joint id that addresses every joint at once."""
TEXT_REPLY_BYTES = 40
"""GET_VERSION / GET_ROBOT_SN reply data: NUL-padded ASCII."""
JOINT_REPLY_FLOATS = 7
"""GET_JOINT_POS always answers 7 floats, whatever the axis count."""
EXTENDED_LINE_REPLY_BYTES = 3
"""Data bytes answered to a MOVE_LINE that carried trailing option bytes."""

_LEGACY_LINE_FLOATS = 9  # x y z roll pitch yaw, speed, acc, mvtime
_EXTENDED_LINE_FLOATS = 10  # ... plus the blend radius


def modbus_crc(data: bytes) -> int:
    """CRC-16/MODBUS of ``data`` (sent low byte first): init 0xFFFF, reflected polynomial 0xA001.

    Every frame ends with the CRC of everything before it.
    """
    crc = 0xFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            lsb = crc & 1
            crc >>= 1
            if lsb:
                crc ^= 0xA001
    return crc


def reply_frame(flags: int, data: bytes = b"") -> bytes:
    """The reply frame carrying ``flags`` and ``data``.

    Raises:
        ValueError: If ``flags`` is not a byte or ``data`` exceeds :data:`MAX_REPLY_DATA`
            (a bug in the emulator, never a client's fault).
    """
    if not 0 <= flags <= 0xFF or len(data) > MAX_REPLY_DATA:
        raise ValueError(f"xarm emulator: cannot frame flags {flags} with {len(data)} data bytes")
    body = REPLY_MAGIC + bytes((len(data) + 1, flags)) + data
    return body + struct.pack("<H", modbus_crc(body))


@dataclass(frozen=True)
class Command:
    """One request the host sent: its register and parameter bytes."""

    register: int
    params: bytes


class RequestReader:
    """Turn the bytes a host writes into checked :class:`Command` objects.

    Bytes that do not start a request are skipped; a frame whose CRC does not match
    is dropped whole and counted in :attr:`bad_frames`.

    Attributes:
        bad_frames: Complete frames dropped for a CRC mismatch or a zero LEN.
        skipped_bytes: Bytes discarded while looking for a request header.
    """

    def __init__(self) -> None:
        self._pending = b""
        self.bad_frames = 0
        self.skipped_bytes = 0

    def feed(self, data: bytes) -> list[Command]:
        """Add received bytes; return the commands completed by them, in order."""
        buf = self._pending + bytes(data)
        commands: list[Command] = []
        while True:
            start = buf.find(REQUEST_MAGIC)
            if start < 0:
                keep = 1 if buf.endswith(REQUEST_MAGIC[:1]) else 0
                self.skipped_bytes += len(buf) - keep
                buf = buf[len(buf) - keep:]
                break
            self.skipped_bytes += start
            buf = buf[start:]
            if len(buf) < 3:
                break
            size = buf[2]
            if size == 0:
                self.bad_frames += 1
                buf = buf[3:]
                continue
            end = 3 + size + 2
            if len(buf) < end:
                break
            frame, buf = buf[:end], buf[end:]
            if struct.unpack("<H", frame[-2:])[0] != modbus_crc(frame[:-2]):
                self.bad_frames += 1
                continue
            commands.append(Command(frame[3], frame[4:-2]))
        self._pending = buf
        return commands


def floats(values: list[float]) -> bytes:
    """``values`` as float32 little-endian (the wire's numbers: millimetres and radians).

    The command counter (the GET_CMDNUM reply) is a big-endian uint16 instead.
    """
    return struct.pack(f"<{len(values)}f", *values)


def text_field(text: str) -> bytes:
    """ASCII ``text`` NUL-padded to :data:`TEXT_REPLY_BYTES` (it must be shorter)."""
    raw = text.encode("ascii")
    if len(raw) >= TEXT_REPLY_BYTES:
        raise ValueError(f"xarm emulator: {text!r} does not fit a {TEXT_REPLY_BYTES}-byte text reply")
    return raw + bytes(TEXT_REPLY_BYTES - len(raw))


@dataclass(frozen=True)
class LineMove:
    """A MOVE_LINE request as the controller reads it.

    Attributes:
        pose: ``[x, y, z]`` mm and ``[roll, pitch, yaw]`` rad (a rotation vector when
            :attr:`axis_angle`); ``inf`` keeps the current value of that coordinate.
        speed_mm_s: Tool speed, mm/s.
        acc_mm_s2: Tool acceleration, mm/s².
        radius_mm: Blend radius (-1 none), None in the legacy layout.
        coord: 0 base frame, 1 tool frame.
        axis_angle: The orientation is a rotation vector.
        only_check: Nonzero: check reachability only, do not move.
        common: Trailing option bytes were sent, so the reply carries
            :data:`EXTENDED_LINE_REPLY_BYTES` data bytes.
    """

    pose: tuple[float, ...]
    speed_mm_s: float
    acc_mm_s2: float
    radius_mm: float | None = None
    coord: int = 0
    axis_angle: bool = False
    only_check: int = 0
    common: bool = False


def read_line_move(params: bytes) -> LineMove | None:
    """Read MOVE_LINE parameters; None if their length fits no layout.

    Layouts (UFACTORY SDK): legacy = 9 floats, optionally followed by
    ``[only_check]`` or ``[only_check, motion_type]``; extended (firmware >= 1.11.100)
    = 10 floats (the 10th the blend radius) then ``[coord, is_axis_angle, only_check]``
    and optionally ``[motion_type]``.
    """
    legacy = 4 * _LEGACY_LINE_FLOATS
    extended = 4 * _EXTENDED_LINE_FLOATS + 3
    n = len(params)
    if legacy <= n <= legacy + 2:
        values = struct.unpack_from(f"<{_LEGACY_LINE_FLOATS}f", params)
        tail = params[legacy:]
        return LineMove(tuple(values[:6]), values[6], values[7], only_check=tail[0] if tail else 0,
                        common=bool(tail))
    if extended <= n <= extended + 1:
        values = struct.unpack_from(f"<{_EXTENDED_LINE_FLOATS}f", params)
        coord, axis_angle, only_check = params[40:43]
        return LineMove(tuple(values[:6]), values[6], values[7], radius_mm=values[9], coord=coord,
                        axis_angle=bool(axis_angle), only_check=only_check, common=True)
    return None
