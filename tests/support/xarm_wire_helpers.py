"""The controller's side of the xArm wire, written on the driver's own framing, for the driver's tests.

Encode replies, decode requests and MOVE_LINE parameters, so the tests can round-trip
the driver's frames, and :class:`ScriptedPeer`, a pty controller answering as a test
scripts it; the emulator (``cellcal.sims.xarm.wire``) keeps its own, independent wire
code, and tests/integration/hostile/test_hostile_xarm.py its own fake.
"""

from __future__ import annotations

import fcntl
import os
import select
import struct
import termios
import threading
import tty
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from cellcal.devices.errors import ProtocolError
from cellcal.drivers.xarm.protocol import (
    ARM_ID,
    HOST_ID,
    MAX_REPLY_LEN,
    MAX_REQUEST_LEN,
    FrameSplitter,
    check_frame,
    crc_bytes,
)
from cellcal.drivers.xarm.registers import unpack_floats

#: Parameter bytes of MOVE_LINE: legacy layout (9 floats), extended layout (10 floats + 3 bytes).
MOVE_LINE_LEGACY_PARAMS = 9 * 4
MOVE_LINE_COMMON_PARAMS = 10 * 4 + 3


@dataclass(frozen=True)
class Request:
    """One decoded request frame (what the controller receives).

    Attributes:
        register: Register (command) number.
        params: Parameter bytes after the register.
    """

    register: int
    params: bytes


def encode_reply(state: int, data: bytes = b"") -> bytes:
    """Build a reply frame ``0x55 0xAA LEN STATE data... CRC_lo CRC_hi``.

    Raises:
        ProtocolError: If the state is not a byte or the data is longer than 48 bytes.
    """
    if not 0 <= state <= 255:
        raise ProtocolError(f"xarm state byte must be 0..255, got {state}")
    if len(data) + 1 > MAX_REPLY_LEN:
        raise ProtocolError(f"xarm reply data too long: {len(data)} bytes (max {MAX_REPLY_LEN - 1})")
    head = bytes([ARM_ID, HOST_ID, len(data) + 1, state]) + bytes(data)
    return head + crc_bytes(head)


def parse_request(frame: bytes | bytearray | memoryview) -> Request:
    """Decode exactly one request frame.

    Raises:
        ProtocolError: As :func:`cellcal.drivers.xarm.protocol.parse_reply`.
    """
    raw = bytes(frame)
    length = check_frame(raw, HOST_ID, ARM_ID, MAX_REQUEST_LEN, "request")
    return Request(register=raw[3], params=raw[4: 3 + length])


def request_splitter() -> FrameSplitter:
    """A splitter for the host -> arm direction."""
    return FrameSplitter(HOST_ID, ARM_ID, MAX_REQUEST_LEN)


@dataclass(frozen=True)
class MoveLine:
    """A decoded MOVE_LINE request.

    Attributes:
        pose: ``[x, y, z]`` mm and ``[roll, pitch, yaw]`` rad, or an axis-angle
            rotation when :attr:`axis_angle`; ``inf`` means "keep the current value"
            (sent by the SDK for firmware >= 2.4.101 when a coordinate is omitted).
        speed_mm_s: Tool speed.
        acc_mm_s2: Tool acceleration.
        radius_mm: Blend radius (-1: none); None in the legacy layout.
        coord: 0 base frame, 1 tool frame.
        axis_angle: Orientation given as a rotation vector.
        only_check: Only check reachability, do not move.
        common: Whether the extended layout was used (its reply carries 3 bytes).
    """

    pose: tuple[float, ...]
    speed_mm_s: float
    acc_mm_s2: float
    radius_mm: float | None = None
    coord: int = 0
    axis_angle: bool = False
    only_check: int = 0
    common: bool = False


def decode_move_line(params: bytes) -> MoveLine:
    """Decode MOVE_LINE parameters in either layout.

    Raises:
        ProtocolError: On a parameter length that matches neither layout.
    """
    n = len(params)
    if n in (MOVE_LINE_LEGACY_PARAMS, MOVE_LINE_LEGACY_PARAMS + 1, MOVE_LINE_LEGACY_PARAMS + 2):
        f = unpack_floats(params, 9)
        only = params[36] if n > 36 else 0
        return MoveLine(tuple(f[:6]), f[6], f[7], only_check=only, common=n > 36)
    if n in (MOVE_LINE_COMMON_PARAMS, MOVE_LINE_COMMON_PARAMS + 1):
        f = unpack_floats(params, 10)
        coord, aa, only = params[40], params[41], params[42]
        return MoveLine(tuple(f[:6]), f[6], f[7], radius_mm=f[9], coord=coord, axis_angle=bool(aa),
                        only_check=only, common=True)
    raise ProtocolError(f"xarm MOVE_LINE with {n} parameter bytes matches no known layout")


