"""The real O3R driver against hostile fake O3R devices written here (not cellcal.sims), over loopback sockets.

A tiny HTTP server plays the XML-RPC configuration channel and a tiny PCIC server the image
channel; each case scripts one misbehaviour (trickled headers, endless bodies, entity bombs,
bad values, oversize notifications, ...). Every case asserts the typed error, the time to
fail (configured timeout + 1 s at most), the memory bound (tracemalloc peak) and that no
thread is left behind. ``pytest -s`` prints the figures per case.
"""

from __future__ import annotations

import contextlib
import json
import re
import socket
import struct
import threading
import time
import tracemalloc
import xmlrpc.client
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest

from cellcal.devices.errors import (
    CellcalError,
    DeviceConnectionError,
    DeviceError,
    DeviceTimeoutError,
    ProtocolError,
    VendorError,
)
from cellcal.drivers.o3r import client as pcic_client
from cellcal.drivers.o3r.camera import O3RCamera, O3RConfig

MiB = 1024 * 1024
IO_TIMEOUT_S = 1.0      # the configured whole-call / stall timeout of every case
CONNECT_TIMEOUT_S = 2.0  # what connect() is given
CAP = 1 * MiB           # max_rpc_reply_bytes and max_buffered_bytes of every case
W, H = 16, 12           # image size of the fake head


# ---------------------------------------------------------------------- fake servers
class FakeServer:
    """Accepts TCP connections on 127.0.0.1 and runs ``handler(conn, stop)`` for each in a thread."""

    def __init__(self, handler: Callable[[socket.socket, threading.Event], None]) -> None:
        self._handler = handler
        self._listener = socket.create_server(("127.0.0.1", 0))
        self._listener.settimeout(0.05)
        self.port: int = self._listener.getsockname()[1]
        self.stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._accept_thread = threading.Thread(target=self._accept, name="fake-accept", daemon=True)
        self._accept_thread.start()

    def _accept(self) -> None:
        while not self.stop.is_set():
            try:
                conn, _ = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            conn.settimeout(5.0)
            t = threading.Thread(target=self._serve, args=(conn,), name="fake-conn", daemon=True)
            self._threads.append(t)
            t.start()

    def _serve(self, conn: socket.socket) -> None:
        with conn, contextlib.suppress(OSError):
            self._handler(conn, self.stop)

    def close(self) -> None:
        self.stop.set()
        self._listener.close()
        for t in [self._accept_thread, *self._threads]:
            t.join(timeout=10.0)
            assert not t.is_alive(), "a fake server thread did not end"


def read_exact(conn: socket.socket, n: int) -> bytes:
    out = bytearray()
    while len(out) < n:
        got = conn.recv(n - len(out))
        if not got:
            raise EOFError
        out += got
    return bytes(out)


def read_http_request(conn: socket.socket) -> str:
    """Read one HTTP request (headers up to 64 KiB, body by Content-Length); return the XML-RPC method."""
    data = b""
    while b"\r\n\r\n" not in data:
        got = conn.recv(4096)
        if not got or len(data) > 65536:
            raise EOFError
        data += got
    head, _, body = data.partition(b"\r\n\r\n")
    length = int(re.search(rb"Content-Length: (\d+)", head).group(1))  # type: ignore[union-attr]
    body += read_exact(conn, length - len(body))
    return re.search(rb"<methodName>([^<]*)</methodName>", body).group(1).decode()  # type: ignore[union-attr]


def http(body: bytes, *, status: str = "200 OK", headers: str | None = None) -> bytes:
    headers = f"Content-Length: {len(body)}\r\n" if headers is None else headers
    return f"HTTP/1.1 {status}\r\nContent-Type: text/xml\r\n{headers}\r\n".encode() + body


def xml_value(text: str) -> bytes:
    return xmlrpc.client.dumps((text,), methodresponse=True).encode()


