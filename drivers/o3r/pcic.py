"""ifm PCIC v3 wire format: message framing and image-chunk walking (pure, no I/O).

Framing: a 16-byte header ``<4-digit ticket>L<9-digit length>\\r\\n``, then ``length``
payload bytes: the ticket again, the content and ``\\r\\n``. Facts: ``shared/spec/protocols.md``
part A. Malformed input raises :class:`~cellcal.devices.errors.ProtocolError` naming the byte
offset; no length field is trusted (or allocated from) before it is checked.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from cellcal.devices.errors import ProtocolError

#: Length of the PCIC v3 message header, bytes.
HEADER_LEN = 16
#: Default cap on a payload, bytes (a 640x480 frame with every chunk is ~5 MB).
DEFAULT_MAX_PAYLOAD = 64 * 1024 * 1024

TICKET_IMAGE = "0000"
TICKET_ASYNC_ERROR = "0001"
TICKET_ASYNC_NOTIFICATION = "0010"
TICKET_ALGO_DEBUG = "0020"
TICKET_C = "1000"
TICKET_T = "1001"
TICKET_P = "1002"

# Chunk types (subset used here; see protocols.md A6).
CHUNK_RADIAL_DISTANCE = 100
CHUNK_NORM_AMPLITUDE = 101
CHUNK_AMPLITUDE = 103
CHUNK_DISTANCE_NOISE = 105
CHUNK_CONFIDENCE = 300
CHUNK_TOF_INFO = 420

#: Pixel format -> numpy dtype (little-endian); 16U2 and 32F3 are multi-channel.
PIXEL_DTYPES: dict[int, tuple[np.dtype[np.generic], int]] = {
    0: (np.dtype("u1"), 1), 1: (np.dtype("i1"), 1), 2: (np.dtype("<u2"), 1), 3: (np.dtype("<i2"), 1),
    4: (np.dtype("<u4"), 1), 5: (np.dtype("<i4"), 1), 6: (np.dtype("<f4"), 1), 7: (np.dtype("<u8"), 1),
    8: (np.dtype("<f8"), 1), 9: (np.dtype("<u2"), 2), 10: (np.dtype("<f4"), 3),
}

_CHUNK_V1 = struct.Struct("<9I")   # type, size, header size, version, w, h, format, ts_us, frame count
_CHUNK_V2_EXTRA = struct.Struct("<3I")  # status, ts sec, ts nsec
#: Minimum HEADER_SIZE per header version.
MIN_HEADER_SIZE = {1: 36, 2: 48, 3: 48}
#: Upper bound on a plausible image side, pixels (any larger value is a corrupt header).
MAX_IMAGE_SIDE = 8192


def encode_message(ticket: str, content: bytes) -> bytes:
    """Frame ``content`` as one PCIC v3 message with ``ticket`` (4 digits)."""
    if len(ticket) != 4 or not ticket.isdigit():
        raise ValueError(f"PCIC ticket must be 4 digits, got {ticket!r}")
    length = 4 + len(content) + 2
    return b"%sL%09d\r\n%s%s\r\n" % (ticket.encode(), length, ticket.encode(), content)


def parse_header(header: bytes | bytearray | memoryview, *, offset: int = 0,
                 max_payload: int = DEFAULT_MAX_PAYLOAD) -> tuple[str, int]:
    """Check a 16-byte PCIC header and return ``(ticket, payload_length)``.

    Args:
        header: Exactly 16 bytes.
        offset: Stream offset of ``header[0]``, for error messages.
        max_payload: Largest acceptable payload length, bytes.

    Raises:
        ProtocolError: On a short header, non-digit ticket/length, missing ``L`` or
            CR LF, a length below 6 (ticket + CR LF) or above ``max_payload``.
    """
    h = bytes(header)
    if len(h) != HEADER_LEN:
        raise ProtocolError(f"PCIC header must be {HEADER_LEN} bytes, got {len(h)}", offset=offset)
    if not h[0:4].isdigit():
        raise ProtocolError(f"PCIC ticket is not 4 ASCII digits: {h[0:4]!r}", offset=offset)
    if h[4:5] != b"L":
        raise ProtocolError(f"PCIC header lacks 'L' after the ticket: {h[4:5]!r}", offset=offset + 4)
    if not h[5:14].isdigit():
        raise ProtocolError(f"PCIC length is not 9 ASCII digits: {h[5:14]!r}", offset=offset + 5)
    if h[14:16] != b"\r\n":
        raise ProtocolError(f"PCIC header does not end in CR LF: {h[14:16]!r}", offset=offset + 14)
    length = int(h[5:14])
    if length < 6:
        raise ProtocolError(f"PCIC payload length {length} is below the minimum 6", offset=offset + 5)
    if length > max_payload:
        raise ProtocolError(f"PCIC payload length {length} exceeds the cap of {max_payload} bytes",
                            offset=offset + 5)
    return h[0:4].decode("ascii"), length


def check_payload(payload: bytes | bytearray | memoryview, ticket: str, *, offset: int = 0) -> None:
    """Check that a payload repeats the header's ticket and ends in CR LF.

    Args:
        payload: The payload bytes (length as announced by the header).
        ticket: Ticket from the header.
        offset: Stream offset of ``payload[0]``.

    Raises:
        ProtocolError: On a mismatching ticket or missing CR LF.
    """
    mv = memoryview(payload)
    if len(mv) < 6:
        raise ProtocolError(f"PCIC payload of {len(mv)} bytes is shorter than 6", offset=offset)
    if bytes(mv[0:4]) != ticket.encode("ascii"):
        raise ProtocolError(f"PCIC payload ticket {bytes(mv[0:4])!r} does not match header ticket {ticket!r}",
                            offset=offset)
    if bytes(mv[-2:]) != b"\r\n":
        raise ProtocolError("PCIC payload does not end in CR LF", offset=offset + len(mv) - 2)


@dataclass(frozen=True)
class Message:
    """One PCIC message.

    Attributes:
        ticket: 4-digit ticket.
        content: Payload without the leading ticket and trailing CR LF (a view).
        payload: The whole payload (ticket .. CR LF), a view.
        offset: Stream offset of the message header.
    """

    ticket: str
    content: memoryview
    payload: memoryview
    offset: int


def iter_messages(data: bytes | bytearray | memoryview, *, max_payload: int = DEFAULT_MAX_PAYLOAD
                  ) -> Iterator[Message]:
    """Split a complete byte stream into messages (for replays, tests and fuzzing).

    Raises:
        ProtocolError: On any malformed message, or trailing bytes that do not form a
            complete message (naming the offset where it starts).
    """
    mv = memoryview(data).cast("B")
    pos = 0
    n = len(mv)
    while pos < n:
        if n - pos < HEADER_LEN:
            raise ProtocolError(f"truncated PCIC header: {n - pos} of {HEADER_LEN} bytes", offset=pos)
        ticket, length = parse_header(mv[pos:pos + HEADER_LEN], offset=pos, max_payload=max_payload)
        start = pos + HEADER_LEN
        if n - start < length:
            raise ProtocolError(f"truncated PCIC payload: {n - start} of {length} bytes", offset=start)
        payload = mv[start:start + length]
        check_payload(payload, ticket, offset=start)
        yield Message(ticket, payload[4:-2], payload, pos)
        pos = start + length


@dataclass(frozen=True)
class Chunk:
    """One image chunk inside an image payload.

    Attributes:
        chunk_type: CHUNK_TYPE.
        offset: Payload offset of the chunk header.
        data_offset: Payload offset of the pixel data (chunk offset + HEADER_SIZE).
        data_size: Bytes of pixel data (CHUNK_SIZE - HEADER_SIZE).
        header_version: 1, 2 or 3.
        width, height: Image size, px (1-D blobs carry whatever the device put there).
        pixel_format: PIXEL_FORMAT code.
        timestamp_us: TIME_STAMP field, microseconds.
        frame_count: FRAME_COUNT.
        status: STATUS_CODE (0 for v1).
        timestamp_ns: Acquisition time from TIME_STAMP_SEC/NSEC, ns since the epoch (None for v1).
        metadata: Raw v3 META_DATA bytes (JSON text, possibly NUL-padded), b"" otherwise.
    """

    chunk_type: int
    offset: int
    data_offset: int
    data_size: int
    header_version: int
    width: int
    height: int
    pixel_format: int
    timestamp_us: int
    frame_count: int
    status: int = 0
    timestamp_ns: int | None = None
    metadata: bytes = field(default=b"", repr=False)


def walk_chunks(payload: bytes | bytearray | memoryview, *, offset: int = 0) -> list[Chunk]:
    """Validate an image payload (``<ticket>star ... stop\\r\\n``) and list its chunks.

    Chunks are walked by their CHUNK_SIZE and their pixel data located by HEADER_SIZE
    (header versions 1-3). Every length is checked against the bytes actually present
    and against a cap before it is used.

    Args:
        payload: The whole payload including the leading ticket and trailing CR LF.
        offset: Stream offset of ``payload[0]`` (added to reported offsets).

    Raises:
        ProtocolError: Missing ``star``/``stop``, a chunk header that does not fit, a
            CHUNK_SIZE smaller than its HEADER_SIZE or running past ``stop``, an unknown
            header version, a HEADER_SIZE too small for its version, or absurd sizes.
    """
    mv = memoryview(payload).cast("B")
    n = len(mv)
    if n < 14:
        raise ProtocolError(f"image payload of {n} bytes is too short for star/stop", offset=offset)
    if bytes(mv[4:8]) != b"star":
        raise ProtocolError(f"image payload lacks 'star' marker: {bytes(mv[4:8])!r}", offset=offset + 4)
    if bytes(mv[n - 6:n]) != b"stop\r\n":
        raise ProtocolError(f"image payload lacks 'stop' CR LF trailer: {bytes(mv[n - 6:n])!r}",
                            offset=offset + n - 6)
    end = n - 6
    pos = 8
    chunks: list[Chunk] = []
    while pos < end:
        if end - pos < _CHUNK_V1.size:
            raise ProtocolError(f"truncated chunk header: {end - pos} bytes left before 'stop'", offset=offset + pos)
        (ctype, csize, hsize, version, width, height, fmt, ts_us, count) = _CHUNK_V1.unpack_from(mv, pos)
        if version not in MIN_HEADER_SIZE:
            raise ProtocolError(f"chunk {ctype}: unsupported HEADER_VERSION {version}", offset=offset + pos + 12)
        if hsize < MIN_HEADER_SIZE[version]:
            raise ProtocolError(f"chunk {ctype}: HEADER_SIZE {hsize} too small for header version {version}",
                                offset=offset + pos + 8)
        if csize < hsize:
            raise ProtocolError(f"chunk {ctype}: CHUNK_SIZE {csize} smaller than HEADER_SIZE {hsize}",
                                offset=offset + pos + 4)
        if csize > end - pos:
            raise ProtocolError(f"chunk {ctype}: CHUNK_SIZE {csize} runs past 'stop' ({end - pos} bytes left)",
                                offset=offset + pos + 4)
        if width > MAX_IMAGE_SIDE or height > MAX_IMAGE_SIDE:
            raise ProtocolError(f"chunk {ctype}: absurd image size {width}x{height}", offset=offset + pos + 16)
        status = 0
        ts_ns: int | None = None
        meta = b""
        if version >= 2:
            status, sec, nsec = _CHUNK_V2_EXTRA.unpack_from(mv, pos + 36)
            ts_ns = sec * 1_000_000_000 + nsec
        if version >= 3 and hsize > 48:
            meta = bytes(mv[pos + 48:pos + hsize])
        chunks.append(Chunk(ctype, pos, pos + hsize, csize - hsize, version, width, height, fmt, ts_us, count,
                            status, ts_ns, meta))
        pos += csize
    return chunks


def image_view(payload: bytes | bytearray | memoryview, chunk: Chunk, *, offset: int = 0,
               expect_format: tuple[int, ...] | None = None) -> NDArray[np.generic]:
    """Pixel data of an image chunk as a (height, width[, channels]) numpy view (no copy).

    Args:
        payload: The payload the chunk was found in.
        chunk: A chunk from :func:`walk_chunks`.
        offset: Stream offset of ``payload[0]``.
        expect_format: Acceptable PIXEL_FORMAT codes; None accepts any known one.

    Raises:
        ProtocolError: Unknown or unexpected pixel format, zero size, or fewer data bytes
            than width x height x pixel size.
    """
    if chunk.pixel_format not in PIXEL_DTYPES:
        raise ProtocolError(f"chunk {chunk.chunk_type}: unknown PIXEL_FORMAT {chunk.pixel_format}",
                            offset=offset + chunk.offset + 24)
    if expect_format is not None and chunk.pixel_format not in expect_format:
        raise ProtocolError(f"chunk {chunk.chunk_type}: PIXEL_FORMAT {chunk.pixel_format}, expected one of "
                            f"{expect_format}", offset=offset + chunk.offset + 24)
    dtype, channels = PIXEL_DTYPES[chunk.pixel_format]
    if chunk.width == 0 or chunk.height == 0:
        raise ProtocolError(f"chunk {chunk.chunk_type}: empty image {chunk.width}x{chunk.height}",
                            offset=offset + chunk.offset + 16)
    count = chunk.width * chunk.height * channels
    need = count * dtype.itemsize
    if chunk.data_size < need:
        raise ProtocolError(f"chunk {chunk.chunk_type}: {chunk.data_size} data bytes, {chunk.width}x"
                            f"{chunk.height} pixels need {need}", offset=offset + chunk.offset + 4)
    arr = np.frombuffer(payload, dtype=dtype, count=count, offset=chunk.data_offset)
    shape = (chunk.height, chunk.width) if channels == 1 else (chunk.height, chunk.width, channels)
    return arr.reshape(shape)


def blob_view(payload: bytes | bytearray | memoryview, chunk: Chunk) -> memoryview:
    """Data bytes of a 1-D blob chunk (e.g. TOF_INFO) as a memoryview (no copy)."""
    return memoryview(payload).cast("B")[chunk.data_offset:chunk.data_offset + chunk.data_size]


def _split_coded(content: bytes | bytearray | memoryview, what: str, offset: int) -> tuple[bytes, str]:
    """Split ``<9 ASCII digits>[:<text>]`` into the digits and the text.

    Raises:
        ProtocolError: If the content does not start with 9 ASCII digits.
    """
    c = bytes(content)
    if len(c) < 9 or not c[:9].isdigit():
        raise ProtocolError(f"{what}: {c[:9]!r}", offset=offset)
    return c[:9], c[10:].decode("utf-8", "replace") if len(c) > 9 else ""


def parse_async_error(content: bytes | bytearray | memoryview, *, offset: int = 0) -> tuple[int, str]:
    """Decode an async error (ticket 0001) content: 9-digit code, optional ``:message``.

    Raises:
        ProtocolError: If the code is not 9 ASCII digits.
    """
    code, message = _split_coded(content, "async error lacks a 9-digit code", offset)
    return int(code), message


def parse_notification(content: bytes | bytearray | memoryview, *, offset: int = 0) -> tuple[str, str]:
    """Decode an async notification (ticket 0010): 9-digit id, ``:``, JSON text.

    Raises:
        ProtocolError: If the id is not 9 ASCII digits.
    """
    ident, text = _split_coded(content, "notification lacks a 9-digit id", offset)
    return ident.decode("ascii"), text
