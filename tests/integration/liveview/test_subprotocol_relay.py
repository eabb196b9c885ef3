"""The relay in front of the SDK: a client offering only ``foxglove.websocket.v1`` (Lichtblick, Foxglove
before the SDK) gets the live view; the renaming itself on handshakes written out byte for byte."""

from __future__ import annotations

import contextlib
import json
import socket
import time
from collections.abc import Iterator

import pytest

pytest.importorskip("foxglove")
pytest.importorskip("websockets")
from websockets.sync.client import connect

from cellcal.core.liveview import LiveView
from cellcal.core.liveview.subprotocol import MAX_BUFFER_BYTES, SubprotocolRelay, rename_offer, rename_reply

REQUEST = (b"GET / HTTP/1.1\r\nHost: 127.0.0.1:8765\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
           b"Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n"
           b"Sec-WebSocket-Protocol: %s\r\n\r\n")


def test_an_offer_of_the_legacy_name_alone_is_renamed_and_the_reply_renamed_back() -> None:
    renamed, legacy = rename_offer(REQUEST % b"foxglove.websocket.v1")
    assert legacy and renamed == REQUEST % b"foxglove.sdk.v1"
    # other offers are kept in their places; header names are case-insensitive
    renamed, legacy = rename_offer((REQUEST % b"x.v2, foxglove.websocket.v1").replace(b"Sec-WebSocket-Protocol",
                                                                                     b"sec-websocket-protocol"))
    assert legacy and b"sec-websocket-protocol: x.v2, foxglove.sdk.v1\r\n" in renamed
    reply = b"HTTP/1.1 101 Switching Protocols\r\nSec-WebSocket-Protocol: foxglove.sdk.v1\r\n\r\n"
    assert rename_reply(reply) == reply.replace(b"foxglove.sdk.v1", b"foxglove.websocket.v1")


@pytest.mark.parametrize("offer", [b"foxglove.sdk.v1", b"foxglove.sdk.v1, foxglove.websocket.v1", b"other.v1"])
def test_an_offer_with_the_sdk_name_or_without_either_passes_unchanged(offer: bytes) -> None:
    assert rename_offer(REQUEST % offer) == (REQUEST % offer, False)


@contextlib.contextmanager
def _relayed(max_clients: int = 16) -> Iterator[tuple[LiveView, SubprotocolRelay]]:
    with LiveView(0) as view:
        relay = SubprotocolRelay("127.0.0.1", 0, view.upstream_port, max_clients=max_clients)
        try:
            yield view, relay
        finally:
            relay.close()


@pytest.mark.parametrize("offer", [["foxglove.websocket.v1"], ["foxglove.sdk.v1"]])
def test_both_names_reach_the_sdk_through_the_relay(offer: list[str]) -> None:
    with _relayed() as (_, relay), connect(f"ws://127.0.0.1:{relay.port}", subprotocols=offer,  # type: ignore[arg-type]
                                           open_timeout=10) as ws:
        assert ws.subprotocol == offer[0]
        info = json.loads(ws.recv(timeout=10))
        assert info["op"] == "serverInfo" and info["name"] == "cellcal"
        advertised = json.loads(ws.recv(timeout=10))
        assert advertised["op"] == "advertise"
        assert {"/camera/points", "/cellcal/plane", "/tf"} <= {c["topic"] for c in advertised["channels"]}


def test_a_header_that_never_ends_and_clients_over_the_cap_are_closed() -> None:
    with _relayed(max_clients=2) as (_, relay):
        bomb = socket.create_connection(("127.0.0.1", relay.port), timeout=10)
        sent = 0
        with contextlib.suppress(OSError):  # the relay closes it once 16 KiB arrived without a blank line
            while sent < 1_000_000:
                bomb.sendall(b"x" * 4096)
                sent += 4096
                time.sleep(0.001)
        assert sent < 1_000_000
        bomb.close()
        held = [socket.create_connection(("127.0.0.1", relay.port), timeout=10) for _ in range(3)]
        held[2].settimeout(10)
        assert held[2].recv(1) == b""  # the third of at most two is closed at accept
        assert relay.refused == 1 and relay.clients == 2
        for s in held:
            s.close()


def test_a_client_that_never_reads_holds_at_most_the_relays_bound_and_does_not_slow_the_run() -> None:
    from cellcal.core.calibration.calibrator import Calibrator, build_devices
    from cellcal.core.calibration.config import load_config

    config = load_config(None)
    camera, arm = build_devices(config)
    with _relayed() as (view, relay):
        sock = socket.socket()
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # a client whose own buffers are small
        sock.connect(("127.0.0.1", relay.port))
        ws = connect(f"ws://127.0.0.1:{relay.port}", sock=sock, subprotocols=["foxglove.websocket.v1"],  # type: ignore[list-item]
                     open_timeout=10, max_queue=1, max_size=None).__enter__()  # a reader that stops at one frame
        json.loads(ws.recv(timeout=10))  # serverInfo
        channels = json.loads(ws.recv(timeout=10))["channels"]
        ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": c["id"], "channelId": c["id"]}
                                                                 for c in channels]}))
        deadline = time.monotonic() + 60
        while view.subscriptions < len(channels):  # the server registers each subscription
            assert time.monotonic() < deadline, view.subscriptions
            time.sleep(0.01)
        document = Calibrator(config, camera, arm, observer=view.observe_pose(config.mount.pose())).run()
        points = view.message_counts["/camera/points"]
        assert points == len(document["poses"]) == 3  # every scene published, none waited for the client
        for _ in range(10):
            view.republish()
        (pair,) = {id(p): p for p in relay._pairs.values()}.values()
        deadline = time.monotonic() + 60
        while len(pair.to_client) < MAX_BUFFER_BYTES:  # the relay thread reads from the SDK until its bound
            assert time.monotonic() < deadline, len(pair.to_client)
            time.sleep(0.01)
        time.sleep(0.3)  # a relay that read past its bound would do so now
        assert pair.stage == "open" and pair.legacy
        # each cloud is n_points x 16 bytes: more than the bound was sent toward the client ...
        assert view.message_counts["/camera/points"] == 13
        assert 13 * document["poses"][0]["full_frame"]["n_points"] * 16 > 10 * MAX_BUFFER_BYTES
        # ... and the relay holds at most its bound (plus the one read that filled it)
        assert MAX_BUFFER_BYTES <= len(pair.to_client) <= MAX_BUFFER_BYTES + 64 * 1024
        ws.__exit__(None, None, None)
