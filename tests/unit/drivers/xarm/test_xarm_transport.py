"""The xArm transport and driver against a scripted controller on a pty: what is resent, what is trusted.

Only idempotent reads are sent again; every other request goes out once whatever comes
back. A reply must come alone and with the length its register answers with; after
anything else the line is resynchronised before the next request. After an unconfirmed
MOVE_LINE the driver reads the state and pose, stops a moving arm and raises MotionError.
"""

from __future__ import annotations

import math
import struct
import threading
import time
from collections.abc import Callable, Iterator

import pytest
from xarm_wire_helpers import Request, ScriptedPeer, encode_reply

from cellcal.devices.errors import DeviceTimeoutError, MotionError, ProtocolError
from cellcal.devices.pose import Pose
from cellcal.drivers.xarm.arm import XArmArm
from cellcal.drivers.xarm.registers import MOTION_REGISTERS, READ_REGISTERS, Reg
from cellcal.drivers.xarm.transport import SerialTransport

REPLY_TIMEOUT_S = 0.2  # far above a reply's scheduling delay on a busy machine
GARBLED = encode_reply(0, b"\x00\x00")[:-1] + b"\x00"  # a 2-byte reply with a bad CRC


def _answers(script: dict[int, list[bytes]], default: Callable[[Request], bytes]) -> Callable[[Request], bytes]:
    """Answer register r from ``script[r]`` in order, then with ``default``."""
    def answer(request: Request) -> bytes:
        queue = script.get(request.register)
        return queue.pop(0) if queue else default(request)
    return answer


@pytest.fixture
def link() -> Iterator[Callable[[Callable[[Request], bytes]], tuple[ScriptedPeer, SerialTransport]]]:
    opened: list[tuple[ScriptedPeer, SerialTransport]] = []

    def make(answer: Callable[[Request], bytes]) -> tuple[ScriptedPeer, SerialTransport]:
        peer = ScriptedPeer(answer).__enter__()
        transport = SerialTransport(peer.path, reply_timeout_s=REPLY_TIMEOUT_S, retries=2)
        transport.open()
        opened.append((peer, transport))
        return peer, transport

    yield make
    for peer, transport in opened:
        transport.close()
        peer.__exit__()


def test_motion_and_read_registers_are_disjoint_and_cover_the_sdk_table() -> None:
    assert not MOTION_REGISTERS & READ_REGISTERS
    assert Reg.MOVE_LINE in MOTION_REGISTERS and Reg.SET_STATE not in READ_REGISTERS
    sdk = pytest.importorskip("xarm.core.config.x_config").XCONF.UxbusReg
    moving = {getattr(sdk, n) for n in dir(sdk) if n.startswith("MOVE_") and n != "MOVE_LINE_TOOL_AA"}
    assert moving <= MOTION_REGISTERS | {getattr(sdk, "MOVE_LINE_TOOL_AA", 0)}
    assert {r for r in READ_REGISTERS} <= {getattr(sdk, n) for n in dir(sdk) if n.startswith("GET_")}


@pytest.mark.parametrize("register", sorted({*MOTION_REGISTERS, Reg.SET_STATE, Reg.MOTION_EN, Reg.SET_MODE,
                                             Reg.CLEAN_ERR, Reg.CLEAN_WAR}))
def test_anything_but_a_read_is_sent_once_whatever_comes_back(register: int, link: Callable[..., tuple[
        ScriptedPeer, SerialTransport]]) -> None:
    peer, transport = link(lambda r: GARBLED)
    with pytest.raises(ProtocolError, match="sent once, not retried"):
        transport.transact(register, b"\x01", expect_len=0)
    assert peer.registers() == [register]
    peer.answer = lambda r: b""
    with pytest.raises(DeviceTimeoutError, match="sent once, not retried"):
        transport.transact(register, b"\x01", expect_len=0)
    assert peer.registers() == [register, register]
    assert transport.stats["retries"] == 0


@pytest.mark.parametrize("register", sorted(READ_REGISTERS))
def test_reads_are_retried_after_a_garbled_or_missing_reply(register: int, link: Callable[..., tuple[
        ScriptedPeer, SerialTransport]]) -> None:
    good = encode_reply(0, b"\x07\x00")
    peer, transport = link(_answers({register: [GARBLED, b""]}, lambda r: good))
    assert transport.transact(register, expect_len=2).data == b"\x07\x00"
    assert peer.registers() == [register] * 3
    assert transport.stats["retries"] == 2 and transport.stats["bad_frames"] == 1 and transport.stats["timeouts"] == 1


