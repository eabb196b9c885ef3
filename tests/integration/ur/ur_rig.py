"""Constants and helpers of the UR integration tests (fixtures live in this folder's conftest.py)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import pytest

from cellcal.devices.pose import Pose
from cellcal.sims.ur.process import UREmulatorProcess

#: Where each test starts: flange pointing down, 0.4 m out, 0.45 m up.
HOME = Pose.from_xyz_rpy([0.40, 0.0, 0.45], [3.141592653589793, 0.0, 0.0])
#: Wall seconds per simulated second in the tests (a 2 cm move at 0.25 m/s takes ~10 ms).
TIME_SCALE = 0.1


def once_moving(emu: UREmulatorProcess, fn: Callable[[], object]) -> threading.Thread:
    """Run ``fn`` in a thread as soon as the controller reports the arm moving (a fault that lands while the
    driver waits for a move), however long the move takes to start on a loaded machine; join the thread."""

    def inject() -> None:
        deadline = time.monotonic() + 60.0
        while not emu.snapshot()["moving"] and time.monotonic() < deadline:
            time.sleep(0.005)
        fn()

    thread = threading.Thread(target=inject, name="fault-injector")
    thread.start()
    return thread


def wait_until(predicate: Callable[[], object], timeout: float = 60.0, what: str = "condition") -> None:
    """Poll ``predicate()`` every 5 ms until true; fail the test after ``timeout`` seconds (generous: what is
    waited for comes in milliseconds, later only on a loaded machine)."""
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() >= deadline:
            pytest.fail(f"{what} not reached within {timeout} s")
        time.sleep(0.005)
