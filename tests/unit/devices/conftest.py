"""Fixtures of the native-isolation host's pinned tests (test_isolation_host_pinned.py and
test_isolation_failures_pinned.py): a started host for "ur 10.0.0.2" over ur_rtde, and one whose
on_crash hook records its calls. test_isolation.py has a ``host`` of its own, which takes precedence there.
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from test_isolation_host_pinned import _new

from cellcal.devices.isolation import NativeHost


@pytest.fixture
def host() -> Iterator[NativeHost]:
    h = _new()
    h.start(10.0)
    yield h
    h.close(2.0)


@pytest.fixture
def stops() -> list[str]:
    return []


@pytest.fixture
def guarded(stops: list[str]) -> Iterator[NativeHost]:
    """A host whose on_crash hook records its calls."""
    h = _new(on_crash=lambda: stops.append("stop") or "the arm was told to stop")
    h.start(10.0)
    yield h
    h.close(2.0)