def test_a_reply_of_the_wrong_length_is_foreign_and_resynchronises(link: Callable[..., tuple[
        ScriptedPeer, SerialTransport]]) -> None:
    # GET_ERROR answers with 2 bytes; a 1-byte reply (a GET_STATE's) does not belong to it
    peer, transport = link(_answers({Reg.GET_ERROR: [encode_reply(0, b"\x02")]},
                                    lambda r: encode_reply(0, b"\x00\x00")))
    assert transport.transact(Reg.GET_ERROR, expect_len=2).data == b"\x00\x00"
    assert transport.stats["bad_frames"] == 1 and transport.stats["resyncs"] >= 1
    assert peer.registers() == [Reg.GET_ERROR, Reg.GET_ERROR]
    with pytest.raises(ProtocolError, match=r"does not belong to register 21 \(MOVE_LINE\), which answers with 0"):
        peer.answer = lambda r: encode_reply(0, b"\x00\x00")
        transport.transact(Reg.MOVE_LINE, bytes(36), expect_len=0)
    assert peer.registers().count(Reg.MOVE_LINE) == 1


def test_two_replies_to_one_request_confirm_nothing(link: Callable[..., tuple[ScriptedPeer, SerialTransport]]) -> None:
    peer, transport = link(lambda r: encode_reply(0) + encode_reply(0))
    with pytest.raises(ProtocolError, match="more than one reply frame"):
        transport.transact(Reg.MOVE_LINE, bytes(36), expect_len=0)
    assert peer.registers() == [Reg.MOVE_LINE]


def test_stray_bytes_before_a_request_are_flushed_first(link: Callable[..., tuple[
        ScriptedPeer, SerialTransport]]) -> None:
    peer, transport = link(lambda r: encode_reply(0, b"\x02"))
    stray = encode_reply(0)
    peer.send(stray)  # a late reply to something before: it must not answer the next request
    deadline = time.monotonic() + 60.0
    while peer.pending_at_host() < len(stray):  # the pty hands it on a moment later
        assert time.monotonic() < deadline
        time.sleep(0.005)
    assert transport.transact(Reg.GET_STATE, expect_len=1).data == b"\x02"
    assert transport.stats["stale_bytes"] == 6 and transport.stats["resyncs"] == 1 and transport.stats["retries"] == 0


def test_a_read_answered_only_on_its_retry_leaves_the_next_request_clear_of_the_late_reply(link: Callable[..., tuple[
        ScriptedPeer, SerialTransport]]) -> None:
    """The first attempt's reply comes just after the retry's: the next request (a move) must not meet it."""
    pose = encode_reply(0, struct.pack("<6f", 300, 0, 500, math.pi, 0, 0))
    poses = 0
    peer: ScriptedPeer | None = None
    later: list[threading.Timer] = []

    def send_later(delay_s: float, frame: bytes) -> None:
        assert peer is not None
        later.append(threading.Timer(delay_s, peer.send, (frame,)))
        later[-1].start()

    def answer(request: Request) -> bytes:
        nonlocal poses
        if request.register == Reg.GET_TCP_POSE:
            poses += 1
            if poses == 1:
                return b""  # late: sent after the retry's reply, below
            if poses == 2:
                send_later(0.01, pose)
            return pose
        send_later(0.03, encode_reply(0))  # a move is confirmed after a while
        return b""

    peer, transport = link(answer)
    transport.quiet_s = 0.5  # the late reply comes well inside the quiet time a resynchronisation waits for
    assert transport.transact(Reg.GET_TCP_POSE, expect_len=24).data == pose[4:-2]
    # (on a busy machine both replies may be read together: out of step, and a third attempt)
    assert transport.stats["retries"] in (1, 2) and transport.stats["timeouts"] == 1
    retried = transport.stats["retries"]
    resyncs = transport.stats["resyncs"]
    # sent at once: the late reply is still on its way; met in the move's wait, it would leave the move
    # unconfirmed (a reply of 24 bytes does not belong to MOVE_LINE). The line is resynchronised first.
    assert transport.transact(Reg.MOVE_LINE, bytes(36), expect_len=0).data == b""
    assert transport.stats["resyncs"] == resyncs + 1 and transport.stats["bad_frames"] == retried - 1
    assert peer.registers() == [Reg.GET_TCP_POSE] * (1 + retried) + [Reg.MOVE_LINE]
    for timer in later:
        timer.join(5.0)


# ---------------------------------------------------------------- the driver after an unconfirmed MOVE_LINE
class Controller:
    """A scripted xArm: idle at 300/0/400 mm, a MOVE_LINE starts a motion that never ends until stopped.

    ``deaf_after_move``: from the MOVE_LINE on, no reply to ``"reads"`` or to ``"all"`` requests.
    """

    def __init__(self, move_reply: bytes | None, *, deaf_after_move: str = "") -> None:
        self.move_reply = move_reply
        self.deaf_after_move = deaf_after_move
        self.moving = self.stopped = self.moved = False

    def __call__(self, r: Request) -> bytes:
        if r.register == Reg.GET_VERSION:
            return encode_reply(0, b"6,6,XS1,AC1,v2.5.0".ljust(40, b"\0"))
        if r.register == Reg.MOVE_LINE:
            self.moving = self.moved = True
            return encode_reply(0, bytes(3)) if self.move_reply is None else self.move_reply
        if r.register == Reg.SET_STATE and r.params == b"\x04":
            self.moving, self.stopped = False, True
        if self.moved and (self.deaf_after_move == "all"
                           or (self.deaf_after_move == "reads" and r.register in READ_REGISTERS)):
            return b""
        replies = {Reg.GET_ERROR: b"\0\0", Reg.GET_STATE: bytes([4 if self.stopped else 1 if self.moving else 2]),
                   Reg.GET_CMDNUM: struct.pack(">H", int(self.moving)),
                   Reg.GET_TCP_POSE: struct.pack("<6f", 300.0, 0.0, 400.0, math.pi, 0.0, 0.0)}
        return encode_reply(0, replies.get(Reg(r.register), b"") if r.register in Reg._value2member_map_ else b"")


