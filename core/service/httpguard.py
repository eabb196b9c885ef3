"""The HTTP face's guards: a body size bound (413), a per-client token bucket (429), the bearer token (401),
and every error as a 4xx (or 500) with a JSON body ``{"error": "<one line>"}`` — never a traceback.

The size and rate guards are plain ASGI middleware in front of the application, so a refused
request costs neither a body read nor a route.
"""

from __future__ import annotations

import hmac
import json
import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Awaitable, Callable, MutableMapping
from typing import Any

__all__ = ["DEFAULT_BURST", "DEFAULT_RATE_PER_S", "MAX_BODY_BYTES", "BodyLimit", "RateLimit", "TokenBucket",
           "check_bearer", "error_body", "one_line"]

log = logging.getLogger(__name__)

#: Largest request body accepted, bytes (a batch of 100 000 pixels as JSON is about 4 MB).
MAX_BODY_BYTES = 8 << 20
#: Requests per second a client may make on average, and how many at once (the bucket's size).
DEFAULT_RATE_PER_S = 1000.0
DEFAULT_BURST = 1000
#: Clients whose buckets are kept (the least recently seen are forgotten first).
MAX_CLIENTS = 10_000
#: Longest error line sent, characters.
MAX_ERROR_CHARS = 500

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]


def one_line(text: str) -> str:
    """``text`` on one line of at most :data:`MAX_ERROR_CHARS` characters."""
    line = " ".join(str(text).split())
    return line if len(line) <= MAX_ERROR_CHARS else line[:MAX_ERROR_CHARS - 3] + "..."


def error_body(message: str) -> bytes:
    """The JSON body of an error: ``{"error": "<one line>"}``."""
    return json.dumps({"error": one_line(message)}).encode("utf-8")


async def send_error(send: Send, status: int, message: str, headers: list[tuple[bytes, bytes]] | None = None) -> None:
    """Answer a request with ``status`` and ``{"error": message}`` straight from ASGI."""
    body = error_body(message)
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
                            *(headers or [])]})
    await send({"type": "http.response.body", "body": body})


class BodyLimit:
    """Refuse bodies over ``max_bytes`` with 413: at once by their Content-Length, else when the stream passes it."""

    def __init__(self, app: ASGIApp, max_bytes: int = MAX_BODY_BYTES) -> None:
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        too_large = f"request body over {self.max_bytes} bytes"
        for name, value in scope.get("headers", ()):
            if name == b"content-length":
                try:
                    declared = int(value)
                except ValueError:
                    await send_error(send, 400, "malformed Content-Length")
                    return
                if declared > self.max_bytes:
                    await send_error(send, 413, too_large)
                    return
        seen = 0
        started = refused = False

        async def counted_receive() -> Message:
            nonlocal seen, refused
            if refused:
                return {"type": "http.disconnect"}
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > self.max_bytes:  # answered here; the application sees the client go
                    refused = True
                    if not started:
                        await send_error(send, 413, too_large)
                    return {"type": "http.disconnect"}
            return message

        async def watched_send(message: Message) -> None:
            nonlocal started
            if refused:
                return  # the 413 is the answer
            started = started or message["type"] == "http.response.start"
            await send(message)

        await self.app(scope, counted_receive, watched_send)


class TokenBucket:
    """Per-client token buckets: ``rate_per_s`` tokens a second up to ``burst``; a request takes one. Thread-safe."""

    def __init__(self, rate_per_s: float = DEFAULT_RATE_PER_S, burst: int = DEFAULT_BURST,
                 max_clients: int = MAX_CLIENTS) -> None:
        if rate_per_s <= 0 or burst < 1:
            raise ValueError("rate_per_s must be > 0 and burst >= 1")
        self.rate_per_s = rate_per_s
        self.burst = float(burst)
        self.max_clients = max_clients
        self._buckets: OrderedDict[str, tuple[float, float]] = OrderedDict()  # client -> (tokens, when)
        self._lock = threading.Lock()

    def take(self, client: str, now: float | None = None) -> float:
        """Take a token for ``client``; 0 when it had one, else the seconds until it will."""
        now = time.monotonic() if now is None else now
        with self._lock:
            tokens, when = self._buckets.pop(client, (self.burst, now))
            tokens = min(self.burst, tokens + (now - when) * self.rate_per_s)  # refilled since its last request
            wait = 0.0
            if tokens >= 1.0:
                tokens -= 1.0
            else:
                wait = (1.0 - tokens) / self.rate_per_s
            self._buckets[client] = (tokens, now)  # most recently seen last
            while len(self._buckets) > self.max_clients:
                self._buckets.popitem(last=False)
            return wait


class RateLimit:
    """Answer 429 (with Retry-After) to a client whose :class:`TokenBucket` is empty."""

    def __init__(self, app: ASGIApp, bucket: TokenBucket) -> None:
        self.app = app
        self.bucket = bucket

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http":
            client = (scope.get("client") or ("unknown", 0))[0]
            wait = self.bucket.take(str(client))
            if wait > 0:
                await send_error(send, 429, f"too many requests: at most {self.bucket.rate_per_s:g} a second "
                                 f"(bursts of {self.bucket.burst:g}) per client; retry in {wait:.3f} s",
                                 [(b"retry-after", str(max(1, round(wait + 0.5))).encode())])
                return
        await self.app(scope, receive, send)


def check_bearer(header: str | None, token: str | None) -> str | None:
    """Why a request with ``Authorization: header`` may not change state when the service's token is ``token``;
    None when it may (or no token is set)."""
    if token is None:
        return None
    if not header:
        return "this request changes state: it needs 'Authorization: Bearer <token>'"
    scheme, _, given = header.partition(" ")
    if scheme.lower() != "bearer" or not given.strip():
        return "the Authorization header must be 'Bearer <token>'"
    if not hmac.compare_digest(given.strip().encode("utf-8"), token.encode("utf-8")):
        return "wrong token"
    return None