def xml_fault(code_xml: str) -> bytes:
    return (f"<?xml version='1.0'?><methodResponse><fault><value><struct><member><name>faultCode</name>"
            f"<value>{code_xml}</value></member><member><name>faultString</name><value><string>boom</string>"
            f"</value></member></struct></value></fault></methodResponse>").encode()


def trickle(conn: socket.socket, data: bytes, stop: threading.Event, interval_s: float = 0.1) -> None:
    """Send one byte per interval (the test's 'slow device'); ends when the client hangs up."""
    for i in range(len(data)):
        if stop.is_set():
            return
        conn.sendall(data[i:i + 1])
        stop.wait(interval_s)


def flood(conn: socket.socket, piece: bytes, stop: threading.Event, max_bytes: int = 2 * 1024 * MiB) -> None:
    """Send ``piece`` again and again (up to ``max_bytes``) until the client hangs up."""
    sent = 0
    while sent < max_bytes and not stop.is_set():
        conn.sendall(piece)
        sent += len(piece)


def tree(pcic_port: int, **port: Any) -> dict[str, Any]:
    """A minimal documented O3R tree with one 3D head on port2."""
    p2 = {"data": {"pcicTCPPort": pcic_port}, "state": "RUN",
          "info": {"features": {"type": "3D", "resolution": {"width": W, "height": H}}}}
    p2.update(port)
    return {"ports": {"port2": p2}, "device": {"swVersion": {"firmware": "1.4.30"}}}


def xmlrpc_server(answer: Callable[[socket.socket, threading.Event], None]) -> FakeServer:
    """A fake configuration channel: reads each request, then runs ``answer``."""
    def handler(conn: socket.socket, stop: threading.Event) -> None:
        read_http_request(conn)
        answer(conn, stop)
    return FakeServer(handler)


def answering(reply: bytes) -> Callable[[socket.socket, threading.Event], None]:
    return lambda conn, stop: conn.sendall(reply)


# ---------------------------------------------------------------------- PCIC
def message(ticket: bytes, content: bytes) -> bytes:
    return ticket + b"L%09d\r\n" % (len(content) + 6) + ticket + content + b"\r\n"


def chunk(kind: int, data: bytes, width: int, height: int, fmt: int) -> bytes:
    return struct.pack("<9I3I", kind, 48 + len(data), 48, 2, width, height, fmt, 0, 1, 0, 0, 0) + data


def tof_info() -> bytes:
    """TOF_INFO v1: 1 mm per count, pinhole models 0 and 1 (fx = fy = 20 px, centre 8, 6)."""
    model = [20.0, 20.0, 8.0, 6.0] + [0.0] * 28
    return (struct.pack("<I2f3f6f", 1, 0.001, 1.0, 0, 0, 0, 0, 0, 0, 0, 0, 0)
            + struct.pack("<I32f", 0, *model) + struct.pack("<I32f", 1, *model))


def frame_message(info_size: tuple[int, int] = (W, H)) -> bytes:
    """An image message: a flat 0.8 m distance image and a TOF_INFO whose header says ``info_size``."""
    distance = np.full((H, W), 800, "<u2").tobytes()
    body = chunk(100, distance, W, H, 2) + chunk(420, tof_info(), *info_size, 0)
    return message(b"0000", b"star" + body + b"stop")


FRAME = frame_message()


def pcic_server(script: Callable[[socket.socket, threading.Event], None], frame: bytes = FRAME) -> FakeServer:
    """A fake PCIC port: answers the client's two setup commands with '*', runs ``script``, then streams frames."""
    def handler(conn: socket.socket, stop: threading.Event) -> None:
        for _ in range(2):  # c (schema) and p (output mask)
            header = read_exact(conn, 16)
            read_exact(conn, int(header[5:14]))
            conn.sendall(message(header[:4], b"*"))
        script(conn, stop)
        for _ in range(1500):  # 30 s of frames at most
            if stop.is_set():
                return
            conn.sendall(frame)
            stop.wait(0.02)
    return FakeServer(handler)


