"""UFACTORY xArm register protocol over TCP on the host side: the Modbus-TCP-style header (pure, no I/O).

Wire facts from ``shared/spec/protocols.md`` part D2, checked against the installed
``xarm-python-sdk``: a request is ``tid (u16 BE), protocol (u16 BE, 2), length (u16 BE,
REG + params), REG, params``; a reply is ``tid, protocol, length (REG + STATE + data),
REG, STATE, data``. No CRC: TCP carries the bytes intact, and the transaction id ties a
reply to its request. The STATE byte means what it means on the serial line
(:class:`~cellcal.drivers.xarm.protocol.Reply`).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from cellcal.devices.errors import ProtocolError

from .protocol import Reply

PROTOCOL_ID = 0x0002
"""Protocol id of the xArm's private register protocol (the SDK's default)."""
HEADER_LEN = 6
"""Transaction id, protocol id, length: three big-endian u16."""
MAX_LENGTH_FIELD = 512
"""Largest length field accepted from the controller; cellcal's longest reply needs 42
(REG + STATE + 40 text bytes). A larger one is noise: the stream is then out of step."""
FEEDBACK_REGISTER = 0xFF
"""Register byte of an unsolicited feedback message on the control socket (firmware >= 2.0.102)."""
MAX_TRANSACTION_ID = 0xFFFF

_HEADER = struct.Struct(">HHH")


@dataclass(frozen=True)
class TcpReply:
    """One decoded reply frame.

    Attributes:
        transaction_id: The id of the request it answers.
        protocol: The protocol id (echoes the request's).
        register: The register echo.
        reply: STATE byte and data.
    """

    transaction_id: int
    protocol: int
    register: int
    reply: Reply


def next_transaction_id(current: int) -> int:
    """The id after ``current``: 1, 2, ... 65535, then 1 again (0 is never used by a request)."""
    return current % MAX_TRANSACTION_ID + 1


def encode_tcp_request(transaction_id: int, register: int, params: bytes = b"", protocol: int = PROTOCOL_ID) -> bytes:
    """Build a request frame.

    Raises:
        ProtocolError: If an id or the register does not fit its field, or the parameters
            are too long for the length field.
    """
    if not 0 <= transaction_id <= MAX_TRANSACTION_ID or not 0 <= protocol <= 0xFFFF:
        raise ProtocolError(f"xarm tcp: transaction id {transaction_id} / protocol {protocol} out of u16 range")
    if not 0 <= register <= 255:
        raise ProtocolError(f"xarm register must be 0..255, got {register}")
    if len(params) + 1 > MAX_LENGTH_FIELD:
        raise ProtocolError(f"xarm request parameters too long: {len(params)} bytes")
    return _HEADER.pack(transaction_id, protocol, len(params) + 1) + bytes([register]) + bytes(params)


def parse_tcp_reply(frame: bytes | bytearray | memoryview) -> TcpReply:
    """Decode exactly one reply frame (as cut by :class:`TcpFrameSplitter`).

    Raises:
        ProtocolError: If the frame is shorter than a header + REG + STATE, or its length
            field disagrees with its size.
    """
    raw = bytes(frame)
    if len(raw) < HEADER_LEN + 2:
        raise ProtocolError(f"xarm tcp reply too short: {len(raw)} bytes (need at least {HEADER_LEN + 2})",
                            offset=len(raw))
    tid, protocol, length = _HEADER.unpack_from(raw)
    if HEADER_LEN + length != len(raw):
        raise ProtocolError(f"xarm tcp reply is {len(raw)} bytes but its length field says {HEADER_LEN + length}",
                            offset=4)
    return TcpReply(tid, protocol, raw[6], Reply(state=raw[7], data=raw[8:]))


class TcpFrameSplitter:
    """Cut the control socket's byte stream into frames by their length field (bounded).

    A length field of 0 or above ``max_length`` cannot be skipped safely on a byte stream:
    :meth:`feed` raises and the caller drops the connection.

    Args:
        max_length: Largest acceptable length field.
    """

    def __init__(self, max_length: int = MAX_LENGTH_FIELD):
        self._max = max_length
        self._buf = bytearray()
        self.offset = 0
        """Stream bytes consumed so far (for error messages)."""

    @property
    def pending(self) -> int:
        """Bytes buffered but not yet a whole frame (at most a header + ``max_length``)."""
        return len(self._buf)

    def clear(self) -> None:
        """Forget buffered bytes (a new connection)."""
        self._buf.clear()
        self.offset = 0

    def feed(self, data: bytes) -> list[bytes]:
        """Add bytes; return the whole frames now available, in order.

        Raises:
            ProtocolError: On a length field of 0 or above ``max_length``.
        """
        self._buf += data
        out: list[bytes] = []
        while len(self._buf) >= HEADER_LEN:
            length = int.from_bytes(self._buf[4:6], "big")
            if not 1 <= length <= self._max:
                raise ProtocolError(f"xarm tcp: length field {length} is not 1..{self._max} (stream out of step)",
                                    offset=self.offset + 4)
            total = HEADER_LEN + length
            if len(self._buf) < total:
                break
            out.append(bytes(self._buf[:total]))
            del self._buf[:total]
            self.offset += total
        return out
