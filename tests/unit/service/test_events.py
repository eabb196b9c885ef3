"""The event bus: bounded per-subscriber queues; a slow subscriber loses the oldest events and is told."""

from __future__ import annotations

import asyncio
import threading

from cellcal.core.service.events import LOST, EventBus


def test_every_subscriber_gets_every_event_in_order() -> None:
    bus = EventBus()
    a, b = bus.subscribe(), bus.subscribe()
    for i in range(5):
        bus.publish("tick", {"i": i})
    for sub in (a, b):
        got = [sub.get(0) for _ in range(5)]
        assert [e.data["i"] for e in got if e is not None] == [0, 1, 2, 3, 4]
        assert sub.get(0) is None


def test_a_slow_subscriber_loses_the_oldest_and_is_told_how_many() -> None:
    bus = EventBus(queue_events=3)
    slow, fast = bus.subscribe(), bus.subscribe()
    for i in range(10):
        bus.publish("tick", {"i": i})
        fast_event = fast.get(0)
        assert fast_event is not None and fast_event.data["i"] == i  # a reader that keeps up loses nothing
    lost = slow.get(0)
    assert lost is not None and lost.type == LOST and lost.data["count"] == 7
    assert [e.data["i"] for e in (slow.get(0), slow.get(0), slow.get(0)) if e is not None] == [7, 8, 9]


def test_a_waiting_reader_wakes_on_publish_and_on_close() -> None:
    bus = EventBus()
    sub = bus.subscribe()
    threading.Timer(0.05, bus.publish, args=("late",)).start()
    event = sub.get(5.0)
    assert event is not None and event.type == "late"
    threading.Timer(0.05, bus.close).start()
    assert sub.get(5.0) is None and sub.closed
    assert bus.subscribers == 0 and bus.subscribe().closed


def test_an_asyncio_reader_wakes_on_a_publish_from_another_thread() -> None:
    bus = EventBus()
    sub = bus.subscribe()

    async def read() -> str | None:
        threading.Timer(0.05, bus.publish, args=("from-thread",)).start()
        event = await sub.aget(5.0)
        return None if event is None else event.type

    assert asyncio.run(read()) == "from-thread"
    assert asyncio.run(sub.aget(0.01)) is None  # nothing more: a timeout, not a hang
    sub.close()
    assert bus.subscribers == 0
