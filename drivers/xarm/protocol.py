"""UFACTORY xArm serial framing ("UX2 hex") on the host side: CRC-16/MODBUS, requests out, replies in.

Pure functions on bytes, no I/O, so they can be fuzzed. Wire facts from
``shared/spec/protocols.md`` part D1, D3; each function names the layout it handles.
"""

from __future__ import annotations

from dataclasses import dataclass

from cellcal.devices.errors import ProtocolError

HOST_ID = 0xAA
"""First byte of a request, second byte of a reply."""
ARM_ID = 0x55
"""Second byte of a request, first byte of a reply."""
MAX_REPLY_LEN = 49
"""Largest LEN byte of a reply (STATE + at most 48 data bytes)."""
MAX_REQUEST_LEN = 255
"""Largest LEN byte of a request (one byte on the wire)."""

# Bits of a reply's STATE byte.
STATE_ERROR = 0x40
"""An uncleared controller error is pending."""
STATE_WARNING = 0x20
"""An uncleared controller warning is pending."""
STATE_NOT_READY = 0x10
"""Not ready to move."""
STATE_INVALID = 0x08
"""Invalid command, or its execution failed."""


def _crc_table() -> tuple[int, ...]:
    """CRC-16/MODBUS of each single byte value (the table of the byte-wise algorithm)."""
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):  # one shift per bit, least significant first (reflected)
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
        table.append(crc)
    return tuple(table)


_CRC_TABLE = _crc_table()


def crc16_modbus(data: bytes | bytearray | memoryview) -> int:
    """CRC-16/MODBUS of ``data`` (init 0xFFFF, reflected poly 0xA001, no final xor).

    Returns:
        The CRC as an int; on the wire it is sent low byte first.
    """
    crc = 0xFFFF
    for b in bytes(data):
        crc = (crc >> 8) ^ _CRC_TABLE[(crc ^ b) & 0xFF]  # fold in one byte through the table
    return crc


def crc_bytes(data: bytes | bytearray | memoryview) -> bytes:
    """The two CRC bytes to append to ``data`` (the whole frame before the CRC), low byte first."""
    return crc16_modbus(data).to_bytes(2, "little")


@dataclass(frozen=True)
class Reply:
    """One decoded reply frame.

    Attributes:
        state: The STATE byte.
        data: The data bytes after STATE (without CRC).
    """

    state: int
    data: bytes

    @property
    def error_pending(self) -> bool:
        """The controller holds an uncleared error (read it with GET_ERROR)."""
        return bool(self.state & STATE_ERROR)

    @property
    def warning_pending(self) -> bool:
        """The controller holds an uncleared warning."""
        return bool(self.state & STATE_WARNING)

    @property
    def not_ready(self) -> bool:
        """The arm is not ready to move (needs motion enable / mode / state 0)."""
        return bool(self.state & STATE_NOT_READY)

    @property
    def invalid(self) -> bool:
        """The command was invalid or failed to execute."""
        return bool(self.state & STATE_INVALID)


def encode_request(register: int, params: bytes = b"") -> bytes:
    """Build a request frame: ``0xAA 0x55 LEN REG params... CRC_lo CRC_hi`` (LEN counts REG + params).

    Args:
        register: Register number, 0..255.
        params: Parameter bytes (at most 254).

    Raises:
        ProtocolError: If the register or the parameter length does not fit a frame.
    """
    if not 0 <= register <= 255:
        raise ProtocolError(f"xarm register must be 0..255, got {register}")
    if len(params) + 1 > MAX_REQUEST_LEN:
        raise ProtocolError(f"xarm request parameters too long: {len(params)} bytes")
    head = bytes([HOST_ID, ARM_ID, len(params) + 1, register]) + bytes(params)
    return head + crc_bytes(head)


