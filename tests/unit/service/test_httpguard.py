"""The HTTP face's guards that need no server: the token bucket and the bearer check."""

from __future__ import annotations

import pytest

from cellcal.core.service.httpguard import TokenBucket, check_bearer, error_body, one_line


def test_the_bucket_allows_a_burst_then_the_rate() -> None:
    bucket = TokenBucket(rate_per_s=10.0, burst=3)
    assert [bucket.take("a", now=100.0) for _ in range(3)] == [0.0, 0.0, 0.0]
    assert bucket.take("a", now=100.0) == pytest.approx(0.1)  # empty: one token in 1/10 s
    assert bucket.take("b", now=100.0) == 0.0  # another client has its own bucket
    assert bucket.take("a", now=100.25) == 0.0  # refilled meanwhile (2.5 tokens, less the refused try's none)


def test_the_bucket_forgets_the_least_recent_clients_beyond_its_bound() -> None:
    bucket = TokenBucket(rate_per_s=1.0, burst=1, max_clients=2)
    for client in ("a", "b", "c"):
        bucket.take(client, now=0.0)
    assert bucket.take("a", now=0.0) == 0.0  # 'a' was forgotten: a full bucket again


def test_the_bearer_check() -> None:
    token = "s3cret-token-0123456789"
    assert check_bearer(None, None) is None  # no token set: nothing to check
    assert "needs 'Authorization: Bearer" in str(check_bearer(None, token))
    assert "must be 'Bearer" in str(check_bearer(f"Basic {token}", token))
    assert check_bearer("Bearer wrong-token-0123456789", token) == "wrong token"
    assert check_bearer(f"Bearer {token}", token) is None


def test_an_error_is_one_bounded_line() -> None:
    assert one_line("a\nb\r\n  c") == "a b c"
    assert len(one_line("x" * 10_000)) == 500
    assert error_body("bad\nthing") == b'{"error": "bad thing"}'
