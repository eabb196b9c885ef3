"""A minimal Foxglove WebSocket client for tests: learn the advertised channels, subscribe, collect messages.

Written against the protocol's specification (JSON text frames for control, binary
``0x01`` frames for message data), with the ``websockets`` package's synchronous client.
"""

from __future__ import annotations

import json
import struct
import time
from dataclasses import dataclass, field
from typing import Any

#: Sub-protocols the client offers (the SDK's current one and the original).
SUBPROTOCOLS = ("foxglove.sdk.v1", "foxglove.websocket.v1")


@dataclass
class Collected:
    """What a client saw: the advertised channels by topic, and the messages per topic (log time ns, JSON)."""

    server_name: str = ""
    channels: dict[str, dict[str, Any]] = field(default_factory=dict)
    messages: dict[str, list[tuple[int, dict[str, Any]]]] = field(default_factory=dict)


class FoxgloveClient:
    """Connects to ``ws://host:port`` (use as a context manager); :meth:`subscribe_all` then :meth:`collect`."""

    def __init__(self, url: str, timeout_s: float = 5.0, subprotocols: tuple[str, ...] = SUBPROTOCOLS) -> None:
        from websockets.sync.client import connect

        connection = connect(url, subprotocols=list(subprotocols), max_size=None,  # type: ignore[arg-type]
                             open_timeout=timeout_s)
        self.ws = connection.__enter__()  # entered: websockets 17 warns about a connection used bare
        self.seen = Collected()
        self._subs: dict[int, str] = {}

    def close(self) -> None:
        self.ws.__exit__(None, None, None)

    def __enter__(self) -> FoxgloveClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _handle(self, frame: str | bytes) -> None:
        if isinstance(frame, str):
            msg = json.loads(frame)
            if msg.get("op") == "serverInfo":
                self.seen.server_name = msg.get("name", "")
            elif msg.get("op") == "advertise":
                for ch in msg["channels"]:
                    self.seen.channels[ch["topic"]] = ch
            return
        if frame[0] == 0x01:  # message data: subscription id, log time, payload
            sub_id, log_time = struct.unpack_from("<IQ", frame, 1)
            topic = self._subs.get(sub_id)
            if topic is not None:
                self.seen.messages.setdefault(topic, []).append((log_time, json.loads(frame[13:])))

    def wait_for_channels(self, topics: set[str], timeout_s: float = 5.0) -> None:
        """Read until every topic in ``topics`` is advertised (TimeoutError otherwise)."""
        deadline = time.monotonic() + timeout_s
        while not topics <= set(self.seen.channels):
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"advertised only {sorted(self.seen.channels)}")
            self._handle(self.ws.recv(timeout=left))

    def subscribe_all(self) -> None:
        """Subscribe to every advertised channel (subscription id = channel id)."""
        subs = [{"id": int(ch["id"]), "channelId": int(ch["id"])} for ch in self.seen.channels.values()]
        self._subs = {int(ch["id"]): topic for topic, ch in self.seen.channels.items()}
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

    def collect(self, until: set[str], timeout_s: float = 10.0, count: int = 1) -> Collected:
        """Read until ``count`` messages arrived on every topic in ``until`` (TimeoutError otherwise)."""
        deadline = time.monotonic() + timeout_s
        while min(len(self.seen.messages.get(t, [])) for t in until) < count:
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"messages only on {sorted(self.seen.messages)}")
            try:
                self._handle(self.ws.recv(timeout=min(left, 0.5)))
            except TimeoutError:
                continue
        return self.seen
