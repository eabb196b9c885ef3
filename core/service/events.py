"""The service's event bus: bounded per-subscriber queues, a slow subscriber loses its oldest events and is told.

Publishers (a run's worker thread, the service) never block: each subscriber has its own
queue of at most ``maxlen`` events; when it is full the oldest event is dropped and the
subscriber's next read returns an ``events_lost`` event counting what it missed, before
the events it still holds. A subscriber reads from a thread (:meth:`Subscription.get`) or
from an asyncio loop (:meth:`Subscription.aget`, e.g. the HTTP face's server-sent events).
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import threading
import time
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

__all__ = ["DEFAULT_QUEUE_EVENTS", "LOST", "Event", "EventBus", "Subscription"]

#: Events a subscriber's queue holds before the oldest are dropped.
DEFAULT_QUEUE_EVENTS = 1000
#: The type of the event that tells a subscriber how many events it lost.
LOST = "events_lost"


@dataclass(frozen=True)
class Event:
    """One thing that happened in the service.

    Attributes:
        seq: Number of the event on its bus, from 1 (an ``events_lost`` event has 0).
        type: What happened, e.g. ``run.progress``.
        time_s: When, seconds since the epoch (UTC).
        data: Its JSON-ready content.
    """

    seq: int
    type: str
    time_s: float
    data: Mapping[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """JSON form."""
        return {"seq": self.seq, "type": self.type, "time_s": self.time_s, "data": dict(self.data)}


class Subscription:
    """One subscriber's bounded queue (made by :meth:`EventBus.subscribe`; :meth:`close` it when done).

    Args:
        bus: The bus it reads.
        maxlen: Most events held; beyond, the oldest are dropped and counted.
    """

    def __init__(self, bus: EventBus, maxlen: int) -> None:
        self._bus = bus
        self._queue: deque[Event] = deque()
        self._maxlen = maxlen
        self._lost = 0
        self._closed = False
        self._cond = threading.Condition()
        self._waiters: list[tuple[asyncio.AbstractEventLoop, asyncio.Event]] = []

    @property
    def closed(self) -> bool:
        """Whether the subscription (or its bus) was closed: reads return None once it is drained."""
        return self._closed

    def _put(self, event: Event) -> None:
        with self._cond:
            if self._closed:
                return
            if len(self._queue) >= self._maxlen:
                self._queue.popleft()  # the slow subscriber loses the oldest event ...
                self._lost += 1  # ... and is told on its next read
            self._queue.append(event)
            self._cond.notify_all()
            waiters = list(self._waiters)
        self._wake(waiters)

    @staticmethod
    def _wake(waiters: list[tuple[asyncio.AbstractEventLoop, asyncio.Event]]) -> None:
        for loop, flag in waiters:
            with contextlib.suppress(RuntimeError):  # that loop is closed: nobody waits there any more
                loop.call_soon_threadsafe(flag.set)

    def _pop(self) -> Event | None:
        """The next event (an ``events_lost`` first when some were dropped), or None; under ``_cond``."""
        if self._lost:
            lost, self._lost = self._lost, 0
            return Event(0, LOST, time.time(), {"count": lost,
                                                "message": f"{lost} events were dropped: this subscriber read "
                                                           "too slowly"})
        return self._queue.popleft() if self._queue else None

    def get(self, timeout: float | None = None) -> Event | None:
        """The next event, waiting at most ``timeout`` seconds (None: until one comes or the bus closes)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            while True:
                event = self._pop()
                if event is not None or self._closed:
                    return event
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    return None
                self._cond.wait(left)

    async def aget(self, timeout: float) -> Event | None:
        """The next event from an asyncio task, waiting at most ``timeout`` seconds (None: none came, or closed)."""
        loop = asyncio.get_running_loop()
        flag = asyncio.Event()
        with self._cond:
            event = self._pop()
            if event is not None or self._closed:
                return event
            self._waiters.append((loop, flag))
        try:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(flag.wait(), timeout)
        finally:
            with self._cond:
                self._waiters.remove((loop, flag))
        with self._cond:
            return self._pop()

    def close(self) -> None:
        """Stop receiving; wakes a waiting reader. Idempotent."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()
            waiters = list(self._waiters)
        self._wake(waiters)
        self._bus._remove(self)


class EventBus:
    """Publishes events to every subscriber's bounded queue; thread-safe, never blocks a publisher.

    Args:
        queue_events: Events each subscriber's queue holds (:data:`DEFAULT_QUEUE_EVENTS`).
    """

    def __init__(self, queue_events: int = DEFAULT_QUEUE_EVENTS) -> None:
        if queue_events < 1:
            raise ValueError("queue_events must be at least 1")
        self.queue_events = queue_events
        self._subscribers: list[Subscription] = []
        self._lock = threading.Lock()
        self._seq = itertools.count(1)
        self._closed = False

    def subscribe(self) -> Subscription:
        """A new subscriber's queue, receiving every event published from now on."""
        sub = Subscription(self, self.queue_events)
        with self._lock:
            if self._closed:
                sub._closed = True
            else:
                self._subscribers.append(sub)
        return sub

    @property
    def subscribers(self) -> int:
        """How many subscriptions are open."""
        with self._lock:
            return len(self._subscribers)

    def publish(self, type_: str, data: Mapping[str, Any] | None = None) -> Event:
        """Send an event of ``type_`` with ``data`` (JSON-ready) to every subscriber; the event."""
        with self._lock:
            event = Event(next(self._seq), type_, time.time(), dict(data or {}))
            subscribers = list(self._subscribers)
        for sub in subscribers:
            sub._put(event)
        return event

    def close(self) -> None:
        """Close every subscription (their readers end); later subscriptions start closed."""
        with self._lock:
            self._closed = True
            subscribers = list(self._subscribers)
        for sub in subscribers:
            sub.close()

    def _remove(self, sub: Subscription) -> None:
        with self._lock, contextlib.suppress(ValueError):
            self._subscribers.remove(sub)
