"""Viewers that do not read, connect too often or send nonsense cannot grow the live view without bound,
hold a run past its end, or flood its output (issue #31, ADR 0039).

The hostile viewers speak raw WebSocket over a plain socket (written here, independently of the
SDK and of ``websockets``, whose client would read for them): they subscribe to every channel and
then never read a byte.
"""

from __future__ import annotations

import base64
import contextlib
import json
import logging
import os
import socket
import struct
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("foxglove")

from cellcal.core.liveview import LiveView
from cellcal.core.liveview.sdklog import MAX_RECORDS_PER_S
from cellcal.core.liveview.server import MAX_CLIENTS
from tests.support.ports import free_port, port_free

#: Longest wait for a line the command prints or a client's handshake, s (a bound, not a timing assertion).
WAIT_S = 60.0


def _recv_exact(sock: socket.socket, n: int) -> bytes:
    data = b""
    while len(data) < n:
        chunk = sock.recv(n - len(data))
        if not chunk:
            raise ConnectionError("closed")
        data += chunk
    return data


def _frame(sock: socket.socket) -> tuple[int, bytes]:
    """One server frame (servers do not mask): its opcode and payload."""
    head = _recv_exact(sock, 2)
    length = head[1] & 0x7F
    if length == 126:
        length = struct.unpack(">H", _recv_exact(sock, 2))[0]
    elif length == 127:
        length = struct.unpack(">Q", _recv_exact(sock, 8))[0]
    return head[0] & 0x0F, _recv_exact(sock, length)


def _send_text(sock: socket.socket, text: str) -> None:
    """One masked text frame, as a client must send it."""
    payload, mask = text.encode(), os.urandom(4)
    n = len(payload)
    head = bytes([0x81]) + (bytes([0x80 | n]) if n < 126 else bytes([0x80 | 126]) + struct.pack(">H", n)
                            if n < 65536 else bytes([0x80 | 127]) + struct.pack(">Q", n))
    sock.sendall(head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(payload)))


def _connect(port: int, subprotocol: str = "foxglove.websocket.v1") -> socket.socket:
    """A raw WebSocket connection to the live view, its handshake done."""
    sock = socket.create_connection(("127.0.0.1", port), timeout=WAIT_S)
    key = base64.b64encode(os.urandom(16)).decode()
    sock.sendall((f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                  f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
                  f"Sec-WebSocket-Protocol: {subprotocol}\r\n\r\n").encode())
    reply = b""
    while b"\r\n\r\n" not in reply:
        chunk = sock.recv(1)
        if not chunk:
            raise ConnectionError(f"closed during the handshake: {reply!r}")
        reply += chunk
    assert reply.startswith(b"HTTP/1.1 101"), reply
    return sock


def _channels(sock: socket.socket) -> list[int]:
    """Read control messages until the channels are advertised; their ids."""
    while True:
        opcode, payload = _frame(sock)
        if opcode == 1 and (msg := json.loads(payload)).get("op") == "advertise":
            return [int(ch["id"]) for ch in msg["channels"]]


def _subscribe_all_and_stop_reading(port: int) -> socket.socket:
    sock = _connect(port)
    ids = _channels(sock)
    _send_text(sock, json.dumps({"op": "subscribe",
                                 "subscriptions": [{"id": i, "channelId": i} for i in ids]}))
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # and read nothing from now on
    return sock


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise AssertionError("no VmRSS")


