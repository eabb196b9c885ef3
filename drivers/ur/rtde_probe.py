"""Is the controller streaming RTDE data? Asked with plain sockets and a deadline (:func:`probe_stream`).

ur_rtde's Python constructors hold the GIL while they connect, so a constructor that
waits on a controller which accepts the connection but sends no data blocks the whole
interpreter for ur_rtde's own 2.5 s, whatever the caller's timeout. The driver asks
this small RTDE client first (protocol 2: ``V``, one-field ``O``, ``S``, first ``U``);
framing from ``shared/spec/protocols.md`` C2. Rationale: docs/adr/0017-ur-emulator.md.
"""

from __future__ import annotations

import socket
import struct
import time

from cellcal.devices.discovery import read_exact
from cellcal.devices.errors import DeviceConnectionError, DeviceTimeoutError, ProtocolError

RTDE_PORT = 30004
_HEADER = struct.Struct(">HB")
_V, _O, _S, _U = 86, 79, 83, 85
#: Rate asked for: every controller generation offers 125 Hz.
PROBE_FREQUENCY_HZ = 125.0


def _read_message(sock: socket.socket, deadline: float) -> tuple[int, bytes]:
    head = read_exact(sock, _HEADER.size, deadline)
    size, msg_type = _HEADER.unpack(head)
    if size < _HEADER.size:
        raise ProtocolError(f"rtde probe: message size {size} is smaller than its header")
    return msg_type, read_exact(sock, size - _HEADER.size, deadline)


def _request(sock: socket.socket, msg_type: int, payload: bytes, deadline: float) -> bytes:
    """Send one request and return the payload of its reply (skipping text messages)."""
    sock.sendall(_HEADER.pack(_HEADER.size + len(payload), msg_type) + payload)
    while True:
        reply_type, reply = _read_message(sock, deadline)
        if reply_type == msg_type:
            return reply
        if reply_type != 77:  # 'M' text messages may come at any time
            raise ProtocolError(f"rtde probe: reply type {reply_type} to request {chr(msg_type)!r}")


def _conversation(sock: socket.socket, deadline: float) -> float:
    if _request(sock, _V, struct.pack(">H", 2), deadline)[:1] != b"\x01":
        raise ProtocolError("rtde probe: the controller refused RTDE protocol version 2")
    setup = _request(sock, _O, struct.pack(">d", PROBE_FREQUENCY_HZ) + b"timestamp", deadline)
    if len(setup) < 2 or setup[0] == 0 or setup[1:] != b"DOUBLE":
        raise ProtocolError(f"rtde probe: output setup refused ({setup[1:]!r})")
    if _request(sock, _S, b"", deadline)[:1] != b"\x01":
        raise ProtocolError("rtde probe: the controller refused to start the data stream")
    while True:
        msg_type, payload = _read_message(sock, deadline)
        if msg_type == _U and len(payload) == 9:
            return float(struct.unpack(">d", payload[1:])[0])


def open_port(host: str, port: int, timeout: float, name: str) -> socket.socket:
    """A TCP connection to ``host:port`` within ``timeout`` s; a refused port and no answer told apart.

    Raises:
        DeviceConnectionError: If the port is refused (nothing listens there) or unreachable.
        DeviceTimeoutError: If the host does not answer within ``timeout`` (down, or a firewall drops).
    """
    try:
        return socket.create_connection((host, port), timeout=max(0.001, timeout))
    except ConnectionRefusedError:
        raise DeviceConnectionError(f"ur {host}: connection refused on the {name} port {port} (nothing listens "
                                    f"there: is the controller on, and is {host} its address?)") from None
    except TimeoutError:
        raise DeviceTimeoutError(f"ur {host}: no answer from the {name} port {port} within {timeout:.3g} s "
                                 "(controller off or unreachable, or a firewall drops the connection)") from None
    except OSError as exc:
        raise DeviceConnectionError(f"ur {host}: {name} port {port}: {exc.strerror or exc}") from None


def probe_stream(host: str, timeout: float, port: int = RTDE_PORT) -> float:
    """Connect to RTDE, ask for the timestamp and wait for one data package; returns the timestamp (s).

    Args:
        host: Controller address.
        timeout: Seconds for the whole exchange.
        port: RTDE port.

    Raises:
        DeviceConnectionError: If the port is refused, cannot be reached or closes.
        DeviceTimeoutError: If the connection or the first data package does not come within
            ``timeout`` (an unreachable host; a silent stream).
        ProtocolError: If a reply does not follow the protocol.
    """
    deadline = time.monotonic() + timeout
    sock = open_port(host, port, timeout, "RTDE")
    try:
        with sock:
            return _conversation(sock, deadline)
    except TimeoutError:  # socket.timeout is TimeoutError
        raise DeviceTimeoutError(f"ur {host}: the RTDE port {port} accepted the connection but sent no data "
                                 f"within {timeout:.3g} s (stream frozen, or not a UR controller?)") from None
    except OSError as exc:
        raise DeviceConnectionError(f"ur {host}: RTDE port {port}: {exc}") from None