def _run(controller: Controller, **cfg: float) -> tuple[ScriptedPeer, BaseException, float]:
    with ScriptedPeer(controller) as peer:
        drv = XArmArm(XArmArm.Config(port=peer.path, reply_timeout_s=0.3, stop_timeout_s=1.5, poll_interval_s=0.005,
                                     **cfg))  # type: ignore[arg-type]
        with drv:
            t0 = time.monotonic()
            with pytest.raises(MotionError) as err:
                drv.move_linear(Pose.from_xyz_rpy([0.35, 0.0, 0.4], [math.pi, 0, 0]), speed=0.1, acceleration=1.0,
                                timeout=2.0)
            elapsed = time.monotonic() - t0
    return peer, err.value, elapsed


@pytest.mark.parametrize("reply", [b"", GARBLED, encode_reply(0, b"\0\0")], ids=["lost", "garbled", "foreign"])
def test_unconfirmed_move_is_assessed_stopped_and_never_resent(reply: bytes) -> None:
    threads = set(threading.enumerate())
    peer, err, elapsed = _run(Controller(reply))
    regs = peer.registers()
    assert regs.count(Reg.MOVE_LINE) == 1
    after = regs[regs.index(Reg.MOVE_LINE) + 1:]
    # find out (error, state, queue, pose), then stop, and nothing that could move the arm again
    assert after[:4] == [Reg.GET_ERROR, Reg.GET_STATE, Reg.GET_CMDNUM, Reg.GET_TCP_POSE]
    assert Reg.SET_STATE in after and all(r.params == b"\x04" for r in peer.requests if r.register == Reg.SET_STATE
                                          and peer.requests.index(r) > regs.index(Reg.MOVE_LINE))
    assert "state 1, 1 queued" in str(err) and "0.0 mm from where it started and 50.0 mm from the target" in str(err)
    assert str(err).endswith("the arm was stopped (clear_errors() before the next move)")
    assert elapsed < 0.3 + 1.5 + 1.0  # reply timeout + stop budget + slack for a busy machine
    assert set(threading.enumerate()) == threads


@pytest.mark.parametrize("deaf", ["reads", "all"])
def test_unconfirmed_move_on_a_deaf_line_still_stops(deaf: str) -> None:
    peer, err, elapsed = _run(Controller(b"", deaf_after_move=deaf))
    regs = peer.registers()
    assert regs.count(Reg.MOVE_LINE) == 1
    assert "its state could not be read back (xarm register 15 (GET_ERROR): no reply within" in str(err)
    stops = [r for r in peer.requests[regs.index(Reg.MOVE_LINE):] if r.register == Reg.SET_STATE]
    assert stops and all(r.params == b"\x04" for r in stops)
    if deaf == "reads":  # SET_STATE 4 is answered, but its state reads 4 only once a read gets through
        assert "stopping the arm failed: xarm: arm did not report stopped within" in str(err)
    else:
        assert "stopping the arm failed" in str(err)
    assert len(stops) >= 2  # the stop is repeated (a stop never moves the arm)
    assert elapsed < 0.3 + 1.5 + 1.0


def test_values_no_arm_can_report_are_protocol_errors() -> None:
    script: dict[int, list[bytes]] = {
        Reg.GET_TCP_POSE: [encode_reply(0, struct.pack("<6f", math.nan, 0, 0, 0, 0, 0))] * 3
        + [encode_reply(0, struct.pack("<6f", 1e9, 0, 0, 0, 0, 0))] * 3,
        Reg.GET_STATE: [encode_reply(0, b"\x09")],
        Reg.GET_JOINT_POS: [encode_reply(0, struct.pack("<7f", 0, 0, math.inf, 0, 0, 0, 0))] * 3}
    with ScriptedPeer(_answers(script, Controller(None))) as peer, \
            XArmArm(XArmArm.Config(port=peer.path, reply_timeout_s=0.5, enable_on_connect=False)) as drv:
        with pytest.raises(ProtocolError, match="not a pose"):
            drv.get_pose()
        with pytest.raises(ProtocolError, match="not a pose"):
            drv.get_pose()
        with pytest.raises(ProtocolError, match="GET_STATE replied 9"):
            drv.status()
        with pytest.raises(ProtocolError, match="not joint angles"):
            drv.joint_positions()
