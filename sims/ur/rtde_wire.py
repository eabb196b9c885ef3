"""RTDE wire format (protocol version 2), controller side: framing, setup messages and recipes.

Every message is a 3-byte header (u16 total size including the header, big-endian, then
a type byte) and a big-endian payload. Facts: ``shared/spec/protocols.md`` section C2.
"""

from __future__ import annotations

import re
import struct
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import cast

from cellcal.devices.errors import ProtocolError

# Message types (ASCII letters on the wire).
REQUEST_PROTOCOL_VERSION = 86       # 'V'
GET_URCONTROL_VERSION = 118         # 'v'
TEXT_MESSAGE = 77                   # 'M'
DATA_PACKAGE = 85                   # 'U'
CONTROL_PACKAGE_SETUP_OUTPUTS = 79  # 'O'
CONTROL_PACKAGE_SETUP_INPUTS = 73   # 'I'
CONTROL_PACKAGE_START = 83          # 'S'
CONTROL_PACKAGE_PAUSE = 80          # 'P'

HEADER = struct.Struct(">HB")
MAX_MESSAGE_BYTES = 0xFFFF           # the size field is a u16
PROTOCOL_VERSION = 2
NOT_FOUND = "NOT_FOUND"
IN_USE = "IN_USE"

#: struct codes (without byte order) and value counts of the RTDE types.
TYPE_CODES: dict[str, tuple[str, int]] = {
    "BOOL": ("?", 1), "UINT8": ("B", 1), "UINT32": ("I", 1), "UINT64": ("Q", 1), "INT32": ("i", 1),
    "DOUBLE": ("d", 1), "VECTOR3D": ("3d", 3), "VECTOR6D": ("6d", 6), "VECTOR6INT32": ("6i", 6),
    "VECTOR6UINT32": ("6I", 6),
}

_V6 = "VECTOR6D"
#: Output names with fixed types (UR's RTDE guide; the names ur_rtde 1.6 asks for are all here).
OUTPUT_TYPES: dict[str, str] = {
    "timestamp": "DOUBLE",
    **dict.fromkeys(("target_q", "target_qd", "target_qdd", "target_current", "target_moment", "actual_q",
                     "actual_qd", "actual_current", "actual_current_window", "joint_control_output",
                     "actual_TCP_pose", "actual_TCP_speed", "actual_TCP_force", "target_TCP_pose",
                     "target_TCP_speed", "joint_temperatures", "actual_joint_voltage", "ft_raw_wrench",
                     "payload_inertia", "joint_position_deviation_ratio"), _V6),
    **dict.fromkeys(("actual_digital_input_bits", "actual_digital_output_bits"), "UINT64"),
    **dict.fromkeys(("robot_mode", "safety_mode", "safety_status", "tool_output_voltage"), "INT32"),
    "joint_mode": "VECTOR6INT32",
    **dict.fromkeys(("actual_tool_accelerometer", "elbow_position", "elbow_velocity", "payload_cog"), "VECTOR3D"),
    **dict.fromkeys(("runtime_state", "robot_status_bits", "safety_status_bits", "analog_io_types",
                     "euromap67_input_bits", "euromap67_output_bits", "tool_mode", "tool_analog_input_types",
                     "output_bit_registers0_to_31", "output_bit_registers32_to_63", "input_bit_registers0_to_31",
                     "input_bit_registers32_to_63", "script_control_line", "time_scale_source"), "UINT32"),
    **dict.fromkeys(("tool_output_mode", "tool_digital_output0_mode", "tool_digital_output1_mode"), "UINT8"),
    **dict.fromkeys(("actual_execution_time", "speed_scaling", "target_speed_fraction", "actual_momentum",
                     "actual_main_voltage", "actual_robot_voltage", "actual_robot_current",
                     "standard_analog_input0", "standard_analog_input1", "standard_analog_output0",
                     "standard_analog_output1", "io_current", "euromap67_24V_voltage", "euromap67_24V_current",
                     "tool_analog_input0", "tool_analog_input1", "tool_output_current", "tool_temperature",
                     "tcp_force_scalar", "payload", "collision_detection_ratio"), "DOUBLE"),
}

