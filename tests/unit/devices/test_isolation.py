"""NativeHost: a library in a worker process; its crash, overrun or garbage is an error here, never our end."""

from __future__ import annotations

import logging
import os
import signal
import time
from collections.abc import Iterator

import pytest

from cellcal.devices.errors import DeviceConnectionError, DeviceTimeoutError, NativeCrashError
from cellcal.devices.isolation import InlineHost, NativeHost, RemoteObject
from cellcal.devices.isolation.protocol import MAX_MESSAGE_BYTES


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except OSError:
        return False
    return True


@pytest.fixture
def host() -> Iterator[NativeHost]:
    stops: list[str] = []
    h = NativeHost("test 127.0.0.1", library="libtest", backend="test", default_timeout_s=5.0,
                   on_crash=lambda: stops.append("stop") or "the arm was told to stop")
    h.start(10.0)
    h.stops = stops  # type: ignore[attr-defined]
    yield h
    h.close(2.0)


def test_values_come_back_by_value_objects_stay_in_the_worker(host: NativeHost) -> None:
    collections = host.module("collections")
    counts = collections.Counter("abracadabra")
    assert isinstance(counts, RemoteObject) and counts.type_name == "Counter"  # a dict subclass: stays there
    assert counts.most_common(2) == [("a", 5), ("b", 2)]  # a list of tuples: plain, travels by value
    queue = host.module("queue").SimpleQueue()              # not plain: stays there
    assert isinstance(queue, RemoteObject) and queue.type_name == "SimpleQueue"
    queue.put([1.5, 2.5, "x"])
    assert queue.qsize() == 1 and queue.get() == [1.5, 2.5, "x"]
    assert host.module("os").getpid() == host.pid != os.getpid()


def test_a_process_wide_socket_timeout_does_not_break_the_pipe() -> None:
    # xarm-python-sdk calls socket.setdefaulttimeout(1) for the whole process; sockets made after it are
    # non-blocking, and a worker reading EAGAIN took it for its parent gone (found by the full suite)
    import socket

    previous = socket.getdefaulttimeout()
    socket.setdefaulttimeout(1.0)
    try:
        h = NativeHost("test", library="libtest", backend="test")
        h.start(10.0)
        try:
            time.sleep(1.5)                                  # longer than the default timeout, idle
            assert h.module("operator").add(20, 22) == 42
        finally:
            h.close(2.0)
    finally:
        socket.setdefaulttimeout(previous)


def test_errors_keep_their_type_and_message(host: NativeHost) -> None:
    with pytest.raises(ImportError, match="No module named 'no_such_vendor_sdk'"):
        host.module("no_such_vendor_sdk")
    with pytest.raises(ValueError, match="invalid literal for int"):
        host.module("builtins").int("twelve")
    with pytest.raises(RuntimeError, match=r"^JSONDecodeError: Expecting property name"):  # not a builtin: named
        host.module("json").loads("{not json")


def test_an_overrunning_call_is_a_timeout_and_its_late_reply_is_discarded(host: NativeHost) -> None:
    remote_time = host.module("time")
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeoutError, match=r"^test 127.0.0.1: sleep in the library \(sleep\) did not finish"), \
            host.deadline(0.3, "sleep in the library"):
        remote_time.sleep(2.0)
    assert time.monotonic() - t0 < 1.5                     # the deadline, not the 2 s sleep (room for a busy machine)
    # the worker finishes the sleep, then answers the next call: its late reply is skipped, not taken for this one
    assert host.module("operator").add(2, 3) == 5
    assert host.module("operator").mul(4, 5) == 20