# ---------------------------------------------------------------------- measuring
@dataclass
class Figure:
    """One case's outcome, time to fail and peak of traced memory above the start."""

    case: str
    outcome: str = ""
    seconds: float = 0.0
    peak_bytes: int = 0


FIGURES: list[Figure] = []


@contextlib.contextmanager
def measured(case: str) -> Iterator[Figure]:
    fig = Figure(case)
    tracemalloc.start()
    base = tracemalloc.get_traced_memory()[0]
    start = time.monotonic()
    try:
        yield fig
    finally:
        fig.seconds = time.monotonic() - start
        fig.peak_bytes = tracemalloc.get_traced_memory()[1] - base
        tracemalloc.stop()
        FIGURES.append(fig)


@pytest.fixture(scope="module", autouse=True)
def figures() -> Iterator[None]:
    yield
    print(f"\n{'case':<34} {'s':>6} {'peak MiB':>9}  outcome")
    for f in FIGURES:
        print(f"{f.case:<34} {f.seconds:6.2f} {f.peak_bytes / MiB:9.2f}  {f.outcome[:110]}")
    if FIGURES:
        print(f"{len(FIGURES)} cases, worst time {max(f.seconds for f in FIGURES):.2f} s, "
              f"worst peak {max(f.peak_bytes for f in FIGURES) / MiB:.2f} MiB")


@pytest.fixture(autouse=True)
def no_thread_left() -> Iterator[None]:
    before = set(threading.enumerate())
    yield
    deadline = time.monotonic() + 5.0
    while True:
        left = [t.name for t in threading.enumerate() if t not in before and t.is_alive()]
        if not left or time.monotonic() > deadline:
            break
        time.sleep(0.01)
    assert left == [], f"threads left behind: {left}"


def config(xmlrpc_port: int, **kw: Any) -> O3RConfig:
    return O3RConfig(host="127.0.0.1", xmlrpc_port=xmlrpc_port, port="port2", trigger="free_run", set_state=False,
                     io_timeout_s=IO_TIMEOUT_S, connect_timeout_s=IO_TIMEOUT_S, reconnect_backoff_s=0.05,
                     max_rpc_reply_bytes=CAP, max_buffered_bytes=CAP, **kw)


def fails_to_connect(case: str, xmlrpc_port: int, error: type[CellcalError], match: str) -> Figure:
    """Connect must raise ``error`` matching ``match``: one line, within the timeout + 1 s, memory bounded."""
    cam = O3RCamera(config(xmlrpc_port))
    with measured(case) as fig, pytest.raises(error, match=match) as ei:
        cam.connect(timeout=CONNECT_TIMEOUT_S)
    fig.outcome = f"{type(ei.value).__name__}: {ei.value}"
    assert not cam.connected
    assert "\n" not in str(ei.value) and len(str(ei.value)) < 400, str(ei.value)
    assert fig.seconds <= CONNECT_TIMEOUT_S + 1.0, fig
    # the reply cap bounds memory: chunked bodies are joined once (2x), plus parser overhead
    assert fig.peak_bytes < 3 * CAP + 2 * MiB, fig
    return fig


# ---------------------------------------------------------------------- configuration channel
GOOD = http(xml_value(json.dumps(tree(50012))))
CHUNK_64K = b"10000\r\n" + b"x" * 65536 + b"\r\n"
X64K = b"<" * 65536
BOMB = (b"<?xml version='1.0'?><!DOCTYPE l [<!ENTITY a '" + b"x" * 100 + b"'>"
        + b"".join(b"<!ENTITY %c '%s'>" % (98 + i, b"&%c;" % (97 + i) * 10) for i in range(8))
        + b"]><methodResponse><params><param><value><string>&i;</string></value></param></params></methodResponse>")
EXTERNAL = (b"<?xml version='1.0'?><!DOCTYPE r [<!ENTITY e SYSTEM 'file:///etc/passwd'>]><methodResponse><params>"
            b"<param><value><string>&e;</string></value></param></params></methodResponse>")
