"""Pinned behaviour of the native-isolation host (issue #32): a worker's life cycle (started and closed in order it
leaves no process, thread or descriptor; a start that fails, hangs or exits is reported and cleaned up), proxies
and values (requests and replies at their exact size bound, the texts a user reads), and the library's own output
logged a bounded line at a time.

The helpers here (a host for "ur 10.0.0.2" over ur_rtde, the probe module made in the worker, the process and
descriptor checks) are imported by test_isolation_failures_pinned.py and this folder's conftest.py (the fixtures).
"""

from __future__ import annotations

import ctypes
import logging
import os
import pickle
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from cellcal.devices.errors import DeviceConnectionError, DeviceError, DeviceTimeoutError, NativeCrashError
from cellcal.devices.isolation import NativeHost, RemoteModule, RemoteObject
from cellcal.devices.isolation import protocol as p
from cellcal.devices.isolation.host import MAX_OUTPUT_LINE

# ---------------------------------------------------------------- host: helpers
#: A module made in the worker: devices whose disconnect() and destruction are recorded (disconnect with its thread),
#: a slow constructor, and a tuple of a class the parent cannot import.
PROBE = """
import collections, sys, threading, time, types
probe = types.ModuleType("probe")
probe.events = []

class Device:
    def __init__(self, tag, delay_s=0.0):
        time.sleep(delay_s)
        self.tag = tag

    def disconnect(self):
        probe.events.append(("disconnect", self.tag, threading.current_thread().name))

    def __del__(self):
        probe.events.append(("freed", self.tag))

def log():
    return list(probe.events)

probe.Device, probe.log = Device, log
probe.Point = collections.namedtuple("Point", "x y", module="probe")
sys.modules["probe"] = probe
"""
NAME, LIBRARY = "ur 10.0.0.2", "ur_rtde"
GONE = "cellcal is unaffected, the device's connections are gone"


def _new(**kwargs: Any) -> NativeHost:
    return NativeHost(NAME, library=LIBRARY, backend="ur", **kwargs)


def _probe(host: NativeHost) -> Any:
    host.module("builtins").exec(PROBE, {})
    return host.module("probe")


def _fds() -> set[str]:
    return set(os.listdir("/proc/self/fd"))


def _output_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == f"{NAME}: {LIBRARY} output"]


def _state(pid: int) -> str:
    """The one-letter state of process ``pid`` ("Z": a zombie), or "" once it is gone (reaped)."""
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii") as f:
            return f.read().rsplit(")", 1)[1].split()[0]
    except FileNotFoundError:
        return ""


def _closed(pid: int) -> bool:
    """Whether process ``pid`` has ended and let go of its descriptors (its last thread gone, not only the first)."""
    try:
        return _state(pid) in ("Z", "") and not os.listdir(f"/proc/{pid}/fd")
    except OSError:
        return True


