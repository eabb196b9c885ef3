"""A dashboard port that streams bytes without a line end, or says nothing, cannot hold a connect past its
timeout (issue #31): the greeting is read with a plain socket, bounded in bytes and time."""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Iterator

import pytest

from cellcal.devices.errors import DeviceConnectionError, DeviceTimeoutError, ProtocolError
from cellcal.drivers.ur.dashboard import MAX_LINE_BYTES, DashboardLink, read_greeting


@pytest.fixture
def hostile_dashboard(request: pytest.FixtureRequest) -> Iterator[int]:
    """A peer on 127.0.0.1 that, per connection, streams 'A' without end ("stream"), stays silent ("silent"),
    or greets as a UR dashboard ("greet")."""
    behaviour = request.param
    server = socket.create_server(("127.0.0.1", 0))
    stop = threading.Event()

    def serve() -> None:
        server.settimeout(0.05)
        while not stop.is_set():
            try:
                conn, _ = server.accept()
            except TimeoutError:
                continue
            with conn:
                conn.settimeout(0.05)
                try:
                    if behaviour == "greet":
                        conn.sendall(b"Connected: Universal Robots Dashboard Server\n")
                    while not stop.is_set():
                        if behaviour == "stream":
                            conn.sendall(b"A" * 1024)
                        time.sleep(0.01)
                except OSError:
                    pass

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    yield int(server.getsockname()[1])
    stop.set()
    thread.join(5)
    server.close()


@pytest.mark.parametrize("hostile_dashboard", ["stream"], indirect=True)
def test_bytes_without_a_line_end_are_refused_at_the_bound(hostile_dashboard: int) -> None:
    with pytest.raises(ProtocolError, match=f"sent {MAX_LINE_BYTES} bytes without a line end: not a UR dashboard"):
        read_greeting("127.0.0.1", hostile_dashboard, 5.0)


@pytest.mark.parametrize("hostile_dashboard", ["silent"], indirect=True)
def test_silence_ends_at_the_timeout(hostile_dashboard: int) -> None:
    started = time.monotonic()
    with pytest.raises(DeviceTimeoutError, match="no greeting line from the dashboard port"):
        read_greeting("127.0.0.1", hostile_dashboard, 0.5)
    assert time.monotonic() - started < 0.5 + 1.0  # the timeout, not a multiple of it (bound, generous)


@pytest.mark.parametrize("hostile_dashboard", ["greet"], indirect=True)
def test_a_real_greeting_is_read(hostile_dashboard: int) -> None:
    assert read_greeting("127.0.0.1", hostile_dashboard, 5.0) == "Connected: Universal Robots Dashboard Server"


@pytest.mark.parametrize("hostile_dashboard", ["stream"], indirect=True)
def test_the_link_refuses_a_streaming_peer_within_its_timeout_or_does_without_it(hostile_dashboard: int) -> None:
    pytest.importorskip("dashboard_client")
    link = DashboardLink("127.0.0.1", hostile_dashboard)
    started = time.monotonic()
    with pytest.raises(ProtocolError):
        link.open(2.0, required=True)
    assert link.open(2.0, required=False) is None and link.identity == {}
    assert time.monotonic() - started < 2 * 2.0 + 1.0


def test_a_refused_port_is_a_connection_error() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # bound, not listening: refused
        with pytest.raises(DeviceConnectionError, match="connection refused on the dashboard port"):
            read_greeting("127.0.0.1", port, 1.0)
