"""The PCIC reader's byte budget for replies and notifications, its drop log, and the stream's port check."""

from __future__ import annotations

import logging

import pytest

from cellcal.devices.errors import ConfigError
from cellcal.drivers.o3r.client import PcicStream
from cellcal.drivers.o3r.inbox import MAX_NOTIFICATIONS, REPLY_HEAD, DropLog, Inbox

TICKETS = ("1000", "1001", "1002")


def inbox(max_bytes: int = 10_000) -> Inbox:
    return Inbox(max_bytes, TICKETS, DropLog("O3R PCIC test:1"))


def test_replies_keep_only_our_tickets_and_only_their_head() -> None:
    box = inbox()
    assert box.reply("1001", b"*" + b"x" * 10_000, 10_007)
    assert box.replies["1001"] == (1, b"*" + b"x" * (REPLY_HEAD - 1))
    assert not box.reply("4321", b"*", 7)
    assert box.replies.keys() == {"1001"} and box.reply_counter == 1
    assert box.drops.counts["reply to unknown ticket"] == 1 and box.drops.bytes["reply to unknown ticket"] == 7
    assert box.used_bytes == REPLY_HEAD


def test_notifications_stay_within_the_budget_oldest_dropped_first() -> None:
    box = inbox(10_000)
    budget = 10_000 - REPLY_HEAD * len(TICKETS)  # 9808 bytes for notifications
    for i in range(30):
        box.notification(f"{i:09d}", "n", 1000)
    held = box.notifications
    assert len(held) == budget // 1000 == 9
    assert [int(i) for i, _ in held] == list(range(21, 30))  # the newest nine
    assert box.drops.counts["notification"] == 21
    assert box.used_bytes <= 10_000
    box.notification("000000099", "big", budget + 1)  # larger than the whole budget: dropped, nothing evicted
    assert len(box.notifications) == 9 and box.drops.counts["notification"] == 22
    assert box.take_notifications()[0][0] == "000000021"
    assert box.notifications == [] and box.used_bytes == 0


def test_notification_count_is_capped_too() -> None:
    box = inbox(1_000_000)
    for i in range(MAX_NOTIFICATIONS + 5):
        box.notification(f"{i:09d}", "{}", 10)
    assert len(box.notifications) == MAX_NOTIFICATIONS
    assert box.notifications[0][0] == f"{5:09d}"


def test_drops_are_logged_at_most_once_per_interval(caplog: pytest.LogCaptureFixture) -> None:
    drops = DropLog("O3R PCIC test:1")
    with caplog.at_level(logging.WARNING, logger="cellcal.drivers.o3r.inbox"):
        for _ in range(300):
            drops.drop("reply to unknown ticket", 8_000_000, "ticket '4321'")
    assert drops.counts["reply to unknown ticket"] == 300
    assert drops.bytes["reply to unknown ticket"] == 300 * 8_000_000
    assert [r.getMessage() for r in caplog.records] == [
        "O3R PCIC test:1: dropped reply to unknown ticket of 8000000 bytes: ticket '4321'"]


@pytest.mark.parametrize("port", [0, 65536, -1, True, 1e308, "50010", None])
def test_stream_refuses_a_port_that_is_not_one(port: object) -> None:
    with pytest.raises(ConfigError, match=r"O3R PCIC port must be an integer in 1\.\.65535, got"):
        PcicStream("127.0.0.1", port)  # type: ignore[arg-type]