def _soon(predicate: Callable[[], bool], timeout_s: float = 60.0) -> bool:
    """Whether ``predicate()`` holds within ``timeout_s`` s (polled)."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


def _filling(size: Callable[[int], int]) -> int:
    """The ``n`` for which the message ``size(n)`` is exactly :data:`MAX_MESSAGE_BYTES` (pickle adds a header)."""
    n = p.MAX_MESSAGE_BYTES - 100
    n += p.MAX_MESSAGE_BYTES - size(n)
    assert (size(n), size(n + 1)) == (p.MAX_MESSAGE_BYTES, p.MAX_MESSAGE_BYTES + 1)
    return n


def _fake_python(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, body: str) -> None:
    """Make the worker command a shell script (``sys.executable`` is what NativeHost starts)."""
    script = tmp_path / "python"
    script.write_text(f"#!/bin/sh\n{body}\n", encoding="ascii")
    script.chmod(0o755)
    monkeypatch.setattr(sys, "executable", str(script))


# ---------------------------------------------------------------- host: life cycle
def test_a_worker_started_and_closed_in_order_leaves_no_process_thread_or_descriptor(
        caplog: pytest.LogCaptureFixture) -> None:
    fds = _fds()
    h = _new()
    assert h.pid is None and h.calls == 0 and h.isolated is True
    h.start(10.0)
    pid, proc = h.pid, h._proc
    assert pid is not None and proc is not None and pid != os.getpid() and _state(pid) in ("R", "S")
    (thread,) = _output_threads()
    assert thread.daemon and thread.is_alive()
    assert h.calls == 0                                   # the ready message is not a call
    t0 = time.monotonic()
    with caplog.at_level(logging.DEBUG, logger="cellcal.devices.isolation.host"):
        h.close(3.0)
    assert time.monotonic() - t0 < 3.0                   # told to close: not waited out, not killed
    assert proc.returncode == 0 and not caplog.records
    assert h.pid is None and _state(pid) == ""            # reaped
    thread.join(2.0)
    assert not thread.is_alive() and _fds() == fds        # the socket and the output pipe are closed
    h.close()                                             # twice: nothing
    with pytest.raises(DeviceConnectionError) as info:
        h.module("os")
    assert str(info.value) == "ur 10.0.0.2: the ur_rtde worker process is not running"
    assert type(info.value) is DeviceConnectionError


def test_a_call_before_start_says_the_worker_is_not_running() -> None:
    with pytest.raises(DeviceConnectionError, match=r"^ur 10.0.0.2: the ur_rtde worker process is not running$"):
        _new().module("os")


def test_a_worker_that_cannot_be_started_is_a_connection_error_and_leaks_no_descriptor(
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(sys, "executable", "/nonexistent/python3")
    fds = _fds()
    h = _new()
    with pytest.raises(DeviceConnectionError) as info:
        h.start(5.0)
    assert str(info.value) == ("ur 10.0.0.2: cannot start the ur_rtde worker process: [Errno 2] No such file or "
                               "directory: '/nonexistent/python3'")
    assert type(info.value) is DeviceConnectionError and info.value.__suppress_context__
    assert h.pid is None and _fds() == fds


def test_a_worker_that_never_answers_times_out_at_start_and_close_kills_it(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    _fake_python(tmp_path, monkeypatch, "exec sleep 30")
    fds = _fds()
    h = _new(default_timeout_s=10.0)
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeoutError) as info:
        h.start(0.3)
    assert 0.3 <= time.monotonic() - t0 < 5.0             # start's own timeout, not the default 10 s
    assert str(info.value) == "ur 10.0.0.2: start the ur_rtde worker process did not finish within 0.3 s"
    pid = h.pid
    assert pid is not None and _state(pid) in ("R", "S")
    t0 = time.monotonic()
    with caplog.at_level(logging.WARNING, logger="cellcal.devices.isolation.host"):
        h.close(0.3)
    assert 0.3 <= time.monotonic() - t0 < 5.0             # killed after 0.3 s, not its 30 s of sleep
    assert [r.getMessage() for r in caplog.records] == ["ur 10.0.0.2: the ur_rtde worker did not exit within 0.3 s; "
                                                        "killed"]
    assert _state(pid) == ""                              # killed and reaped
    for thread in _output_threads():
        thread.join(2.0)
    assert _fds() == fds


def test_a_worker_that_exits_at_start_is_a_crash_naming_its_status(tmp_path: Path,
                                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    _fake_python(tmp_path, monkeypatch, "exit 3")
    h = _new()
    try:
        with pytest.raises(NativeCrashError) as info:
            h.start(5.0)
        assert str(info.value) == (f"ur 10.0.0.2: the ur_rtde worker process died during start the ur_rtde worker "
                                   f"process (exit status 3); {GONE}")
    finally:
        h.close(1.0)


def test_the_worker_reads_nothing_from_our_terminal_and_holds_none_of_our_descriptors() -> None:
    read_end, write_end = os.pipe()                       # our standard input, for the time of the start
    saved = os.dup(0)
    os.dup2(read_end, 0)
    host = _new()
    try:
        host.start(10.0)
    finally:
        os.dup2(saved, 0)
        for fd in (saved, read_end, write_end):
            os.close(fd)
    try:
        _check_the_workers_descriptors(host)
    finally:
        host.close(1.0)


def _check_the_workers_descriptors(host: NativeHost) -> None:
    os_ = host.module("os")
    assert os_.readlink("/proc/self/fd/0") == os.devnull
    assert os_.read(0, 10) == b""
    # 0, 1, 2, the socket to us, and the descriptor listdir itself opens
    assert len(os_.listdir("/proc/self/fd")) == 5


# ---------------------------------------------------------------- host: proxies and values
def test_remote_objects_are_proxies_named_by_type_handle_and_library(host: NativeHost) -> None:
    queue = host.module("queue")
    assert type(queue) is RemoteModule and queue.type_name == "module"
    assert repr(queue) == "<module #1 in the ur_rtde worker>"
    fifo = queue.SimpleQueue()
    assert type(fifo) is RemoteObject and repr(fifo) == "<SimpleQueue #2 in the ur_rtde worker>"
    assert fifo.put.__name__ == "put" and fifo._private.__name__ == "_private"
    with pytest.raises(AttributeError) as info:
        fifo.__len__  # noqa: B018 (the attribute access is the test)
    assert info.value.args == ("__len__",)
    assert not hasattr(fifo, "__array__")                 # numpy and friends see a plain object
    assert host.calls == 2
    fifo.put((1, "two", 3.0))
    assert fifo.get() == (1, "two", 3.0) and host.calls == 4


def test_importing_something_that_is_not_a_module_is_an_import_error(host: NativeHost) -> None:
    host.module("builtins").exec("import sys; sys.modules['plain_setting'] = 42", {})
    with pytest.raises(ImportError) as info:
        host.module("plain_setting")
    assert type(info.value) is ImportError and str(info.value) == "plain_setting is not a module"


def test_a_library_error_message_is_carried_back_to_max_error_chars(host: NativeHost) -> None:
    with pytest.raises(KeyError) as info:
        host.module("operator").getitem({}, "k" * 3000)
    assert type(info.value) is KeyError and info.value.args == ("'" + "k" * (p.MAX_ERROR_CHARS - 1),)


def test_a_request_of_exactly_max_message_bytes_is_sent_one_byte_more_is_refused_unsent(guarded: NativeHost,
                                                                                         stops: list[str]) -> None:
    builtins = guarded.module("builtins")

    def size(n: int) -> int:  # the request the next call sends: (seq, op, handle, name, args, kwargs)
        return len(pickle.dumps((guarded.calls + 1, p.CALL, 1, "len", (b"x" * n,), {})))

    n = _filling(size)
    assert builtins.len(b"x" * n) == n
    with pytest.raises(DeviceError) as info:
        builtins.len(b"x" * (n + 1))
    assert type(info.value) is DeviceError
    assert str(info.value) == (f"ur 10.0.0.2: len: the request is {p.MAX_MESSAGE_BYTES + 1} bytes, over the "
                               f"1048576 the ur_rtde worker reads; nothing was sent")
    assert builtins.len(b"ab") == 2 and guarded.calls == 3 and stops == []  # the worker serves on, no crash


def test_an_argument_that_cannot_be_pickled_is_the_callers_error_not_a_crash(guarded: NativeHost,
                                                                           stops: list[str]) -> None:
    operator = guarded.module("operator")
    with pytest.raises(ValueError, match="ctypes objects containing pointers cannot be pickled"):
        operator.add(ctypes.pointer(ctypes.c_int(3)), 1)
    assert operator.add(3, 1) == 4 and stops == []


def test_a_reply_of_exactly_max_message_bytes_is_read_one_byte_more_stops_the_worker(host: NativeHost) -> None:
    builtins = host.module("builtins")

    def size(n: int) -> int:  # the reply to the next call: (seq, kind, payload)
        return len(pickle.dumps((host.calls + 1, p.VALUE, bytes(n))))

    n = _filling(size)
    assert builtins.bytes(n) == bytes(n)
    pid = host.pid
    assert pid is not None
    with pytest.raises(DeviceConnectionError) as info:
        builtins.bytes(n + 1)
    assert type(info.value) is DeviceConnectionError and info.value.__suppress_context__
    assert str(info.value) == ("ur 10.0.0.2: the ur_rtde worker sent an unreadable reply to bytes (bad message "
                               "length); it was stopped")
    assert _soon(lambda: _state(pid) in ("Z", ""))        # killed
    with pytest.raises(NativeCrashError) as later:
        builtins.len(b"")
    assert str(later.value) == "ur 10.0.0.2: the ur_rtde worker process died earlier (exited); connect again"
    assert (later.value.backend, later.value.signal_name) == ("ur", "")


def test_a_tuple_of_a_class_only_the_worker_has_stays_there(guarded: NativeHost, stops: list[str]) -> None:
    """A vendor's namedtuple is not plain: it stays in the worker, and its module is never imported here."""
    probe = _probe(guarded)
    point = probe.Point(1, 2)
    assert isinstance(point, RemoteObject) and point.type_name == "Point"
    assert point.count(2) == 1 and point.index(2) == 1     # its methods run in the worker
    assert "probe" not in sys.modules
    assert probe.log() == [] and stops == []              # the worker serves on