def test_an_abort_in_the_library_is_a_typed_error_and_the_arm_is_stopped_once(host: NativeHost) -> None:
    pid = host.pid
    assert pid is not None
    with pytest.raises(NativeCrashError) as info:
        host.module("os").abort()
    assert str(info.value) == ("test 127.0.0.1: the libtest worker process died during abort (SIGABRT, a crash in "
                               "native code); cellcal is unaffected, the device's connections are gone; the arm was "
                               "told to stop")
    assert (info.value.backend, info.value.signal_name) == ("test", "SIGABRT")
    assert isinstance(info.value, DeviceConnectionError)
    with pytest.raises(NativeCrashError, match=r"died earlier \(SIGABRT\); connect again"):
        host.module("os").getpid()
    assert host.stops == ["stop"] and not _alive(pid)  # type: ignore[attr-defined]


def test_a_segfault_is_contained(host: NativeHost) -> None:
    ctypes = host.module("ctypes")
    with pytest.raises(NativeCrashError, match=r"during string_at \(SIGSEGV, a crash in native code\)"):
        ctypes.string_at(0)                                # a read of address 0 in the worker


def test_a_worker_killed_between_calls_is_found_on_the_next_call(host: NativeHost) -> None:
    assert host.pid is not None
    os.kill(host.pid, signal.SIGKILL)
    with pytest.raises(NativeCrashError, match=r"during import os \(SIGKILL, killed from outside\)"):
        host.module("os").getpid()


def test_ctrl_c_is_not_the_workers_to_handle(host: NativeHost) -> None:
    assert host.pid is not None
    os.kill(host.pid, signal.SIGINT)                       # the terminal sends it to the whole group
    time.sleep(0.1)
    assert host.module("operator").neg(7) == -7


def test_a_reply_over_the_bound_is_refused_and_the_worker_stopped(host: NativeHost) -> None:
    with pytest.raises(DeviceConnectionError, match="worker sent an unreadable reply to mul"):
        host.module("operator").mul("x", MAX_MESSAGE_BYTES + 10)
    assert host.pid is not None
    deadline = time.monotonic() + 60.0
    while _alive(host.pid) and time.monotonic() < deadline:
        os.waitpid(host.pid, os.WNOHANG)
        time.sleep(0.02)
    assert not _alive(host.pid)


def test_close_ends_a_worker_stuck_in_a_call(host: NativeHost) -> None:
    pid = host.pid
    assert pid is not None
    with pytest.raises(DeviceTimeoutError), host.deadline(0.1, "block"):
        host.module("time").sleep(60)
    t0 = time.monotonic()
    host.close(0.5)
    assert time.monotonic() - t0 < 10.0 and not _alive(pid)  # not the 60 s of its sleep


def test_dropped_objects_are_disconnected_on_the_reaper_not_the_main_thread(host: NativeHost) -> None:
    threading = host.module("threading")
    event = threading.Event()
    queue = host.module("queue").SimpleQueue()
    host.drop(queue)                                       # no disconnect(): simply freed
    host.drop(event, disconnect=False)
    assert host.module("operator").add(1, 1) == 2         # the worker serves on


def test_the_libraries_own_output_goes_to_the_debug_log(host: NativeHost, caplog: pytest.LogCaptureFixture,
                                                         capfd: pytest.CaptureFixture[str]) -> None:
    with caplog.at_level(logging.DEBUG, logger="cellcal.devices.isolation.host"):
        os_ = host.module("os")
        os_.write(1, b"connect: Connection refused\n")    # as ur_rtde's std::cout does
        deadline = time.monotonic() + 60.0
        while not caplog.records and time.monotonic() < deadline:
            time.sleep(0.01)
    assert [r.getMessage() for r in caplog.records] == ["test 127.0.0.1: libtest: connect: Connection refused"]
    assert capfd.readouterr() == ("", "")


def test_the_inline_host_is_the_same_interface_in_this_process() -> None:
    inline = InlineHost("test", library="libtest", backend="test")
    inline.start(1.0)
    assert inline.module("os").getpid() == os.getpid()
    with pytest.raises(DeviceTimeoutError, match=r"test: nap did not finish within 0\.1 s"):
        inline.bounded(lambda: time.sleep(0.5), 0.1, "nap")
    inline.close(1.0)
