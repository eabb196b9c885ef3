"""The xArm TCP framing, the rich report and the TCP transport's id matching, against independent peers."""

from __future__ import annotations

import math
import struct
import time

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from xarm_wire_helpers import ScriptedTcpPeer, tcp_reply

from cellcal.devices.errors import DeviceConnectionError, DeviceTimeoutError, ProtocolError
from cellcal.drivers.xarm.registers import Reg
from cellcal.drivers.xarm.report import RICH_MIN_BYTES, parse_report
from cellcal.drivers.xarm.tcp_protocol import (
    TcpFrameSplitter,
    encode_tcp_request,
    next_transaction_id,
    parse_tcp_reply,
)
from cellcal.drivers.xarm.tcp_transport import TcpTransport
from cellcal.sims.xarm.tcp_wire import ReportValues, read_requests, reply_bytes, rich_report


def test_get_version_request_has_the_documented_layout() -> None:
    # tid 1, protocol 2, length 1 (REG only), REG 1 (protocols.md D2)
    assert encode_tcp_request(1, Reg.GET_VERSION) == bytes.fromhex("00010002000101")
    assert next_transaction_id(65535) == 1 and next_transaction_id(1) == 2


def test_emulator_reads_driver_requests_and_skips_heartbeats() -> None:
    heartbeat = bytes([0, 0, 0, 1, 0, 2, 0, 0])  # the SDK's keep-alive frame (protocol 1)
    stream = bytearray(heartbeat + encode_tcp_request(7, Reg.SET_STATE, b"\x04") + encode_tcp_request(8, 41)[:4])
    got = read_requests(stream)
    assert [(c.transaction_id, c.protocol, c.command.register, c.command.params) for c in got] == [
        (7, 2, 12, b"\x04")]
    assert len(stream) == 4  # the half request waits for the rest


@given(data=st.binary(max_size=40), state=st.integers(0, 255), tid=st.integers(0, 65535), chunk=st.integers(1, 9))
@settings(max_examples=60, deadline=None)
def test_emulator_replies_split_and_parse_in_the_driver(data: bytes, state: int, tid: int, chunk: int) -> None:
    stream = reply_bytes(tid, 2, 41, state, data) * 2
    splitter = TcpFrameSplitter()
    frames = [f for i in range(0, len(stream), chunk) for f in splitter.feed(stream[i:i + chunk])]
    assert len(frames) == 2 and splitter.pending == 0
    reply = parse_tcp_reply(frames[1])
    assert (reply.transaction_id, reply.protocol, reply.register) == (tid, 2, 41)
    assert (reply.reply.state, reply.reply.data) == (state, data)


@pytest.mark.parametrize("length", [0, 513, 0xFFFF])
def test_impossible_length_field_is_refused_not_buffered(length: int) -> None:
    splitter = TcpFrameSplitter()
    with pytest.raises(ProtocolError, match=f"length field {length}"):
        splitter.feed(b"\x00\x01\x00\x02" + length.to_bytes(2, "big") + bytes(100))


def _values(**over: object) -> ReportValues:
    base = dict(state=1, mode=0, cmdnum=1, joints=(0.1, -0.2, 0.3, 0.0, 1.5),
                pose=(300.5, -20.25, 410.0, 3.0, 0.1, -0.2), error=0, warning=0, enabled=True, axes=5, arm_type=5)
    base.update(over)
    return ReportValues(**base)  # type: ignore[arg-type]


def test_rich_report_of_the_emulator_reads_back_in_the_driver() -> None:
    packet = rich_report(_values())
    assert len(packet) == RICH_MIN_BYTES == struct.unpack(">I", packet[:4])[0]
    report = parse_report(packet, received=1.0, seq=3)
    assert (report.state, report.mode, report.cmdnum, report.error, report.enabled_bits) == (1, 0, 1, 0, 0b11111)
    assert report.pose_mm_rad == pytest.approx((300.5, -20.25, 410.0, 3.0, 0.1, -0.2), abs=1e-5)
    assert report.joints_rad[:5] == pytest.approx((0.1, -0.2, 0.3, 0.0, 1.5), abs=1e-6) and report.moving
    idle = parse_report(rich_report(_values(state=2, cmdnum=0)))
    assert idle.idle and not idle.moving
    faulted = parse_report(rich_report(_values(state=4, cmdnum=0, error=21)))
    assert faulted.error == 21 and not faulted.moving and not faulted.idle