class ScriptedPeer:
    """A controller on a pty that answers each request with ``answer(request)`` (bytes; b"" = no reply).

    For the driver's unit tests: the requests it received are in :attr:`requests`. Use it as
    a context manager; the serving thread and both pty ends are closed on exit.

    Args:
        answer: Called on the serving thread for every well-formed request.
    """

    def __init__(self, answer: Callable[[Request], bytes]):
        self.answer = answer
        self.requests: list[Request] = []
        self._stop = threading.Event()
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        self.path = os.ttyname(self._slave)
        self._thread = threading.Thread(target=self._serve, name="scripted-xarm", daemon=True)

    def __enter__(self) -> ScriptedPeer:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(5.0)
        os.close(self._master)
        os.close(self._slave)

    def registers(self) -> list[int]:
        """The register of every request received, in order."""
        return [r.register for r in self.requests]

    def send(self, data: bytes) -> None:
        """Write unsolicited bytes to the host."""
        os.write(self._master, data)

    def pending_at_host(self) -> int:
        """How many bytes wait to be read at the host's end of the line (a write reaches it a moment later)."""
        return int(struct.unpack("i", fcntl.ioctl(self._slave, termios.FIONREAD, b"\0\0\0\0"))[0])

    def _serve(self) -> None:
        splitter = request_splitter()
        while not self._stop.is_set():
            ready, _, _ = select.select([self._master], [], [], 0.01)
            if not ready:
                continue
            for frame in splitter.feed(os.read(self._master, 4096)):
                try:
                    request = parse_request(frame)
                except ProtocolError:
                    continue
                self.requests.append(request)
                out = self.answer(request)
                if out:
                    os.write(self._master, out)


class ScriptedTcpPeer:
    """A controller on a loopback TCP port answering each request with ``answer(tid, request)`` (b"" = no reply).

    For the TCP transport's unit tests: the requests received are in :attr:`requests` as
    ``(transaction_id, Request)``. One client at a time; a context manager.

    Args:
        answer: Called on the serving thread for every request frame.
    """

    def __init__(self, answer: Callable[[int, Request], bytes]):
        import socket

        self.answer = answer
        self.requests: list[tuple[int, Request]] = []
        self._stop = threading.Event()
        self._server = socket.socket()
        self._server.bind(("127.0.0.1", 0))
        self._server.listen(1)
        self.port = self._server.getsockname()[1]
        self._thread = threading.Thread(target=self._serve, name="scripted-xarm-tcp", daemon=True)

    def __enter__(self) -> ScriptedTcpPeer:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(5.0)
        self._server.close()

    def registers(self) -> list[int]:
        """The register of every request received, in order."""
        return [r.register for _, r in self.requests]

    def _serve(self) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select([self._server], [], [], 0.01)
            if ready:
                client, _ = self._server.accept()
                with client:
                    self._talk(client)

    def _talk(self, client: object) -> None:
        import socket

        assert isinstance(client, socket.socket)
        buf = b""
        while not self._stop.is_set():
            ready, _, _ = select.select([client], [], [], 0.01)
            if not ready:
                continue
            chunk = client.recv(4096)
            if not chunk:
                return
            buf += chunk
            while len(buf) >= 6 and len(buf) >= 6 + int.from_bytes(buf[4:6], "big"):
                end = 6 + int.from_bytes(buf[4:6], "big")
                tid, request = int.from_bytes(buf[:2], "big"), Request(buf[6], buf[7:end])
                buf = buf[end:]
                self.requests.append((tid, request))
                out = self.answer(tid, request)
                if out:
                    client.sendall(out)


def tcp_reply(tid: int, register: int, state: int = 0, data: bytes = b"", protocol: int = 2) -> bytes:
    """A reply frame of the TCP protocol: tid, protocol, length, REG echo, STATE, data."""
    return (tid.to_bytes(2, "big") + protocol.to_bytes(2, "big") + (len(data) + 2).to_bytes(2, "big")
            + bytes([register, state]) + data)


def bounded_call(fn: Callable[[], Any], timeout: float) -> Any:
    """Run ``fn`` (a vendor SDK call without a timeout) in a thread; fail the test if it does not return in time."""
    out: dict[str, Any] = {}

    def run() -> None:
        try:
            out["value"] = fn()
        except BaseException as exc:  # re-raised in the caller
            out["error"] = exc

    t = threading.Thread(target=run, name="sdk-call", daemon=True)
    t.start()
    t.join(timeout)
    assert not t.is_alive(), f"SDK call did not return within {timeout} s"
    if "error" in out:
        raise out["error"]
    return out.get("value")


def sdk_refuses_an_out_of_workspace_move(sdk: Any, sim: Any) -> None:
    """With xarm-python-sdk's ``XArmAPI`` enabled and ready: a target 1.5 m out ends in controller
    error 21 (the SDK returns non-zero), the simulated arm ``sim`` does not move, and
    ``clean_error`` clears the error."""
    import math

    start = sim.true_flange_pose()
    code = bounded_call(lambda: sdk.set_position(1500, 0, 300, math.pi, 0, 0, speed=200, mvacc=2000,
                                                 is_radian=True, wait=True, timeout=10), 20.0)
    assert code != 0
    assert sdk.get_err_warn_code()[1][0] == 21
    assert sim.true_flange_pose().distance_to(start) == 0.0
    assert sdk.clean_error() == 0
    assert sdk.get_err_warn_code()[1][0] == 0