DEEP_XML = (b"<?xml version='1.0'?><methodResponse><params><param>" + b"<value><array><data>" * 20000
            + b"</data></array></value>" * 20000 + b"</param></params></methodResponse>")
TWO_VALUES = (b"<?xml version='1.0'?><methodResponse><params><param><value><string>{}</string></value></param>"
              b"<param><value><string>{}</string></value></param></params></methodResponse>")

RPC_CASES: list[tuple[str, Callable[[socket.socket, threading.Event], None], type[CellcalError], str]] = [
    ("slow headers (1 byte / 0.1 s)", lambda c, s: trickle(c, GOOD, s), DeviceTimeoutError,
     r"get\(\['/ports'\]\): no complete answer within 1 s"),
    ("slow body (1 byte / 0.1 s)", lambda c, s: (c.sendall(GOOD[:GOOD.index(b"\r\n\r\n") + 4]),
                                                  trickle(c, GOOD[GOOD.index(b"\r\n\r\n") + 4:], s)),
     DeviceTimeoutError, "no complete answer within 1 s"),
    ("chunked body trickled", lambda c, s: (c.sendall(http(b"", headers="Transfer-Encoding: chunked\r\n")),
                                            trickle(c, b"1\r\n<\r\n" * 10000, s)),
     DeviceTimeoutError, "no complete answer within 1 s"),
    ("endless chunked body", lambda c, s: (c.sendall(http(b"", headers="Transfer-Encoding: chunked\r\n")),
                                           flood(c, CHUNK_64K, s)),
     ProtocolError, "the reply exceeds the cap of 1048576 bytes"),
    ("400 MB reply, declared", lambda c, s: (c.sendall(http(b"", headers=f"Content-Length: {400 * 10**6}\r\n")),
                                             flood(c, X64K, s, 400 * 10**6)),
     ProtocolError, "exceeds the cap of 1048576 bytes"),
    ("400 MB reply, undeclared", lambda c, s: (c.sendall(b"HTTP/1.0 200 OK\r\n\r\n"), flood(c, X64K, s, 400 * 10**6)),
     ProtocolError, "exceeds the cap of 1048576 bytes"),
    ("header flood", lambda c, s: (c.sendall(b"HTTP/1.1 200 OK\r\n"), flood(c, b"X-A: b\r\n" * 8192, s)),
     ProtocolError, "malformed HTTP answer|exceeds the cap"),
    ("not HTTP", answering(b"SSH-2.0-OpenSSH_9.6\r\n" * 3), ProtocolError, "malformed HTTP answer"),
    ("hangs up", lambda c, s: None, DeviceConnectionError, "closed the connection without an answer"),
    ("HTTP 500", answering(http(b"oops", status="500 Internal Server Error")), DeviceConnectionError,
     "HTTP 500 'Internal Server Error'"),
    ("entity bomb", answering(http(BOMB)), ProtocolError, r"get\(\['/ports'\]\): malformed XML-RPC reply"),
    ("external entity", answering(http(EXTERNAL)), ProtocolError, "malformed XML-RPC reply"),
    ("nested JSON (100k deep)", answering(http(xml_value("[" * 100000 + "]" * 100000))), ProtocolError,
     "nested too deeply"),
    ("nested XML-RPC arrays (20k deep)", answering(http(DEEP_XML)), ProtocolError, "nested deeper than 32"),
    ("an array, not a string", answering(http(xmlrpc.client.dumps(([1],), methodresponse=True).encode())),
     ProtocolError, "answered an array, expected a JSON string"),
    ("faultCode a string", answering(http(xml_fault("<string>abc</string>"))), ProtocolError,
     "faultCode 'abc' and faultString 'boom'"),
    ("faultCode a bool", answering(http(xml_fault("<boolean>1</boolean>"))), ProtocolError, "faultCode True"),
    ("faultCode a 5000-digit int", answering(http(xml_fault("<int>" + "9" * 5000 + "</int>"))), ProtocolError,
     "malformed XML-RPC reply"),
    ("fault without faultCode", answering(http(xml_fault("<string>x</string>").replace(b"faultCode", b"code"))),
     ProtocolError, "malformed XML-RPC reply"),
    ("two values", answering(http(TWO_VALUES)), ProtocolError, "holds 2 values"),
    ("not JSON", answering(http(xml_value("nope"))), ProtocolError, "the answer is not JSON"),
    ("JSON NaN", answering(http(xml_value('{"ports": NaN}'))), ProtocolError, "NaN is not JSON"),
    ("JSON 5000-digit number", answering(http(xml_value('{"ports": 1' + "0" * 5000 + "}"))), ProtocolError,
     "the answer is not JSON"),
    ("JSON array", answering(http(xml_value("[1, 2]"))), ProtocolError, "is an array, expected an object"),
]