@pytest.mark.skipif(not Path("/proc/self/status").is_file(), reason="reads the child's memory from /proc")
def test_four_viewers_that_never_read_and_200_idle_connections_cost_bounded_memory_and_the_run_ends_on_time(
        tmp_path: Path) -> None:
    port, duration_s = free_port(), 12.0
    proc = subprocess.Popen([sys.executable, "-m", "cellcal.core.cli", "monitor", "--duration", str(duration_s),
                             "--quiet", "--viz-port", str(port)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    sockets: list[socket.socket] = []
    try:
        assert proc.stderr is not None
        assert "live view:" in proc.stderr.readline()
        started = time.monotonic()
        sockets += [_subscribe_all_and_stop_reading(port) for _ in range(4)]
        for _ in range(200):  # idle connections: no handshake at all
            with_idle = socket.create_connection(("127.0.0.1", port), timeout=WAIT_S)
            sockets.append(with_idle)
        samples = []
        while proc.poll() is None and time.monotonic() - started < duration_s + WAIT_S:
            samples.append((time.monotonic() - started, _rss_mb(proc.pid)))
            time.sleep(0.25)
        out, err = proc.communicate(timeout=WAIT_S)
        ended_after_s = time.monotonic() - started
    finally:
        for sock in sockets:
            sock.close()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err
    assert "monitor finished" in out
    # the run ends when --duration is over (plus its start-up and the close's bounded wait), not when the viewers go
    assert ended_after_s < duration_s + 15.0, ended_after_s
    # memory: what the second half of the run adds is small (no growth with the frames published)
    late = [mb for t, mb in samples if t > duration_s / 2]
    early = [mb for t, mb in samples if 1.0 < t <= duration_s / 2]
    assert late and early, samples
    assert max(late) - max(early) < 20.0, samples  # flat at ~135 MB here; unbounded queues grew ~30 MB/s
    assert max(mb for _, mb in samples) < 600.0, samples
    assert port_free(port)


def test_more_viewers_than_the_cap_are_closed_as_they_connect_and_the_others_are_served() -> None:
    with LiveView(0) as view:
        admitted = [_connect(view.port) for _ in range(MAX_CLIENTS)]
        try:
            assert all(_channels(sock) for sock in admitted)
            extra = socket.create_connection(("127.0.0.1", view.port), timeout=WAIT_S)
            with extra:
                assert extra.recv(1) == b""  # closed at accept
            assert _channels(_connect_after_one_leaves(admitted, view.port))
        finally:
            for sock in admitted:
                sock.close()


def _connect_after_one_leaves(admitted: list[socket.socket], port: int) -> socket.socket:
    """Close one admitted viewer; a new one is admitted once the relay has seen it leave."""
    admitted.pop().close()
    deadline = time.monotonic() + WAIT_S
    while True:
        try:
            sock = _connect(port)
            admitted.append(sock)
            return sock
        except (ConnectionError, AssertionError):
            assert time.monotonic() < deadline
            time.sleep(0.05)


def test_a_thousand_unknown_channel_ids_in_one_message_make_a_bounded_number_of_log_records(
        caplog: pytest.LogCaptureFixture, capfd: pytest.CaptureFixture[str]) -> None:
    caplog.set_level(logging.INFO, logger="cellcal.liveview")
    with LiveView(0) as view:
        sock = _connect(view.port)
        _channels(sock)
        _send_text(sock, json.dumps({"op": "subscribe",
                                     "subscriptions": [{"id": 10_000 + i, "channelId": 50_000 + i}
                                                       for i in range(1000)]}))
        # the SDK answers each unknown id with a status message (and logs it), then drops the client, whose
        # control queue (MESSAGE_BACKLOG) overflowed: read until then
        statuses = 0
        with contextlib.suppress(ConnectionError):
            while statuses < 1000:
                opcode, payload = _frame(sock)
                statuses += opcode == 1 and json.loads(payload).get("op") == "status"
        sock.close()
    ours = _records(caplog)  # closing the view reported what was held back
    texts = [r.getMessage() for r in ours]
    (summary,) = [t for t in texts if "suppressed" in t]
    suppressed = int(summary.split()[1])
    # at most ten records a second and one line saying how many more (one record per unknown id: 1000 in all)
    assert len(texts) <= 2 * MAX_RECORDS_PER_S + 1, texts
    assert sum("unknown channel" in t for t in texts) + suppressed >= 1000, texts
    assert capfd.readouterr() == ("", "")


def _records(caplog: pytest.LogCaptureFixture) -> list[Any]:
    return [r for r in caplog.records if r.name == "cellcal.liveview"]