@pytest.mark.parametrize(("spoil", "match"), [
    (lambda p: p[:4] + bytes([0x0C]) + p[5:], "state 12"),                 # state nibble 12
    (lambda p: p[:35] + struct.pack("<f", math.nan) + p[39:], "position"),  # x = NaN
    (lambda p: p[:35] + struct.pack("<f", 2e5) + p[39:], "position"),      # x = 200 m
    (lambda p: p[:7] + struct.pack("<f", 40.0) + p[11:], "angles"),        # joint 1 = 40 rad
    (lambda p: p[:131] + bytes([9]) + p[132:], "sensitivities"),
    (lambda p: p[:-1], "says 245"),
    (lambda p: struct.pack(">I", 9) + p[4:], "length field 9"),
])
def test_report_values_a_controller_cannot_send_are_refused(spoil: object, match: str) -> None:
    packet = spoil(rich_report(_values()))  # type: ignore[operator]
    with pytest.raises(ProtocolError, match=match):
        parse_report(packet)


@given(st.binary(min_size=0, max_size=600))
@settings(max_examples=200, deadline=None)
def test_any_bytes_are_a_report_or_a_protocol_error(blob: bytes) -> None:
    try:
        report = parse_report(blob)
    except ProtocolError:
        return
    assert len(blob) >= RICH_MIN_BYTES and all(math.isfinite(v) for v in report.pose_mm_rad)


def test_stale_reply_before_the_right_one_is_dropped_and_counted() -> None:
    pose = struct.pack("<6f", 300, 0, 500, math.pi, 0, 0)

    def answer(tid: int, request: object) -> bytes:
        # a late reply to some earlier request first, then this request's own
        return tcp_reply(tid - 1 or 65535, 41, 0, pose) + tcp_reply(tid, 41, 0, pose)

    with ScriptedTcpPeer(answer) as peer:
        link = TcpTransport("127.0.0.1", peer.port, reply_timeout_s=0.3, retries=0)
        link.open(2.0)
        try:
            assert link.transact(Reg.GET_TCP_POSE, expect_len=24).data == pose
            assert link.stats["stale_replies"] == 1 and link.stats["retries"] == 0
        finally:
            link.close()


def test_move_answered_only_with_a_stale_id_times_out_and_is_sent_once() -> None:
    with ScriptedTcpPeer(lambda tid, req: tcp_reply(tid + 1, req.register)) as peer:
        link = TcpTransport("127.0.0.1", peer.port, reply_timeout_s=0.2, retries=2)
        link.open(2.0)
        try:
            t0 = time.monotonic()
            with pytest.raises(DeviceTimeoutError, match="not retried"):
                link.transact(Reg.MOVE_LINE, bytes(43), expect_len=3)
            assert time.monotonic() - t0 < 0.2 + 1.0  # its one reply timeout (the count below: sent once)
            assert peer.registers() == [Reg.MOVE_LINE] and link.stats["stale_replies"] == 1
        finally:
            link.close()


def test_reply_echoing_another_register_is_a_protocol_error() -> None:
    with ScriptedTcpPeer(lambda tid, req: tcp_reply(tid, 13, 0, b"\x02")) as peer:
        link = TcpTransport("127.0.0.1", peer.port, reply_timeout_s=0.2, retries=0)
        link.open(2.0)
        try:
            with pytest.raises(ProtocolError, match="echoes register 13"):
                link.transact(Reg.GET_ERROR, expect_len=2)
        finally:
            link.close()


def test_connecting_to_nothing_backs_off_until_the_deadline() -> None:
    import socket

    probe = socket.socket()
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()  # nothing listens there now: every attempt is refused at once
    link = TcpTransport("127.0.0.1", port, connect_timeout_s=0.2)
    t0 = time.monotonic()
    with pytest.raises(DeviceConnectionError, match=f"cannot connect to 127.0.0.1:{port}"):
        link.open(0.5)
    took = time.monotonic() - t0
    # refused attempts 50, 100, 200 ms apart (backoff), not thousands in a busy loop
    assert 0.3 <= took <= 1.5 and 2 <= link.stats["connect_failures"] <= 6
