"""xArm serial framing at its exact limits: registers, lengths, headers, CRC, and the stream splitter.

Frames are built by hand here (bytes + the CRC-16/MODBUS check value), so a framing rule
the driver's own encoder shares with its parser cannot hide a mistake.
"""

from __future__ import annotations

import pytest

from cellcal.devices.errors import ProtocolError
from cellcal.drivers.xarm.protocol import (
    ARM_ID,
    HOST_ID,
    MAX_REPLY_LEN,
    FrameSplitter,
    check_frame,
    crc16_modbus,
    crc_bytes,
    encode_request,
    parse_reply,
)


def reply(state: int, data: bytes = b"", *, length: int | None = None) -> bytes:
    """A reply frame ``55 AA LEN STATE data CRC``, LEN overridable."""
    head = bytes([0x55, 0xAA, len(data) + 1 if length is None else length, state]) + data
    return head + crc_bytes(head)


def test_crc_of_known_frames_and_of_every_single_byte() -> None:
    # CRC-16/MODBUS check value, the spec's GET_VERSION request, and the empty input (the init value)
    assert crc16_modbus(b"123456789") == 0x4B37
    assert crc16_modbus(b"") == 0xFFFF
    assert crc_bytes(bytes.fromhex("AA 55 01 01")) == bytes.fromhex("F1 BC")
    # byte-wise reference (reflected polynomial 0xA001), independent of the table
    for value in range(256):
        crc = 0xFFFF ^ value
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
        assert crc16_modbus(bytes([value])) == crc, value
    assert crc16_modbus(memoryview(b"123456789")) == crc16_modbus(bytearray(b"123456789")) == 0x4B37


@pytest.mark.parametrize("register", [0, 1, 254, 255])
def test_every_register_byte_can_be_sent(register: int) -> None:
    frame = encode_request(register, b"\x07")
    assert frame[:5] == bytes([0xAA, 0x55, 2, register, 7]) and len(frame) == 7
    assert check_frame(frame, HOST_ID, ARM_ID, 255, "request") == 2


@pytest.mark.parametrize("register", [-1, 256])
def test_a_register_outside_a_byte_is_refused(register: int) -> None:
    with pytest.raises(ProtocolError) as info:
        encode_request(register)
    assert str(info.value) == f"xarm register must be 0..255, got {register}"


def test_parameters_fill_a_request_up_to_len_255() -> None:
    frame = encode_request(9, bytes(range(254)))
    assert frame[2] == 255 and len(frame) == 3 + 255 + 2
    assert check_frame(frame, HOST_ID, ARM_ID, 255, "request") == 255
    with pytest.raises(ProtocolError) as info:
        encode_request(9, bytes(255))
    assert str(info.value) == "xarm request parameters too long: 255 bytes"


def test_the_shortest_and_longest_replies_parse() -> None:
    shortest = reply(0x10)
    assert len(shortest) == 6
    r = parse_reply(shortest)
    assert (r.state, r.data) == (0x10, b"") and r.not_ready
    longest = reply(0, bytes(range(48)))
    assert longest[2] == MAX_REPLY_LEN and parse_reply(longest).data == bytes(range(48))
    assert parse_reply(bytearray(longest)).data == parse_reply(memoryview(longest)).data == bytes(range(48))


@pytest.mark.parametrize(("state", "flags"), [
    (0x40, (True, False, False, False)), (0x20, (False, True, False, False)),
    (0x10, (False, False, True, False)), (0x08, (False, False, False, True)),
    (0x87, (False, False, False, False)), (0x78, (True, True, True, True)),
])
def test_each_state_bit_means_one_thing(state: int, flags: tuple[bool, bool, bool, bool]) -> None:
    r = parse_reply(reply(state, b"\x01"))
    assert (r.error_pending, r.warning_pending, r.not_ready, r.invalid) == flags


