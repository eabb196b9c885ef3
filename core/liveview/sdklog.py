"""The SDK's own log records (e.g. a failed client handshake) as cellcal log records at INFO at most, rate-limited
(ADR 0035, ADR 0039)."""

from __future__ import annotations

import logging
import threading
import time

__all__ = ["LOGGER", "flush_sdk_log", "route_sdk_logging"]

#: Where the live view logs, the SDK's records included.
LOGGER = logging.getLogger("cellcal.liveview")
#: The SDK logs through Python logging under this logger (``foxglove.websocket.server`` and others).
SDK_LOGGER = "foxglove"
#: Added to a failed handshake: the live view admits either name of the protocol (ADR 0035).
HANDSHAKE_HINT = ("(a client must offer the WebSocket subprotocol 'foxglove.sdk.v1' or its earlier name "
                  "'foxglove.websocket.v1')")
#: Most SDK records re-logged per second; the rest are counted and summed up in one record (ADR 0039).
MAX_RECORDS_PER_S = 10


class _Reroute(logging.Handler):
    """Re-logs each SDK record on :data:`LOGGER`, at INFO at most, naming the SDK logger it came from.

    At most :data:`MAX_RECORDS_PER_S` records a second: a client sending 1000 bad requests in one
    message makes 10 records and one "N more ... suppressed" record, not 1000.
    """

    def __init__(self) -> None:
        super().__init__()
        self._window_start = -1.0  # monotonic s at which the current one-second window opened
        self._in_window = 0
        self._suppressed = 0
        self._guard = threading.Lock()  # the SDK logs from its own threads

    def flush(self) -> None:
        """Log how many records were suppressed since the last such record (if any)."""
        with self._guard:
            suppressed, self._suppressed = self._suppressed, 0
        if suppressed:
            LOGGER.info("foxglove: %d more records from the live view's server suppressed", suppressed)

    def emit(self, record: logging.LogRecord) -> None:
        now = time.monotonic()
        if now - self._window_start >= 1.0:  # a new window: say first what the last one dropped
            self.flush()
        with self._guard:
            if now - self._window_start >= 1.0:
                self._window_start, self._in_window = now, 0
            if self._in_window >= MAX_RECORDS_PER_S:
                self._suppressed += 1
                return
            self._in_window += 1
        message = record.getMessage()
        if "handshake" in message:
            message = f"{message} {HANDSHAKE_HINT}"
        LOGGER.log(min(record.levelno, logging.INFO), "%s: %s", record.name, message)


def route_sdk_logging() -> None:
    """Send the SDK's records to :data:`LOGGER` instead of the process's handlers. Idempotent.

    Without this, Python's last-resort handler prints the SDK's warnings and errors (a
    viewer's failed handshake) into the run's stderr; now they are log records a caller
    can enable (``logging.basicConfig(level=logging.INFO)``).
    """
    sdk = logging.getLogger(SDK_LOGGER)
    if not any(isinstance(h, _Reroute) for h in sdk.handlers):
        sdk.addHandler(_Reroute())
    sdk.propagate = False


def flush_sdk_log() -> None:
    """Log the count of SDK records suppressed and not yet reported (the live view calls this as it closes)."""
    for handler in logging.getLogger(SDK_LOGGER).handlers:
        if isinstance(handler, _Reroute):
            handler.flush()
