"""The controller's side of the xArm's TCP protocol, for the emulator: control-port frames and the rich report.

Pure functions on bytes; no I/O. Written from ``shared/spec/protocols.md`` part D2 and the
report layout the installed ``xarm-python-sdk`` parses, independent of the driver's wire
code (docs/adr/0014-simulated-cell.md). Control frames: :func:`read_requests`,
:func:`reply_bytes`; the report: :func:`rich_report`.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from .wire import Command

HEADER = struct.Struct(">HHH")
"""Transaction id, protocol id, length (counts REG + params, or REG + STATE + data)."""
PROTOCOL_IDS = (2, 3)
"""Protocol ids of the register protocol; the SDK switches from 2 to 3 (with keep-alive) on newer firmware."""
HEARTBEAT_PROTOCOL = 1
"""Protocol id of the SDK's optional heartbeat frame (no reply)."""
MAX_REQUEST_LENGTH = 1024
"""Largest length field the emulator reads; a larger one ends the connection."""
RICH_REPORT_BYTES = 245
"""Size of the rich report the emulator sends (the layout every SDK since 2019 reads)."""


@dataclass(frozen=True)
class TcpCommand:
    """One request read from a control connection."""

    transaction_id: int
    protocol: int
    command: Command


def read_requests(buffer: bytearray) -> list[TcpCommand]:
    """Take the whole request frames off the front of ``buffer`` (in place); heartbeats are skipped.

    Raises:
        ValueError: On a length field of 0 or above :data:`MAX_REQUEST_LENGTH` (the stream
            cannot be followed past it; the caller closes the connection).
    """
    out: list[TcpCommand] = []
    while len(buffer) >= HEADER.size:
        tid, protocol, length = HEADER.unpack_from(buffer)
        if not 1 <= length <= MAX_REQUEST_LENGTH:
            raise ValueError(f"xarm emulator: request length field {length}")
        end = HEADER.size + length
        if len(buffer) < end:
            break
        register, params = buffer[HEADER.size], bytes(buffer[HEADER.size + 1:end])
        del buffer[:end]
        if protocol in PROTOCOL_IDS:
            out.append(TcpCommand(tid, protocol, Command(register, params)))
    return out


def reply_bytes(transaction_id: int, protocol: int, register: int, flags: int, data: bytes = b"") -> bytes:
    """One reply frame: header, the register echo, the STATE flags, the data."""
    return HEADER.pack(transaction_id & 0xFFFF, protocol, len(data) + 2) + bytes((register, flags)) + data


@dataclass(frozen=True)
class ReportValues:
    """What one report tells; wire units (mm, rad).

    Attributes:
        state: GET_STATE value (1 moving, 2 sleeping, 4 stopped).
        mode: Control mode.
        cmdnum: Commands queued.
        joints: Joint angles, rad (padded to 7).
        pose: x, y, z mm, roll, pitch, yaw rad.
        error: Controller error code.
        warning: Controller warning code.
        enabled: Motors enabled (and brakes released).
        axes: Axis count.
        arm_type: Arm type number.
    """

    state: int
    mode: int
    cmdnum: int
    joints: tuple[float, ...]
    pose: tuple[float, ...]
    error: int
    warning: int
    enabled: bool
    axes: int
    arm_type: int


#: Limits the rich report carries (TCP jerk, min/max acc, min/max speed; joint the same; rotation jerk, max acc).
_TCP_LIMITS = (10000.0, 1.0, 50000.0, 0.1, 1000.0)
_JOINT_LIMITS = (500.0, 0.01, 20.0, 0.01, 3.14)
_ROT_LIMITS = (50.0, 20.0)


def rich_report(values: ReportValues) -> bytes:
    """The :data:`RICH_REPORT_BYTES`-byte rich report (u32 BE length first; floats LE).

    Offsets: 4 state | mode << 4; 5 cmdnum (u16 BE); 7 joints (7 f32); 35 pose (6 f32);
    59 torques (7 f32); 87 brake bits, enable bits, error, warning; 91 pose offset (6 f32);
    115 TCP load (4 f32); 131 collision and teach sensitivity; 133 gravity direction
    (3 f32); 145 arm type, axes, master id, slave id, motor tid, motor fid; 151 version
    text (30 bytes); 181 TCP limits (5 f32); 201 joint limits (5 f32); 221 rotation limits
    (2 f32); 229 servo status/code pairs (16 bytes).
    """
    bits = (1 << values.axes) - 1 if values.enabled else 0
    joints = (tuple(values.joints) + (0.0,) * 7)[:7]
    out = bytearray(struct.pack(">IBH", RICH_REPORT_BYTES, (values.state & 0x0F) | (values.mode & 0x0F) << 4,
                                values.cmdnum & 0xFFFF))
    out += struct.pack("<7f", *joints) + struct.pack("<6f", *values.pose) + struct.pack("<7f", *([0.0] * 7))
    out += bytes((bits, bits, values.error & 0xFF, values.warning & 0xFF))
    out += struct.pack("<6f", *([0.0] * 6)) + struct.pack("<4f", *([0.0] * 4))
    out += bytes((3, 3)) + struct.pack("<3f", 0.0, 0.0, -1.0)
    out += bytes((values.arm_type, values.axes, 1, 1, 0, 0)) + bytes(30)
    out += struct.pack("<5f", *_TCP_LIMITS) + struct.pack("<5f", *_JOINT_LIMITS) + struct.pack("<2f", *_ROT_LIMITS)
    out += bytes(16)
    assert len(out) == RICH_REPORT_BYTES, len(out)  # the layout above adds up
    return bytes(out)
