"""Waiting for a viewer before a run, and serving the last scene for a while after it (ADR 0035)."""

from __future__ import annotations

import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager

from cellcal.core.console import say
from cellcal.core.liveview.server import LiveView, open_live_view

__all__ = ["POLL_S", "linger", "live_view_session", "wait_for_viewer"]

#: How often the waits look at the server's subscriptions, s.
POLL_S = 0.05
#: A viewer's subscriptions count as complete after this long without a new one, s (or when every channel has one).
SETTLE_S = 0.5
#: Longest wait for a viewer's subscriptions to settle, s.
MAX_SETTLE_S = 5.0


def _say(text: str) -> None:
    say(f"live view: {text}")


def wait_for_viewer(view: LiveView, timeout_s: float) -> bool:
    """Wait until a client subscribes to a channel, at most ``timeout_s``; say on stderr what happened.

    A connected client that subscribes to nothing receives nothing, so a subscription, not
    a connection, is what ends the wait. Ctrl-C (KeyboardInterrupt) passes through.

    Returns:
        Whether a viewer subscribed in time (without one, the run starts anyway).
    """
    _say(f"waiting up to {timeout_s:g} s for a viewer to subscribe (Ctrl-C to stop)")
    deadline = time.monotonic() + timeout_s
    while not view.has_subscribers():
        left = deadline - time.monotonic()
        if left <= 0:
            _say(f"no viewer after {timeout_s:g} s; starting without one")
            return False
        time.sleep(min(POLL_S, left))
    _settle(view)
    _say("a viewer subscribed; starting")
    return True


def _settle(view: LiveView) -> None:
    """Let a viewer finish subscribing: until every channel is subscribed, or no new subscription came for
    :data:`SETTLE_S`, at most :data:`MAX_SETTLE_S` (a viewer subscribes channel by channel; the run's first
    scenes must not go out between its first subscription and its last)."""
    settle_end = time.monotonic() + MAX_SETTLE_S
    count, quiet_since = view.subscriptions, time.monotonic()
    while not view.all_subscribed() and time.monotonic() < settle_end:
        if view.subscriptions != count:
            count, quiet_since = view.subscriptions, time.monotonic()
        elif time.monotonic() - quiet_since >= SETTLE_S:
            return
        time.sleep(POLL_S)


def linger(view: LiveView, seconds: float) -> None:
    """Keep serving for ``seconds`` after the run: each new subscription is sent the last scenes again.

    Ctrl-C (KeyboardInterrupt) passes through; the caller's exit status is then 130.
    """
    if seconds <= 0:
        return
    _say(f"serving the last scene for {seconds:g} s more (Ctrl-C to stop)")
    deadline = time.monotonic() + seconds
    seen = view.subscriptions
    while (left := deadline - time.monotonic()) > 0:
        time.sleep(min(POLL_S, left))
        if view.subscriptions != seen:  # a client subscribed since the last look: show it the last scenes
            seen = view.subscriptions
            view.republish()


@contextmanager
def live_view_session(port: int | None, *, drift: bool = False, track: bool = False, wait_s: float | None = None,
                      cameras: Sequence[str] = ()) -> Iterator[LiveView | None]:
    """The live view of ``--viz-port`` for the block (None: no live view), stopped when the block ends.

    Args:
        port: ``--viz-port``, or None.
        drift: Also advertise the drift channel (the monitor).
        track: Also advertise the track channel (``cellcal track``).
        wait_s: ``--viz-wait``: first wait (at most this long) for a viewer to subscribe.
        cameras: A cell's several cameras (each its own topics: :class:`LiveView`); empty: one camera.

    Raises:
        ConfigError: If foxglove-sdk is not installed or the port cannot be listened on.
    """
    view = open_live_view(port, drift=drift, track=track, cameras=cameras)
    if view is None:
        yield None
        return
    with view:
        if wait_s:
            wait_for_viewer(view, wait_s)
        yield view