@pytest.mark.parametrize(("frame", "message", "offset"), [
    (reply(0)[:5], "xarm reply frame too short: 5 bytes (need at least 6)", 5),
    (b"", "xarm reply frame too short: 0 bytes (need at least 6)", 0),
    (b"\x13" + reply(0, b"\x01")[1:], "xarm reply frame has bad header 0x13 0xaa", 0),
    (b"\x55\x55" + reply(0, b"\x01")[2:], "xarm reply frame has bad header 0x55 0x55", 0),
    (reply(0, b"\x01", length=0), "xarm reply frame has bad LEN 0", 2),
    (reply(0, bytes(49)), "xarm reply frame has bad LEN 50", 2),
    (reply(0, b"\x01\x02", length=2), "xarm reply frame is 8 bytes but LEN 2 says 7", 7),
    (reply(0, b"\x01", length=3), "xarm reply frame is 7 bytes but LEN 3 says 8", 7),
    (reply(0, b"\x01")[:-1] + b"\x00", "xarm reply CRC mismatch: got 0x0069, expected 0xd469", 5),
])
def test_each_bad_reply_is_named_with_its_offset(frame: bytes, message: str, offset: int) -> None:
    with pytest.raises(ProtocolError) as info:
        parse_reply(frame)
    assert info.value.offset == offset
    assert str(info.value) == f"{message} (at byte offset {offset})"


def test_a_request_check_names_the_request() -> None:
    frame = bytearray(encode_request(1))
    frame[-1] ^= 0xFF
    expected = r"^xarm request CRC mismatch: got 0x43f1, expected 0xbcf1 \(at byte offset 4\)$"
    with pytest.raises(ProtocolError, match=expected):
        check_frame(bytes(frame), HOST_ID, ARM_ID, 255, "request")


def test_a_reply_that_is_not_bytes_is_refused() -> None:
    with pytest.raises(ProtocolError) as info:
        parse_reply("UU")  # type: ignore[arg-type]
    assert str(info.value) == "xarm reply must be bytes, got str"


def test_splitter_resynchronises_after_noise_headers_and_bad_len() -> None:
    a, b = reply(0, b"\x01\x02"), reply(0x40, bytes(48))
    sp = FrameSplitter.for_replies()
    # a lone 0x55 before a non-0xAA byte is noise; a bad LEN (0, then 50) drops the 0x55 and the
    # scan goes on from the next byte: every byte before frame a is skipped, one by one
    noise = b"\x55\x00" + b"\x55\xaa\x00" + b"\x55\xaa\x32"
    assert sp.feed(noise + a + b) == [a, b]
    assert sp.skipped == len(noise) and sp.pending == 0
    # the skipped count adds up over calls
    assert sp.feed(b"\x00\x00\x00" + a) == [a] and sp.skipped == len(noise) + 3


def test_splitter_waits_for_a_whole_frame_and_keeps_a_header_at_the_end() -> None:
    a = reply(0x20, b"\x05\x06\x07")
    sp = FrameSplitter.for_replies()
    assert sp.feed(b"\x13\x55") == [] and sp.skipped == 1 and sp.pending == 1  # 0x55 may start a frame
    assert sp.feed(b"\xaa") == [] and sp.pending == 2
    assert sp.feed(a[2:3]) == [] and sp.pending == 3  # header + LEN: still no frame
    assert sp.feed(a[3:-1]) == [] and sp.pending == len(a) - 1
    assert sp.feed(a[-1:]) == [a] and sp.pending == 0 and sp.skipped == 1
    assert sp.feed(a[:4]) == [] and sp.pending == 4
    sp.clear()
    assert sp.pending == 0 and sp.feed(a) == [a]


def test_splitter_takes_the_longest_and_shortest_len_and_nothing_longer() -> None:
    sp = FrameSplitter.for_replies()
    longest, shortest = reply(0, bytes(48)), reply(0)
    assert sp.feed(shortest + longest + shortest) == [shortest, longest, shortest] and sp.skipped == 0
    requests = FrameSplitter(HOST_ID, ARM_ID, 255)
    big = encode_request(3, bytes(254))
    assert requests.feed(big[:100]) == [] and requests.feed(big[100:]) == [big]


@pytest.mark.parametrize(("stream", "skipped", "pending"), [
    (b"\x13", 1, 0),            # one byte that cannot start a frame
    (b"\x55", 0, 1),            # one that can: wait for the next
    (b"\x55\x00", 2, 0),        # a 0x55 not followed by 0xAA is noise, to the last byte
    (b"\x55\xaa", 0, 2),        # a header: wait for LEN
    (b"\x55\xaa\x00", 3, 0),    # header + a LEN that no frame has: all noise at once
    (b"\x55\xaa\x01", 0, 3),    # header + LEN 1: wait for STATE and CRC
])
def test_splitter_decides_on_each_byte_as_soon_as_it_can(stream: bytes, skipped: int, pending: int) -> None:
    sp = FrameSplitter.for_replies()
    assert sp.feed(stream) == []
    assert (sp.skipped, sp.pending) == (skipped, pending)