#: Input names with fixed types (registers are matched by :data:`_REGISTER`).
INPUT_TYPES: dict[str, str] = {
    "speed_slider_mask": "UINT32", "speed_slider_fraction": "DOUBLE",
    **dict.fromkeys(("standard_digital_output_mask", "standard_digital_output", "configurable_digital_output_mask",
                     "configurable_digital_output", "tool_digital_output_mask", "tool_digital_output",
                     "standard_analog_output_mask", "standard_analog_output_type"), "UINT8"),
    "standard_analog_output_0": "DOUBLE", "standard_analog_output_1": "DOUBLE",
    "input_bit_registers0_to_31": "UINT32", "input_bit_registers32_to_63": "UINT32",
    "external_force_torque": _V6,
}

#: The index is at most three digits without a leading zero (the banks end at 127): a name with thousands of
#: digits is no field, never an int() of unbounded length (found by the fuzzer; Python refuses > 4300 digits).
_REGISTER = re.compile(r"(input|output)_(int|double|bit)_register_(0|[1-9][0-9]{0,2})\Z")
#: Register banks: (kind -> (RTDE type, first index, last index)).
REGISTER_BANKS: dict[str, tuple[str, int, int]] = {"int": ("INT32", 0, 47), "double": ("DOUBLE", 0, 47),
                                                   "bit": ("BOOL", 64, 127)}


def register_of(name: str) -> tuple[str, str, int] | None:
    """``(direction, kind, index)`` of a register name such as ``input_int_register_3``, else None."""
    m = _REGISTER.match(name)
    if m is None:
        return None
    direction, kind, index = m.group(1), m.group(2), int(m.group(3))
    _, lo, hi = REGISTER_BANKS[kind]
    return (direction, kind, index) if lo <= index <= hi else None


def output_type(name: str) -> str | None:
    """RTDE type of an output (readable) field, or None if the controller has no such field."""
    reg = register_of(name)
    if reg is not None:
        return REGISTER_BANKS[reg[1]][0]  # input registers may be read back as outputs too
    return OUTPUT_TYPES.get(name) or INPUT_TYPES.get(name)


def input_type(name: str) -> str | None:
    """RTDE type of an input (writable) field, or None if it cannot be written."""
    reg = register_of(name)
    if reg is not None:
        return REGISTER_BANKS[reg[1]][0] if reg[0] == "input" else None
    return INPUT_TYPES.get(name)


# ---------------------------------------------------------------------- recipes
@dataclass
class Recipe:
    """An output or input recipe: named fields packed in order.

    Attributes:
        recipe_id: The id on the wire (1..255).
        names: Field names, in the client's order.
        types: RTDE type per field.
        frequency_hz: Output rate (outputs only; 0 for inputs).
    """

    recipe_id: int
    names: tuple[str, ...]
    types: tuple[str, ...]
    frequency_hz: float = 0.0
    _struct: struct.Struct = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self._struct = struct.Struct(">" + "".join(TYPE_CODES[t][0] for t in self.types))

    @property
    def size(self) -> int:
        """Bytes of one packed data package body (after the recipe id)."""
        return self._struct.size

    def pack(self, values: Sequence[object]) -> bytes:
        """Pack one value per field (sequences for vector types) into a data package body."""
        flat: list[object] = []
        for value, kind in zip(values, self.types, strict=True):
            if TYPE_CODES[kind][1] > 1:
                flat.extend(cast(Sequence[object], value))
            else:
                flat.append(value)
        return self._struct.pack(*flat)

    def unpack(self, body: bytes) -> dict[str, object]:
        """Field values of a data package body (vectors as tuples)."""
        if len(body) != self._struct.size:
            raise ProtocolError(f"rtde: recipe {self.recipe_id} expects {self._struct.size} data bytes, "
                                f"got {len(body)}")
        flat = list(self._struct.unpack(body))
        out: dict[str, object] = {}
        for name, kind in zip(self.names, self.types, strict=True):
            n = TYPE_CODES[kind][1]
            out[name] = tuple(flat[:n]) if n > 1 else flat[0]
            del flat[:n]
        return out