@pytest.mark.parametrize(("case", "answer", "error", "match"), RPC_CASES, ids=[c[0] for c in RPC_CASES])
def test_hostile_configuration_channel(case: str, answer: Callable[[socket.socket, threading.Event], None],
                                       error: type[CellcalError], match: str) -> None:
    server = xmlrpc_server(answer)
    try:
        fails_to_connect(case, server.port, error, match)
    finally:
        server.close()


def test_well_formed_fault_is_a_vendor_error() -> None:
    server = xmlrpc_server(answering(http(xml_fault("<int>101000</int>"))))
    try:
        fig = fails_to_connect("well-formed fault", server.port, VendorError, r"o3r error 101000: .*get.*: boom")
        assert fig.seconds < 0.5
    finally:
        server.close()


BAD_VALUES: list[tuple[dict[str, Any], str, str]] = [
    *[({"data": {"pcicTCPPort": v}}, "/ports/port2/data/pcicTCPPort", f"must be an integer in 1..65535, got {shown}")
      for v, shown in [(0, "0"), (65536, "65536"), (-1, "-1"), (True, "True"), (1e308, "1e+308"),
                       ("50010", "'50010'"), (None, "null"), ([50010], "an array"), (50010.5, "50010.5")]],
    *[({"state": v}, "/ports/port2/state", f"must be one of RUN, IDLE, CONF, got {shown}")
      for v, shown in [(["RUN"], "an array"), ("FAST", "'FAST'"), (3, "3"), ({"RUN": 1}, "an object")]],
    *[({"info": {"features": {"type": v}}}, "/ports/port2/info/features/type",
       f"must be a printable string of 1..64 characters, got {shown}")
      for v, shown in [(["3D"], "an array"), ("", "''"), (3, "3"), ("3D\n\x1b[2J", "'3D\\n\\x1b[2J'")]],
    ({"info": {"features": {"type": "3D", "resolution": {"width": 10**9, "height": H}}}},
     "/ports/port2/info/features/resolution/width", "must be an integer in 1..8192, got 1000000000"),
    ({"info": {"features": {"type": "3D", "resolution": {"width": W, "height": "12"}}}},
     "/ports/port2/info/features/resolution/height", "must be an integer in 1..8192, got '12'"),
    ({"data": []}, "/ports/port2/data", "must be an object, got an array"),
    ({"data": {}}, "/ports/port2/data/pcicTCPPort", "is missing"),
]


@pytest.mark.parametrize(("patch", "pointer", "message"), BAD_VALUES,
                         ids=[f"{b[1].rsplit('/', 1)[1]}:{b[2].rsplit(' ', 1)[1]}" for b in BAD_VALUES])
def test_values_from_the_device_are_checked_against_the_tree(patch: dict[str, Any], pointer: str,
                                                             message: str) -> None:
    doc = tree(50012)
    doc["ports"]["port2"].update(patch)
    server = xmlrpc_server(answering(http(xml_value(json.dumps(doc)))))
    try:
        fig = fails_to_connect(f"{pointer.rsplit('/', 1)[1]}: {message.rsplit(' ', 1)[1]}", server.port,
                               ProtocolError, re.escape(f"get(['/ports']): {pointer} {message}") + "$")
        assert fig.seconds < 0.5
    finally:
        server.close()


