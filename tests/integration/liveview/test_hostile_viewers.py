"""Viewers that do not read, connect too often or send nonsense cannot grow the live view without bound,
hold a run past its end, or flood its output (issue #31, ADR 0039).

The hostile viewers speak raw WebSocket over a plain socket (written here, independently of the
SDK and of ``websockets``, whose client would read for them): they subscribe to every channel and
then never read a byte.
"""

from __future__ import annotations

import contextlib
import json
import logging
import socket
import time
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("foxglove")

from hostile_viewer import WAIT_S, channels, connect, frame, monitor_with_slow_viewers, send_text

from cellcal.core.liveview import LiveView
from cellcal.core.liveview.sdklog import MAX_RECORDS_PER_S
from cellcal.core.liveview.server import MAX_CLIENTS
from tests.support.ports import free_port, port_free


@pytest.mark.skipif(not Path("/proc/self/status").is_file(), reason="reads the child's memory from /proc")
def test_four_viewers_that_never_read_and_200_idle_connections_cost_bounded_memory_and_the_run_ends_on_time(
        tmp_path: Path) -> None:
    port, duration_s = free_port(), 12.0
    run = monitor_with_slow_viewers(port, duration_s)
    assert run.returncode == 0, run.err
    assert "monitor finished" in run.out
    # the run ends when --duration is over (plus its start-up and the close's bounded wait), not when the viewers go
    assert run.ended_after_s < duration_s + 15.0, run.ended_after_s
    # memory: what the second half of the run adds is small (no growth with the frames published)
    early, late = run.peaks_mb(duration_s)
    assert late - early < 20.0, run.samples  # flat at ~135 MB here; unbounded queues grew ~30 MB/s
    assert max(mb for _, mb in run.samples) < 600.0, run.samples
    assert port_free(port)


def test_more_viewers_than_the_cap_are_closed_as_they_connect_and_the_others_are_served() -> None:
    with LiveView(0) as view:
        admitted = [connect(view.port) for _ in range(MAX_CLIENTS)]
        try:
            assert all(channels(sock) for sock in admitted)
            extra = socket.create_connection(("127.0.0.1", view.port), timeout=WAIT_S)
            with extra:
                assert extra.recv(1) == b""  # closed at accept
            assert channels(_connect_after_one_leaves(admitted, view.port))
        finally:
            for sock in admitted:
                sock.close()


def _connect_after_one_leaves(admitted: list[socket.socket], port: int) -> socket.socket:
    """Close one admitted viewer; a new one is admitted once the relay has seen it leave."""
    admitted.pop().close()
    deadline = time.monotonic() + WAIT_S
    while True:
        try:
            sock = connect(port)
            admitted.append(sock)
            return sock
        except (ConnectionError, AssertionError):
            assert time.monotonic() < deadline
            time.sleep(0.05)


def test_a_thousand_unknown_channel_ids_in_one_message_make_a_bounded_number_of_log_records(
        caplog: pytest.LogCaptureFixture, capfd: pytest.CaptureFixture[str]) -> None:
    caplog.set_level(logging.INFO, logger="cellcal.liveview")
    with LiveView(0) as view:
        sock = connect(view.port)
        channels(sock)
        send_text(sock, json.dumps({"op": "subscribe",
                                     "subscriptions": [{"id": 10_000 + i, "channelId": 50_000 + i}
                                                       for i in range(1000)]}))
        # the SDK answers each unknown id with a status message (and logs it), then drops the client, whose
        # control queue (MESSAGE_BACKLOG) overflowed: read until then
        statuses = 0
        with contextlib.suppress(ConnectionError):
            while statuses < 1000:
                opcode, payload = frame(sock)
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
