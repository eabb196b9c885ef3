"""ur_rtde's crash is contained: the ``ur`` backend's worker process dies, cellcal says so in one typed line.

Two ways in: the worker is killed with SIGSEGV in the middle of a move (as the segfault in
ur_rtde's teardown did), and the controller sends an RTDE message whose size field (1) is
smaller than its header, on which ur_rtde's own receive thread throws ``std::length_error``
and aborts its process. Either way the caller gets a ``NativeCrashError`` (a
``DeviceConnectionError``) naming the backend and the signal, the arm is told to stop over
the dashboard's plain socket, and the driver connects again with a new worker.
"""

from __future__ import annotations

import contextlib
import os
import signal
import struct
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest
from ur_rig import HOME, once_moving, wait_until

from cellcal.devices.errors import CellcalError, DeviceConnectionError, NativeCrashError
from cellcal.devices.pose import Pose
from cellcal.drivers.ur.arm import URArm
from cellcal.sims.ur.process import UREmulatorProcess

pytest.importorskip("rtde_control")  # the ur extra

#: An RTDE header claiming a whole message of 1 byte (less than the 3-byte header itself), type 'U'.
SHORT_SIZE_MESSAGE = struct.pack(">HB", 1, ord("U"))


@pytest.fixture
def arm(emu: UREmulatorProcess) -> Iterator[URArm]:
    arm = URArm.from_config({"host": emu.host, "timeout_s": 2.0, "stale_after_s": 0.2, "poll_interval_s": 0.005})
    arm.connect(timeout=10.0)
    yield arm
    arm.close()


def _pid_gone(pid: int, within_s: float = 60.0) -> bool:
    deadline = time.monotonic() + within_s
    while time.monotonic() < deadline:
        try:
            os.kill(pid, 0)
        except OSError:
            return True
        time.sleep(0.02)
    return False


def _crash_during_a_move(call: Callable[[], Any], pid: int, emu: UREmulatorProcess) -> NativeCrashError:
    """``call()`` (a move), the worker ``pid`` sent SIGSEGV as soon as the controller reports the arm moving."""
    done = threading.Event()

    def crash_once_moving() -> None:
        deadline = time.monotonic() + 60.0
        while not done.is_set() and time.monotonic() < deadline:
            if emu.snapshot()["moving"]:
                os.kill(pid, signal.SIGSEGV)
                return
            time.sleep(0.005)

    crasher = threading.Thread(target=crash_once_moving, name="crasher")
    crasher.start()
    try:
        with pytest.raises(NativeCrashError) as info:
            call()
    finally:
        done.set()
        crasher.join(60.0)
    return info.value


def test_a_segfault_during_a_move_is_one_typed_error_and_the_arm_is_stopped(emu: UREmulatorProcess,
                                                                           arm: URArm) -> None:
    pid = arm._host.pid
    assert pid is not None and pid != os.getpid()
    start = arm.get_pose()
    far = Pose(start.rotation, start.translation + np.array([0.0, 0.0, -0.15]))
    emu.call("set_time_scale", time_scale=1.0)                # real time: 0.15 m at 0.05 m/s is 3 s
    error = _crash_during_a_move(lambda: arm.move_linear(far, speed=0.05, acceleration=0.5, timeout=10.0), pid, emu)
    message = str(error)
    assert message.startswith(f"ur {emu.host}: the ur_rtde worker process died during ")
    assert "(SIGSEGV, a crash in native code); cellcal is unaffected, the device's connections are gone; " \
           "the arm was told to stop (dashboard 'stop', port 29999)" in message
    assert isinstance(error, DeviceConnectionError) and (error.backend, error.signal_name) == ("ur", "SIGSEGV")
    assert "stop" in emu.snapshot()["dashboard_commands"]
    wait_until(lambda: not emu.snapshot()["moving"])          # the controller stopped the arm
    assert _pid_gone(pid)
    with pytest.raises(NativeCrashError, match="died earlier"):
        arm.get_pose()                                          # no call pretends the link is still there
    arm.close()
    arm.connect(timeout=10.0)                                   # a new worker, the same arm
    assert arm._host.pid not in (None, pid)
    assert arm.get_pose().distance_to(HOME) < 0.2


def test_an_rtde_size_field_smaller_than_its_header_aborts_the_worker_not_cellcal(emu: UREmulatorProcess,
                                                                               arm: URArm) -> None:
    pid = arm._host.pid
    assert pid is not None
    arm.get_pose()
    assert emu.call("send_raw_rtde", data_hex=SHORT_SIZE_MESSAGE.hex(), target="all") >= 1
    deadline = time.monotonic() + 60.0
    with pytest.raises(NativeCrashError) as info:
        while time.monotonic() < deadline:                      # ur_rtde's thread aborts when it reads it
            arm.get_pose()
            time.sleep(0.01)
    assert info.value.signal_name == "SIGABRT" and "(SIGABRT, a crash in native code)" in str(info.value)
    assert _pid_gone(pid)


@pytest.mark.parametrize("run", range(4))
def test_a_controller_resetting_every_link_after_a_move_then_accepting_again_never_takes_cellcal_down(
        emu: UREmulatorProcess, arm: URArm, run: int) -> None:
    # the case that segfaulted 4 runs of 4 while a background thread disconnected the stale receive interface
    emu.call("set_time_scale", time_scale=1.0)
    before = emu.snapshot()["moves_started"]
    start = arm.get_pose()
    target = Pose(start.rotation, start.translation + np.array([0.0, -0.1, 0.0]))
    injector = once_moving(emu, lambda: emu.call("drop_connections", refuse_s=0.0))   # during the 1 s move
    try:
        with pytest.raises(CellcalError):       # typed: a lost contact, a crash of the worker: never ours
            arm.move_linear(target, speed=0.1, acceleration=1.0, timeout=3.0)
    finally:
        injector.join()
    assert emu.snapshot()["moves_started"] - before <= 1          # never a second move
    for _ in range(3):                                             # later calls: typed errors or answers
        with contextlib.suppress(CellcalError):
            arm.get_pose(timeout=1.0)
    arm.close()
    arm.connect(timeout=10.0)                                      # and the cell can go on
    assert arm.get_pose().distance_to(start) < 0.2
