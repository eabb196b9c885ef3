"""A hostile live-view client over a plain socket: raw WebSocket, written independently of the SDK and of
``websockets`` (whose client would read for it). Used by ``tests/integration/liveview/test_hostile_viewers.py``
and ``benchmarks/liveview_slow_clients.py``.
"""

from __future__ import annotations

import base64
import json
import os
import socket
import struct
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

#: Longest wait for a line the command prints or a client's handshake, s (a bound, not a timing assertion).
WAIT_S = 60.0


def recv_exact(sock: socket.socket, n: int) -> bytes:
    data = b""
    while len(data) < n:
        chunk = sock.recv(n - len(data))
        if not chunk:
            raise ConnectionError("closed")
        data += chunk
    return data


def frame(sock: socket.socket) -> tuple[int, bytes]:
    """One server frame (servers do not mask): its opcode and payload."""
    head = recv_exact(sock, 2)
    length = head[1] & 0x7F
    if length == 126:
        length = struct.unpack(">H", recv_exact(sock, 2))[0]
    elif length == 127:
        length = struct.unpack(">Q", recv_exact(sock, 8))[0]
    return head[0] & 0x0F, recv_exact(sock, length)


def send_text(sock: socket.socket, text: str) -> None:
    """One masked text frame, as a client must send it."""
    payload, mask = text.encode(), os.urandom(4)
    n = len(payload)
    head = bytes([0x81]) + (bytes([0x80 | n]) if n < 126 else bytes([0x80 | 126]) + struct.pack(">H", n)
                            if n < 65536 else bytes([0x80 | 127]) + struct.pack(">Q", n))
    sock.sendall(head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(payload)))


def connect(port: int, subprotocol: str = "foxglove.websocket.v1") -> socket.socket:
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


def channels(sock: socket.socket) -> list[int]:
    """Read control messages until the channels are advertised; their ids."""
    while True:
        opcode, payload = frame(sock)
        if opcode == 1 and (msg := json.loads(payload)).get("op") == "advertise":
            return [int(ch["id"]) for ch in msg["channels"]]


def subscribe_all_and_stop_reading(port: int) -> socket.socket:
    sock = connect(port)
    ids = channels(sock)
    send_text(sock, json.dumps({"op": "subscribe",
                                 "subscriptions": [{"id": i, "channelId": i} for i in ids]}))
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # and read nothing from now on
    return sock


def rss_mb(pid: int) -> float | None:
    """Resident memory of process ``pid``, MB; None once it has exited (a zombie's status has no VmRSS)."""
    try:
        lines = Path(f"/proc/{pid}/status").read_text().splitlines()
    except FileNotFoundError:
        return None
    for line in lines:
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return None


@dataclass
class SlowViewerRun:
    """What ``cellcal monitor --viz-port`` did with four viewers that never read and 200 idle connections.

    Attributes:
        returncode, out, err: The command's exit status and output.
        samples: ``(seconds since the live view started, resident MB)`` every 0.25 s.
        ended_after_s: When the command had ended, seconds since the live view started.
    """

    returncode: int
    out: str
    err: str
    samples: list[tuple[float, float]]
    ended_after_s: float

    def peaks_mb(self, duration_s: float) -> tuple[float, float]:
        """The largest resident memory in the first half of the run (after its first second) and the second."""
        early = max(mb for t, mb in self.samples if 1.0 < t <= duration_s / 2)
        late = max(mb for t, mb in self.samples if t > duration_s / 2)
        return early, late


def monitor_with_slow_viewers(port: int, duration_s: float) -> SlowViewerRun:
    """Run ``cellcal monitor --duration duration_s --viz-port port`` against hostile viewers; sample its memory."""
    proc = subprocess.Popen([sys.executable, "-m", "cellcal.core.cli", "monitor", "--duration", str(duration_s),
                             "--quiet", "--viz-port", str(port)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    sockets: list[socket.socket] = []
    samples: list[tuple[float, float]] = []
    try:
        assert proc.stderr is not None
        assert "live view:" in proc.stderr.readline()
        started = time.monotonic()
        sockets += [subscribe_all_and_stop_reading(port) for _ in range(4)]
        # idle connections: no handshake at all
        sockets += [socket.create_connection(("127.0.0.1", port), timeout=WAIT_S) for _ in range(200)]
        while proc.poll() is None and time.monotonic() - started < duration_s + WAIT_S:
            mb = rss_mb(proc.pid)
            if mb is not None:  # the command may end between the poll and the read
                samples.append((time.monotonic() - started, mb))
            time.sleep(0.25)
        out, err = proc.communicate(timeout=WAIT_S)
        ended_after_s = time.monotonic() - started
    finally:
        for sock in sockets:
            sock.close()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return SlowViewerRun(proc.returncode, out, err, samples, ended_after_s)
