"""One UR emulator process for the UR integration tests, reset before each test, and a leak check.

The emulator runs as a child process (``python -m cellcal.sims.ur --control``): ur_rtde's
constructors hold the GIL, so an emulator thread in this interpreter could not answer them.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import pytest
from leaks import open_fds
from ur_rig import HOME, TIME_SCALE

from cellcal.devices.geometry.vendor_poses import pose_to_ur
from cellcal.sims.ur.process import UREmulatorProcess


@pytest.fixture(scope="session")
def emulator_process() -> Iterator[UREmulatorProcess]:
    emu = UREmulatorProcess("auto", arm_config={"time_scale": TIME_SCALE}, unlock_delay_s=0.0)
    emu.start()
    yield emu
    emu.close()
    assert not emu.running


@pytest.fixture
def emu(emulator_process: UREmulatorProcess) -> UREmulatorProcess:
    """The shared emulator, healthy, with the arm at rest at :data:`HOME`."""
    emulator_process.call("reset")
    emulator_process.call("set_time_scale", time_scale=TIME_SCALE)
    emulator_process.call("set_unlock_delay", delay_s=0.0)
    deadline = time.monotonic() + 60.0
    while emulator_process.snapshot()["moving"] and time.monotonic() < deadline:
        time.sleep(0.01)
    emulator_process.call("set_flange_pose", pose=[float(v) for v in pose_to_ur(HOME)])
    return emulator_process


@pytest.fixture
def no_leaks() -> Iterator[None]:
    """The test leaves no Python thread and no file descriptor behind."""
    threads = set(threading.enumerate())
    fds = open_fds()
    yield
    deadline = time.monotonic() + 30.0
    extra = [t for t in threading.enumerate() if t not in threads]
    for t in extra:
        t.join(max(0.0, deadline - time.monotonic()))
    alive = [t.name for t in extra if t.is_alive()]
    assert not alive, f"threads left running: {alive}"
    leaked = open_fds() - fds
    assert not leaked, f"file descriptors left open: {sorted(leaked)}"