def check_frame(frame: bytes, first: int, second: int, max_len: int, what: str) -> int:
    """Check one whole frame: header bytes ``first``, ``second``, LEN in 1..``max_len``, size, CRC.

    Returns:
        The LEN byte (the frame is ``3 + LEN + 2`` bytes long).

    Raises:
        ProtocolError: Naming ``what`` (``"reply"``, ``"request"``) and the first problem found.
    """
    if len(frame) < 6:
        raise ProtocolError(f"xarm {what} frame too short: {len(frame)} bytes (need at least 6)", offset=len(frame))
    if frame[0] != first or frame[1] != second:
        raise ProtocolError(f"xarm {what} frame has bad header {frame[0]:#04x} {frame[1]:#04x}", offset=0)
    length = frame[2]
    if length < 1 or length > max_len:
        raise ProtocolError(f"xarm {what} frame has bad LEN {length}", offset=2)
    total = 3 + length + 2
    if len(frame) != total:
        raise ProtocolError(f"xarm {what} frame is {len(frame)} bytes but LEN {length} says {total}",
                            offset=min(len(frame), total))
    expected = crc16_modbus(frame[: 3 + length])
    got = int.from_bytes(frame[3 + length:], "little")
    if got != expected:
        raise ProtocolError(f"xarm {what} CRC mismatch: got {got:#06x}, expected {expected:#06x}", offset=3 + length)
    return length


def parse_reply(frame: bytes | bytearray | memoryview) -> Reply:
    """Decode exactly one reply frame: ``0x55 0xAA LEN STATE data... CRC_lo CRC_hi``.

    LEN counts STATE + data and is below 50 (the vendor's parser drops longer frames).
    There is no register echo on the serial line: a reply is matched to its request
    only by order (and by the data length the caller expects).

    Raises:
        ProtocolError: On a short frame, a bad header, a bad LEN, trailing bytes or a
            CRC mismatch.
    """
    if not isinstance(frame, (bytes, bytearray, memoryview)):
        raise ProtocolError(f"xarm reply must be bytes, got {type(frame).__name__}")
    raw = bytes(frame)
    length = check_frame(raw, ARM_ID, HOST_ID, MAX_REPLY_LEN, "reply")
    return Reply(state=raw[3], data=raw[4: 3 + length])


class FrameSplitter:
    """Cut a byte stream into candidate frames by header and LEN (no CRC check).

    Bytes before a header are skipped (counted in :attr:`skipped`). Complete frames
    come out in order; checking them (CRC, contents) is the caller's job, e.g. with
    :func:`parse_reply`.

    Args:
        first: Expected first header byte (``ARM_ID`` for replies).
        second: Expected second header byte.
        max_len: Largest acceptable LEN byte; a larger one is treated as noise.
    """

    def __init__(self, first: int, second: int, max_len: int):
        self._first = first
        self._second = second
        self._max_len = max_len
        self._buf = bytearray()
        self.skipped = 0

    @classmethod
    def for_replies(cls) -> FrameSplitter:
        """A splitter for the arm -> host direction."""
        return cls(ARM_ID, HOST_ID, MAX_REPLY_LEN)

    def clear(self) -> None:
        """Forget buffered bytes."""
        self._buf.clear()

    @property
    def pending(self) -> int:
        """Bytes buffered but not yet part of a complete frame."""
        return len(self._buf)

    def feed(self, data: bytes) -> list[bytes]:
        """Add bytes; return the complete frames now available."""
        self._buf += data
        out: list[bytes] = []
        while True:
            buf = self._buf
            start = 0
            while start < len(buf):
                if buf[start] == self._first and (start + 1 >= len(buf) or buf[start + 1] == self._second):
                    break
                start += 1
            if start:
                self.skipped += start
                del buf[:start]
            if len(buf) < 3:
                return out
            length = buf[2]
            if length < 1 or length > self._max_len:
                self.skipped += 1
                del buf[:1]
                continue
            total = 3 + length + 2
            if len(buf) < total:
                return out
            out.append(bytes(buf[:total]))
            del buf[:total]