def test_ports_not_an_object_and_port_not_an_object() -> None:
    for doc, match in [({"ports": [1]}, "/ports must be an object, got an array"),
                       ({"ports": {"port2": "x"}}, "/ports/port2 must be an object, got 'x'"),
                       ({"device": {}}, "/ports is missing")]:
        server = xmlrpc_server(answering(http(xml_value(json.dumps(doc)))))
        try:
            fails_to_connect(f"tree {json.dumps(doc)[:24]}", server.port, ProtocolError, re.escape(match))
        finally:
            server.close()


# ---------------------------------------------------------------------- the PCIC port itself
def _wait_for_stop(conn: socket.socket, stop: threading.Event) -> None:
    stop.wait(30.0)


PORT_CASES: list[tuple[str, Callable[[socket.socket, threading.Event], None] | None, type[CellcalError], str]] = [
    ("PCIC port answers HTTP", answering(b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\n\r\n"), ProtocolError,
     r"does not answer as PCIC: its first bytes are b'HTTP/1.1 400 Bad'; that is HTTP: does the PCIC port "
     r"point at the XML-RPC server\?"),
    ("PCIC port sends garbage", answering(bytes(range(256))), ProtocolError,
     r"does not answer as PCIC: its first bytes are b'\\x00\\x01"),
    ("PCIC port silent", _wait_for_stop, DeviceConnectionError,
     r"not set up within [\d.]+ s \(the port accepted the TCP connection but gave no PCIC reply to the schema and "
     r"output mask \(is it a PCIC port\?\)\)"),
    ("PCIC port closed", None, DeviceConnectionError, r"not set up within [\d.]+ s \(connect failed: .*refused"),
]


@pytest.mark.parametrize(("case", "behaviour", "error", "match"), PORT_CASES, ids=[c[0] for c in PORT_CASES])
def test_a_port_that_does_not_answer_as_pcic_is_named(case: str,
                                                      behaviour: Callable[[socket.socket, threading.Event], None],
                                                      error: type[CellcalError], match: str) -> None:
    if behaviour is None:
        with socket.socket() as probe:  # a port nobody listens on
            probe.bind(("127.0.0.1", 0))
            pcic_port = probe.getsockname()[1]
        pcic = None
    else:
        pcic = FakeServer(behaviour)
        pcic_port = pcic.port
    server = xmlrpc_server(answering(http(xml_value(json.dumps(tree(pcic_port))))))
    try:
        fails_to_connect(case, server.port, error, match)
    finally:
        server.close()
        if pcic is not None:
            pcic.close()


def test_pcic_port_pointing_at_the_xmlrpc_server() -> None:
    box: list[int] = []
    server = xmlrpc_server(lambda conn, stop: conn.sendall(http(xml_value(json.dumps(tree(box[0]))))))
    box.append(server.port)
    try:
        fig = fails_to_connect("pcicTCPPort = the XML-RPC port", server.port, ProtocolError,
                               f"/ports/port2/data/pcicTCPPort is {server.port}, the XML-RPC port; it does not "
                               f"answer as PCIC")
        assert fig.seconds < 0.5
    finally:
        server.close()


# ---------------------------------------------------------------------- image channel
CAPTURE_TIMEOUT_S = 2.0


@contextlib.contextmanager
def streaming(script: Callable[[socket.socket, threading.Event], None], frame: bytes = FRAME
              ) -> Iterator[O3RCamera]:
    """A camera connected to a fake PCIC port that runs ``script`` and then streams ``frame``."""
    pcic = pcic_server(script, frame)
    server = xmlrpc_server(answering(http(xml_value(json.dumps(tree(pcic.port))))))
    cam = O3RCamera(config(server.port))
    try:
        cam.connect(timeout=CONNECT_TIMEOUT_S)
        yield cam
    finally:
        cam.close()
        server.close()
        pcic.close()


def assert_flat_frame(cam: O3RCamera) -> None:
    f = cam.capture(CAPTURE_TIMEOUT_S)
    assert f.distance.shape == (H, W)
    np.testing.assert_allclose(f.distance, 0.8, atol=1e-6)  # 800 counts x 1 mm
    assert f.xyz[H // 2, W // 2, 2] == pytest.approx(0.8, abs=0.01)


NOTE_20MB = message(b"0010", b"000000001:" + b'"' * (20 * 10**6))
NOTE_10KB = message(b"0010", b'000000002:{"x": "' + b"y" * 10_000 + b'"}')
REPLY_8MB = message(b"4321", b"*" + b"r" * (8 * 10**6))
REPLY_8MB_T = message(b"1001", b"*" + b"r" * (8 * 10**6))
REPLY_SMALL = message(b"4321", b"*")
ASYNC_5MB = message(b"0001", b"000000042:" + b"\x1b[2J overheat " * 350_000)


def test_huge_notifications_are_dropped_within_the_budget() -> None:
    def script(conn: socket.socket, stop: threading.Event) -> None:
        for _ in range(10):
            conn.sendall(NOTE_20MB)
        for _ in range(300):
            conn.sendall(NOTE_10KB)

    with measured("10 x 20 MB + 300 x 10 kB notifications") as fig, streaming(script) as cam:
        stream = cam.stream
        assert stream is not None
        deadline = time.monotonic() + 10.0
        while stream.drops.counts["notification"] < 10 + 300 - 100 and time.monotonic() < deadline:
            assert_flat_frame(cam)
        assert_flat_frame(cam)
        fig.outcome = f"frames OK; dropped {dict(stream.drops.counts)}; held {stream.buffered_bytes} bytes"
        # all ten 20 MB ones, and the small ones beyond 100 held / the budget
        assert stream.drops.counts["notification"] >= 10 + 300 - 100
        assert stream.buffered_bytes <= CAP
        assert 0 < len(stream.notifications) <= 100
    assert fig.peak_bytes < CAP + 2 * MiB, fig  # 200 MB went through


def test_replies_to_unknown_tickets_are_dropped() -> None:
    def script(conn: socket.socket, stop: threading.Event) -> None:
        for _ in range(40):
            conn.sendall(REPLY_8MB)
        conn.sendall(REPLY_8MB_T)  # one of ours, unasked: only its head is kept
        for _ in range(200):
            conn.sendall(REPLY_SMALL)

    with measured("40 x 8 MB + 200 replies, unknown ticket") as fig, streaming(script) as cam:
        stream = cam.stream
        assert stream is not None
        deadline = time.monotonic() + 10.0
        while stream.drops.counts["reply to unknown ticket"] < 240 and time.monotonic() < deadline:
            assert_flat_frame(cam)
        fig.outcome = f"frames OK; dropped {dict(stream.drops.counts)}; held {stream.buffered_bytes} bytes"
        assert stream.drops.counts["reply to unknown ticket"] == 240
        assert stream.drops.bytes["reply to unknown ticket"] == 40 * (len(REPLY_8MB) - 16) + 200 * 7
        assert stream.buffered_bytes <= 3 * 64  # the heads of c, p and t replies
    assert fig.peak_bytes < CAP + 2 * MiB, fig  # 330 MB went through


def test_huge_async_error_is_one_clipped_line() -> None:
    with measured("5 MB async error") as fig, streaming(lambda conn, stop: conn.sendall(ASYNC_5MB)) as cam:
        with pytest.raises(VendorError, match=r"^o3r error 42: \\x1b\[2J overheat .*\.\.\.$") as ei:
            for _ in range(50):
                cam.capture(CAPTURE_TIMEOUT_S)
        fig.outcome = f"VendorError ({len(str(ei.value))} chars), then frames OK"
        assert len(str(ei.value)) < 250
        assert_flat_frame(cam)
    assert fig.peak_bytes < CAP + 2 * MiB, fig


def test_frame_whose_size_disagrees_with_its_tof_info_is_refused() -> None:
    with streaming(lambda conn, stop: None, frame_message((224, 172))) as cam, measured("TOF_INFO 224x172, "
                                                                                        "image 16x12") as fig:
        with pytest.raises(ProtocolError, match=r"distance image is 16x12 but its TOF_INFO says 224x172"):
            cam.capture(CAPTURE_TIMEOUT_S)
        fig.outcome = "ProtocolError on every capture"
        with pytest.raises(ProtocolError, match="TOF_INFO says 224x172"):
            cam.capture(CAPTURE_TIMEOUT_S)
    assert fig.seconds <= 2 * (CAPTURE_TIMEOUT_S + 1.0)


def test_unexpected_exception_in_the_reader_reaches_capture_typed(monkeypatch: pytest.MonkeyPatch) -> None:
    real = pcic_client.walk_chunks
    calls: list[int] = []

    def walk_once_broken(payload: Any, *, offset: int = 0) -> Any:
        calls.append(offset)
        if len(calls) == 3:
            raise ZeroDivisionError("a defect nobody foresaw")
        return real(payload, offset=offset)

    monkeypatch.setattr(pcic_client, "walk_chunks", walk_once_broken)
    with streaming(lambda conn, stop: None) as cam, measured("reader hits a ZeroDivisionError") as fig:
        with pytest.raises(DeviceError, match=r"unexpected ZeroDivisionError at stream offset \d+: "
                                              r"'a defect nobody foresaw'"):
            for _ in range(10):
                cam.capture(CAPTURE_TIMEOUT_S)
        fig.outcome = "DeviceError, then reconnected"
        stream = cam.stream
        assert stream is not None
        deadline = time.monotonic() + 3.0
        while stream.reconnects < 1 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert stream.reconnects == 1
        for _ in range(3):
            assert_flat_frame(cam)


def test_reader_that_dies_leaves_a_typed_error_for_every_call(monkeypatch: pytest.MonkeyPatch) -> None:
    def broken_connect(*args: Any, **kw: Any) -> socket.socket:
        raise RuntimeError("no sockets today")

    monkeypatch.setattr(pcic_client, "connect", broken_connect)
    server = xmlrpc_server(answering(http(xml_value(json.dumps(tree(50012))))))
    try:
        fails_to_connect("reader dies on RuntimeError", server.port, DeviceError,
                         r"O3R PCIC 127.0.0.1:50012: the reader stopped on RuntimeError: 'no sockets today'")
    finally:
        server.close()
    stream = pcic_client.PcicStream("127.0.0.1", 50012)
    with pytest.raises(DeviceError, match="reader stopped on RuntimeError"):
        stream.start(1.0)
    with pytest.raises(DeviceError, match="reader stopped on RuntimeError"):
        stream.next_frame(0.1, 0.0)


# ---------------------------------------------------------------------- the same tree read by ifm3dpy
@pytest.mark.parametrize(("patch", "pointer", "message"), BAD_VALUES[::3],
                         ids=[f"{b[1].rsplit('/', 1)[1]}:{b[2].rsplit(' ', 1)[1]}" for b in BAD_VALUES[::3]])
def test_the_ifm3dpy_backend_checks_the_tree_as_the_own_client_does(patch: dict[str, Any], pointer: str,
                                                                     message: str) -> None:
    pytest.importorskip("ifm3dpy.device", reason="ifm3dpy (the o3r-ifm3d extra) is not installed")
    from cellcal.devices.registry import default_registry

    doc = tree(50012)
    doc["ports"]["port2"].update(patch)
    server = xmlrpc_server(answering(http(xml_value(json.dumps(doc)))))
    try:
        cam = default_registry().create_camera({"backend": "o3r-ifm3d", "host": "127.0.0.1",
                                                "xmlrpc_port": server.port, "port": "port2"})
        with pytest.raises(ProtocolError) as err:
            cam.connect(timeout=3.0)
        assert str(err.value) == f"o3r-ifm3d 127.0.0.1 get(['/ports']): {pointer} {message}"
    finally:
        server.close()
