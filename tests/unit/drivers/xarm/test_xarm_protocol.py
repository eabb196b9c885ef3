"""xArm serial framing, CRC, register layouts."""

from __future__ import annotations

import math
import struct

import pytest
from xarm_wire_helpers import MoveLine, decode_move_line, encode_reply, parse_request

from cellcal.devices.errors import ProtocolError
from cellcal.drivers.xarm import codes
from cellcal.drivers.xarm.protocol import FrameSplitter, crc16_modbus, encode_request, parse_reply
from cellcal.drivers.xarm.registers import decode_serials, decode_text, encode_move_line, parse_version, unpack_floats


def test_crc_matches_the_modbus_check_value_and_the_spec_example() -> None:
    # CRC-16/MODBUS check value of "123456789" is 0x4B37.
    assert crc16_modbus(b"123456789") == 0x4B37
    # protocols.md D1: get-version request.
    assert encode_request(1) == bytes.fromhex("AA 55 01 01 F1 BC")


def test_request_and_reply_round_trip() -> None:
    req = encode_request(21, b"\x01\x02\x03")
    assert req[:4] == bytes([0xAA, 0x55, 4, 21])
    parsed = parse_request(req)
    assert (parsed.register, parsed.params) == (21, b"\x01\x02\x03")
    rep = encode_reply(0x60, b"\x07\x08")
    assert rep[:4] == bytes([0x55, 0xAA, 3, 0x60])
    r = parse_reply(rep)
    assert r.data == b"\x07\x08"
    assert r.error_pending and r.warning_pending and not r.not_ready and not r.invalid


@pytest.mark.parametrize("mutate", ["crc", "short", "header", "len", "extra"])
def test_bad_replies_are_protocol_errors(mutate: str) -> None:
    good = bytearray(encode_reply(0, b"\x01\x02\x03\x04"))
    if mutate == "crc":
        good[-1] ^= 0x01
    elif mutate == "short":
        good = good[:5]
    elif mutate == "header":
        good[0] = 0xAA
    elif mutate == "len":
        good[2] = 60
    else:
        good += b"\x00"
    with pytest.raises(ProtocolError):
        parse_reply(bytes(good))


def test_reply_longer_than_the_serial_limit_cannot_be_built() -> None:
    encode_reply(0, bytes(48))
    with pytest.raises(ProtocolError):
        encode_reply(0, bytes(49))


def test_splitter_skips_noise_and_handles_split_frames() -> None:
    a, b = encode_reply(0, b"\x01"), encode_reply(0x10, bytes(24))
    stream = b"\x00\x13\x55\x00" + a + b
    sp = FrameSplitter.for_replies()
    frames = []
    for i in range(0, len(stream), 3):
        frames += sp.feed(stream[i:i + 3])
    assert frames == [a, b]
    assert sp.skipped == 4


def test_move_line_layouts_round_trip() -> None:
    pose = [300.5, -20.25, 250.0, math.pi, 0.1, -0.2]
    legacy = encode_move_line(pose, 100.0, 2000.0, common=False)
    common = encode_move_line(pose, 100.0, 2000.0, common=True)
    assert len(legacy) == 36 and len(common) == 43
    for raw, is_common in ((legacy, False), (common, True)):
        m = decode_move_line(raw)
        assert isinstance(m, MoveLine) and m.common is is_common
        assert m.pose == pytest.approx(pose, abs=1e-4)
        assert (m.speed_mm_s, m.acc_mm_s2) == (100.0, 2000.0)
    assert decode_move_line(common).radius_mm == -1.0
    with pytest.raises(ProtocolError):
        decode_move_line(bytes(20))
    with pytest.raises(ProtocolError):
        encode_move_line([0, 0, float("nan"), 0, 0, 0], 1, 1, common=False)


def test_version_and_serials() -> None:
    v = parse_version("6,6,XS1305EMU0001,AC1305EMU0001,v2.5.0")
    assert (v.axes, v.arm_type, v.robot_sn, v.box_sn, v.firmware) == (6, 6, "XS1305EMU0001", "AC1305EMU0001",
                                                                      (2, 5, 0))
    assert v.uses_common_move_line
    old = parse_version("xArm v1.5.0")
    assert old.axes is None and old.firmware == (1, 5, 0) and not old.uses_common_move_line
    assert parse_version("garbage").firmware is None
    assert decode_text(b"abc\0def") == "abc"
    assert decode_serials(b"XS1\0AC2 \0\0") == ("XS1", "AC2")
    assert unpack_floats(struct.pack("<2f", 1.5, -2.0), 2) == (1.5, -2.0)
    with pytest.raises(ProtocolError):
        unpack_floats(b"\x00\x00", 1)


def test_code_meanings() -> None:
    assert "safety boundary" in codes.error_meaning(35)
    assert codes.error_meaning(0) == "no error"
    assert "unknown" in codes.error_meaning(250)
    assert "no solution" in codes.warning_meaning(14)


# The bounded fuzz of the frame parser lives in tests/integration/faults/test_fuzz_parsers.py (targets shared with
# benchmarks/fuzz_parsers.py, see tests/support/fuzz_targets.py).
