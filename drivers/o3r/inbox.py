"""What the PCIC reader keeps besides frames: command replies and notifications, within one byte budget.

Replies are kept only for the tickets the client sends (their first bytes: the reply code is
all a caller reads); notifications FIFO, oldest dropped first; a message nobody waits for is
dropped, counted and logged (rate-limited). Not thread-safe: the stream's lock guards it.
"""

from __future__ import annotations

import collections
import logging
import time

log = logging.getLogger(__name__)

#: Bytes of a command reply that are kept (the reply code and a short message).
REPLY_HEAD = 64
#: Most notifications kept, whatever their size.
MAX_NOTIFICATIONS = 100
#: Shortest interval between two log lines about drops of one kind, seconds.
LOG_INTERVAL_S = 5.0


class DropLog:
    """Counts dropped messages per kind and logs them at most once per :data:`LOG_INTERVAL_S` per kind.

    Args:
        where: Names the stream in log lines, e.g. ``"O3R PCIC 10.0.0.1:50012"``.
    """

    def __init__(self, where: str) -> None:
        self.where = where
        self.counts: collections.Counter[str] = collections.Counter()
        self.bytes: collections.Counter[str] = collections.Counter()
        self._last_log: dict[str, float] = {}
        self._unlogged: collections.Counter[str] = collections.Counter()

    def drop(self, kind: str, size: int, detail: str = "") -> None:
        """Count one dropped message of ``size`` bytes and maybe log it."""
        self.counts[kind] += 1
        self.bytes[kind] += size
        self._unlogged[kind] += 1
        now = time.monotonic()
        if now - self._last_log.get(kind, -LOG_INTERVAL_S) >= LOG_INTERVAL_S:
            n = self._unlogged.pop(kind)
            self._last_log[kind] = now
            more = f" ({n} dropped since the last report, {self.counts[kind]} in all)" if n > 1 else ""
            log.warning("%s: dropped %s of %d bytes%s%s", self.where, kind, size,
                        f": {detail}" if detail else "", more)


class Inbox:
    """Command replies and notifications within ``max_bytes`` in total.

    Args:
        max_bytes: Budget for everything kept here, bytes.
        tickets: The command tickets whose replies are kept.
        drops: Where drops are counted and logged.
    """

    def __init__(self, max_bytes: int, tickets: tuple[str, ...], drops: DropLog) -> None:
        self.max_bytes = max_bytes
        self.tickets = frozenset(tickets)
        self.drops = drops
        self.replies: dict[str, tuple[int, bytes]] = {}
        self.reply_counter = 0
        self._notes: collections.deque[tuple[str, str, int]] = collections.deque()
        self._note_bytes = 0

    @property
    def used_bytes(self) -> int:
        """Bytes held now (replies and notifications)."""
        return self._note_bytes + sum(len(r[1]) for r in self.replies.values())

    @property
    def notifications(self) -> list[tuple[str, str]]:
        """Notifications held, oldest first, as (9-digit id, JSON text)."""
        return [(ident, text) for ident, text, _ in self._notes]

    def reply(self, ticket: str, content: bytes | bytearray, size: int) -> bool:
        """Keep the head of a reply to one of our tickets; False (dropped) for any other ticket."""
        if ticket not in self.tickets:
            self.drops.drop("reply to unknown ticket", size, f"ticket {ticket!r}")
            return False
        self.reply_counter += 1
        self.replies[ticket] = (self.reply_counter, bytes(content[:REPLY_HEAD]))
        return True

    def notification(self, ident: str, text: str, size: int) -> None:
        """Keep a notification taking ``size`` bytes, dropping the oldest ones to stay within budget."""
        budget = self.max_bytes - REPLY_HEAD * len(self.tickets)  # the rest is reserved for replies
        if size > budget:
            self.drops.drop("notification", size, f"id {ident}, larger than the {budget}-byte budget")
            return
        while self._notes and (self._note_bytes + size > budget or len(self._notes) >= MAX_NOTIFICATIONS):
            old_id, _, old_size = self._notes.popleft()
            self._note_bytes -= old_size
            self.drops.drop("notification", old_size, f"id {old_id}, unread when the budget ran out")
        self._notes.append((ident, text, size))
        self._note_bytes += size

    def take_notifications(self) -> list[tuple[str, str]]:
        """Remove and return the notifications held, oldest first."""
        out = self.notifications
        self._notes.clear()
        self._note_bytes = 0
        return out
