"""xArm register numbers and their parameter / reply layouts (pure).

Facts from ``shared/spec/protocols.md`` part D4, checked against the installed
``xarm-python-sdk``: floats are float32 little-endian, the command counter is a
big-endian uint16, wire units are millimetres and radians.
"""

from __future__ import annotations

import math
import re
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from enum import IntEnum

from cellcal.devices.errors import ProtocolError


class Reg(IntEnum):
    """Register (command) numbers used by cellcal and by the SDK's serial polling."""

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


READ_REGISTERS: frozenset[int] = frozenset({
    Reg.GET_VERSION, Reg.GET_ROBOT_SN, Reg.GET_STATE, Reg.GET_CMDNUM, Reg.GET_ERROR,
    Reg.GET_TCP_POSE, Reg.GET_JOINT_POS, Reg.GET_TCP_POSE_AA,
})
"""Idempotent reads: the only requests the transport may send again after a bad or missing reply."""

MOTION_REGISTERS: frozenset[int] = frozenset({*range(21, 26), *range(27, 31), 83, 92, 93})
"""Commands that move the arm, by the SDK's register table (MOVE_LINE 21, MOVE_LINEB,
MOVE_JOINT, MOVE_JOINTB, MOVE_HOME 25, MOVE_CIRCLE 27, MOVE_LINE_TOOL, MOVE_SERVOJ,
MOVE_SERVO_CART 30, MOVE_RELATIVE 83, MOVE_LINE_AA 92, MOVE_SERVO_CART_AA 93): sent once,
never again, whatever the reply (ADR 0016). SET_STATE 0 (run) can resume a paused queue,
so every write is sent once too; only :data:`READ_REGISTERS` are retried."""


class ArmState(IntEnum):
    """Values of the GET_STATE reply."""

    MOVING = 1
    SLEEPING = 2
    """Idle and ready: the motion queue is empty."""
    SUSPENDED = 3
    STOPPED = 4
    """Stopped / not ready; a SET_STATE 0 is needed before moving."""
    STOPPING = 5


class SetState(IntEnum):
    """Parameters of SET_STATE."""

    RUN = 0
    PAUSE = 3
    STOP = 4
    DECELERATE_STOP = 6


ALL_AXES = 8
"""MOTION_EN axis id meaning "every joint"."""

VERSION_LEN = 40
"""Data bytes of the GET_VERSION and GET_ROBOT_SN replies."""
JOINT_FLOATS = 7
"""GET_JOINT_POS always carries 7 floats, whatever the axis count."""
COMMON_MOVE_LINE_SINCE = (1, 11, 100)
"""Firmware from which MOVE_LINE takes the extended ("common") parameter layout."""
MOVE_LINE_COMMON_REPLY = 3
"""Data bytes in the reply to an extended MOVE_LINE (only-check result in the last)."""


def pack_floats(values: Sequence[float]) -> bytes:
    """float32 little-endian."""
    return struct.pack(f"<{len(values)}f", *values)


def unpack_floats(data: bytes, count: int) -> tuple[float, ...]:
    """Read ``count`` float32 LE values from the start of ``data``.

    Raises:
        ProtocolError: If ``data`` is shorter than ``4 * count`` bytes.
    """
    if len(data) < 4 * count:
        raise ProtocolError(f"xarm reply carries {len(data)} bytes, expected {4 * count} for {count} floats",
                            offset=len(data))
    return struct.unpack_from(f"<{count}f", data)


def encode_move_line(pose_mm_rad: Sequence[float], speed_mm_s: float, acc_mm_s2: float,
                     *, common: bool, mvtime: float = 0.0) -> bytes:
    """Parameters of MOVE_LINE in the base frame, fixed-axis roll/pitch/yaw.

    Args:
        pose_mm_rad: ``[x, y, z]`` millimetres then ``[roll, pitch, yaw]`` radians.
        speed_mm_s: Tool speed, mm/s.
        acc_mm_s2: Tool acceleration, mm/s².
        common: Use the extended layout of firmware >= 1.11.100 (adds a blend radius
            float -1 = none, and the bytes ``[coord 0 = base, is_axis_angle 0,
            only_check 0]``).
        mvtime: Reserved by the controller; 0.

    Raises:
        ProtocolError: If the pose does not have 6 finite numbers.
    """
    values = [float(v) for v in pose_mm_rad]
    if len(values) != 6 or not all(math.isfinite(v) for v in values):
        raise ProtocolError(f"xarm MOVE_LINE needs 6 finite numbers, got {values}")
    floats = [*values, float(speed_mm_s), float(acc_mm_s2), float(mvtime)]
    if not common:
        return pack_floats(floats)
    return pack_floats([*floats, -1.0]) + bytes([0, 0, 0])


def decode_text(data: bytes) -> str:
    """ASCII text up to the first NUL (version / serial replies)."""
    return data.split(b"\0", 1)[0].decode("ascii", errors="replace")


def decode_serials(data: bytes) -> tuple[str, str]:
    """GET_ROBOT_SN reply: robot serial, NUL, control-box serial, NUL."""
    parts = data.split(b"\0")
    robot = parts[0].decode("ascii", errors="replace")
    box = parts[1].decode("ascii", errors="replace").strip() if len(parts) > 1 else ""
    return robot, box


@dataclass(frozen=True)
class VersionInfo:
    """What the GET_VERSION string says.

    Attributes:
        text: The whole string, e.g. ``"6,6,XS1305EMU0001,AC1305EMU0001,v2.5.0"``.
        axes: Axis count, or None if the string has no such field.
        arm_type: Arm type number, or None.
        robot_sn: Robot serial ("" if absent).
        box_sn: Control-box serial ("" if absent).
        firmware: ``(major, minor, revision)``, or None if no ``vX.Y.Z`` is found.
    """

    text: str
    axes: int | None
    arm_type: int | None
    robot_sn: str
    box_sn: str
    firmware: tuple[int, int, int] | None

    @property
    def uses_common_move_line(self) -> bool:
        """Whether MOVE_LINE takes the extended layout (firmware >= 1.11.100)."""
        return self.firmware is not None and self.firmware >= COMMON_MOVE_LINE_SINCE


_VERSION_FULL = re.compile(r"^\s*(\d+)\s*,\s*(\d+)\s*,([^,]*),([^,]*),.*?[vV]?(\d+)\.(\d+)\.(\d+)")
_VERSION_ONLY = re.compile(r"[vV]?(\d+)\.(\d+)\.(\d+)")


def parse_version(text: str) -> VersionInfo:
    """Parse the GET_VERSION string ``"axes,type,robot_sn,box_sn,vX.Y.Z"`` (fields optional)."""
    m = _VERSION_FULL.match(text)
    if m:
        axes, arm_type, sn, box, a, b, c = m.groups()
        return VersionInfo(text, int(axes), int(arm_type), sn.strip(), box.strip(), (int(a), int(b), int(c)))
    m2 = _VERSION_ONLY.search(text)
    fw = (int(m2.group(1)), int(m2.group(2)), int(m2.group(3))) if m2 else None
    return VersionInfo(text, None, None, "", "", fw)