# ---------------------------------------------------------------------- framing
def message(msg_type: int, payload: bytes = b"") -> bytes:
    """One framed message."""
    size = HEADER.size + len(payload)
    if size > MAX_MESSAGE_BYTES:
        raise ProtocolError(f"rtde: message of {size} bytes exceeds the u16 size field")
    return HEADER.pack(size, msg_type) + payload


class FrameReader:
    """Splits a byte stream into ``(type, payload)`` messages; bounded by the u16 size field."""

    def __init__(self) -> None:
        self._buf = bytearray()

    def feed(self, data: bytes) -> list[tuple[int, bytes]]:
        """Add received bytes; return the complete messages now available.

        Raises:
            ProtocolError: A size field smaller than the header (the stream cannot be resynchronised).
        """
        self._buf += data
        out: list[tuple[int, bytes]] = []
        while len(self._buf) >= HEADER.size:
            size, msg_type = HEADER.unpack_from(self._buf)
            if size < HEADER.size:
                raise ProtocolError(f"rtde: message size {size} is smaller than the 3-byte header")
            if len(self._buf) < size:
                break
            out.append((msg_type, bytes(self._buf[HEADER.size:size])))
            del self._buf[:size]
        return out


# ---------------------------------------------------------------------- client requests
def parse_protocol_request(payload: bytes) -> int:
    """The protocol version a ``V`` request asks for."""
    if len(payload) != 2:
        raise ProtocolError(f"rtde: protocol request of {len(payload)} bytes, expected 2")
    return int(struct.unpack(">H", payload)[0])


def _names(text: bytes) -> tuple[str, ...]:
    try:
        decoded = text.decode("ascii")
    except UnicodeDecodeError:
        raise ProtocolError("rtde: recipe names are not ASCII") from None
    names = tuple(n.strip() for n in decoded.split(","))
    if names and names[-1] == "":
        names = names[:-1]  # ur_rtde ends the list with a comma
    if not names or any(not n for n in names):
        raise ProtocolError(f"rtde: empty name in recipe {decoded!r}")
    return names


def parse_output_setup(payload: bytes) -> tuple[float, tuple[str, ...]]:
    """``(frequency_hz, names)`` of an ``O`` request (protocol 2: f64 frequency, then names)."""
    if len(payload) < 9:
        raise ProtocolError(f"rtde: output setup of {len(payload)} bytes is too short")
    (freq,) = struct.unpack_from(">d", payload)
    return float(freq), _names(payload[8:])


def parse_input_setup(payload: bytes) -> tuple[str, ...]:
    """Names of an ``I`` request."""
    return _names(payload)


# ---------------------------------------------------------------------- controller replies
def protocol_reply(accepted: bool) -> bytes:
    """Reply to ``V``."""
    return message(REQUEST_PROTOCOL_VERSION, bytes([1 if accepted else 0]))


def version_reply(major: int, minor: int, bugfix: int, build: int) -> bytes:
    """Reply to ``v``: the controller software version."""
    return message(GET_URCONTROL_VERSION, struct.pack(">IIII", major, minor, bugfix, build))


def setup_reply(msg_type: int, recipe_id: int, types: Sequence[str]) -> bytes:
    """Reply to ``O`` / ``I``: recipe id and one type (or NOT_FOUND / IN_USE) per name."""
    return message(msg_type, bytes([recipe_id & 0xFF]) + ",".join(types).encode("ascii"))


def start_reply(ok: bool) -> bytes:
    """Reply to ``S``."""
    return message(CONTROL_PACKAGE_START, bytes([1 if ok else 0]))


def pause_reply(ok: bool) -> bytes:
    """Reply to ``P``."""
    return message(CONTROL_PACKAGE_PAUSE, bytes([1 if ok else 0]))


def data_package(recipe_id: int, body: bytes) -> bytes:
    """An output data package: recipe id, then the packed fields."""
    return message(DATA_PACKAGE, bytes([recipe_id & 0xFF]) + body)


def text_message(text: str, source: str = "cellcal-ur-emulator", level: int = 1) -> bytes:
    """A ``M`` text message (protocol 2: length-prefixed message and source, then a warning level)."""
    msg = text.encode("utf-8")[:255]
    src = source.encode("ascii")[:255]
    return message(TEXT_MESSAGE, bytes([len(msg)]) + msg + bytes([len(src)]) + src + bytes([level & 0xFF]))