# ---------------------------------------------------------------- host: the library's own output
def test_the_libraries_output_is_logged_a_bounded_line_at_a_time(host: NativeHost, caplog: pytest.LogCaptureFixture,
                                                                  capfd: pytest.CaptureFixture[str]) -> None:
    os_ = host.module("os")
    with caplog.at_level(logging.DEBUG, logger="cellcal.devices.isolation.host"):
        os_.write(1, b"  indented  \n\n\xff bad byte\n" + b"y" * 600 + b"\n" + b"z" * 4097 + b"\n")
        os_.write(2, b"to stderr\n")
        assert _soon(lambda: len(caplog.records) >= 6)
        time.sleep(0.05)
    prefix = "ur 10.0.0.2: ur_rtde: "
    assert [r.getMessage() for r in caplog.records] == [
        prefix + "  indented",                            # trailing blanks dropped, the indent kept
        prefix + "\ufffd bad byte",                       # undecodable bytes replaced
        prefix + "y" * MAX_OUTPUT_LINE,                   # one line, cut at MAX_OUTPUT_LINE characters
        prefix + "z" * MAX_OUTPUT_LINE, prefix + "z",     # longer than the 4096-byte read: in two pieces
        prefix + "to stderr"]
    assert all(r.levelno == logging.DEBUG for r in caplog.records)
    assert capfd.readouterr() == ("", "")
