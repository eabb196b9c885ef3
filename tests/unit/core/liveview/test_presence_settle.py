"""``--viz-wait`` starts the run once the viewer has finished subscribing, not at its first channel."""

from __future__ import annotations

import time

import pytest

from cellcal.core.liveview import presence


class Subscribing:
    """A server a viewer subscribes to channel by channel: one more subscription each time it is looked at."""

    def __init__(self, channels: int, stop_after: int | None = None) -> None:
        self.channels, self.stop_after, self.count = channels, stop_after, 1

    @property
    def subscriptions(self) -> int:
        if self.count < self.channels and (self.stop_after is None or self.count < self.stop_after):
            self.count += 1
        return self.count

    def all_subscribed(self) -> bool:
        return self.count >= self.channels

    def has_subscribers(self) -> bool:
        return True


def test_the_wait_lasts_until_every_channel_is_subscribed() -> None:
    view = Subscribing(channels=4)
    assert presence.wait_for_viewer(view, timeout_s=30.0)  # type: ignore[arg-type]
    assert view.all_subscribed() and view.count == 4


def test_a_viewer_that_subscribes_to_some_channels_only_starts_the_run_once_it_is_quiet() -> None:
    view = Subscribing(channels=4, stop_after=2)  # a viewer with a panel for two of the four channels
    t0 = time.monotonic()
    assert presence.wait_for_viewer(view, timeout_s=30.0)  # type: ignore[arg-type]
    took = time.monotonic() - t0
    assert view.count == 2 and not view.all_subscribed()
    assert presence.SETTLE_S <= took < presence.MAX_SETTLE_S + 5.0  # quiet for SETTLE_S; never past the bound


def test_settle_is_bounded(monkeypatch: pytest.MonkeyPatch) -> None:
    """A viewer that keeps subscribing for ever (a new count at every look) is waited for at most MAX_SETTLE_S."""
    monkeypatch.setattr(presence, "MAX_SETTLE_S", 0.3)
    view = Subscribing(channels=10**9)
    t0 = time.monotonic()
    assert presence.wait_for_viewer(view, timeout_s=30.0)  # type: ignore[arg-type]
    assert 0.3 <= time.monotonic() - t0 < 10.0 and not view.all_subscribed()
