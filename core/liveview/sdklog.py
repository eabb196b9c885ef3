"""The SDK's own log records (e.g. a failed client handshake) as cellcal log records at INFO at most (ADR 0035)."""

from __future__ import annotations

import logging

__all__ = ["LOGGER", "route_sdk_logging"]

#: Where the live view logs, the SDK's records included.
LOGGER = logging.getLogger("cellcal.liveview")
#: The SDK logs through Python logging under this logger (``foxglove.websocket.server`` and others).
SDK_LOGGER = "foxglove"
#: Added to a failed handshake: the SDK speaks only ``foxglove.sdk.v1`` (ADR 0035).
HANDSHAKE_HINT = ("(a client must offer the WebSocket subprotocol 'foxglove.sdk.v1'; one offering only "
                  "'foxglove.websocket.v1', such as an older Foxglove Studio, is refused by foxglove-sdk)")


class _Reroute(logging.Handler):
    """Re-logs each SDK record on :data:`LOGGER`, at INFO at most, naming the SDK logger it came from."""

    def emit(self, record: logging.LogRecord) -> None:
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
