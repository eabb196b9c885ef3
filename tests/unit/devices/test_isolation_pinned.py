"""Pinned behaviour of the native-isolation protocol and host (issue #32): bounds at their exact limits,
the texts a user reads, every field of the messages, deadlines honoured, nothing left behind."""

from __future__ import annotations

import collections
import ctypes
import logging
import os
import pickle
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from cellcal.devices.errors import DeviceConnectionError, DeviceError, DeviceTimeoutError, NativeCrashError
from cellcal.devices.isolation import NativeHost, RemoteModule, RemoteObject
from cellcal.devices.isolation import protocol as p
from cellcal.devices.isolation.host import MAX_OUTPUT_LINE


# ---------------------------------------------------------------- protocol: what travels by value
def _nested_lists(levels: int) -> object:
    """``levels`` lists one inside the other around the scalar 1 (``levels=2``: ``[[1]]``)."""
    value: object = 1
    for _ in range(levels):
        value = [value]
    return value


def _nested_dicts(levels: int) -> object:
    """``levels`` str-keyed dicts one inside the other around the scalar 1."""
    value: object = 1
    for _ in range(levels):
        value = {"k": value}
    return value


@pytest.mark.parametrize("value", [None, True, 0, -7, 2.5, float("nan"), "", "text", b"", b"\x00\xff"])
def test_every_scalar_type_is_plain(value: object) -> None:
    assert p.is_plain(value) is True


@pytest.mark.parametrize("value", [object(), {1, 2}, frozenset(), bytearray(b"x"), 1j, range(3), print])
def test_other_types_stay_in_the_worker(value: object) -> None:
    assert p.is_plain(value) is False


def test_containers_are_plain_to_exactly_max_plain_depth_levels() -> None:
    assert p.MAX_PLAIN_DEPTH == 4
    for nest in (_nested_lists, _nested_dicts):
        assert p.is_plain(nest(p.MAX_PLAIN_DEPTH)) is True            # [[[[1]]]]: four levels travel
        assert p.is_plain(nest(p.MAX_PLAIN_DEPTH + 1)) is False       # [[[[[1]]]]]: the fifth stays
    assert p.is_plain([[[[]]]]) is True
    assert p.is_plain([[[[[]]]]]) is False                            # an empty container at depth 4 too
    assert p.is_plain((1, [2.0, {"a": ("b", b"c")}], None)) is True     # mixed kinds count levels alike
    assert p.is_plain((1, [2.0, {"a": ("b", [b"c"])}], None)) is False


def test_the_depth_argument_counts_the_levels_already_descended() -> None:
    assert p.is_plain([1], depth=p.MAX_PLAIN_DEPTH - 1) is True
    assert p.is_plain([1], depth=p.MAX_PLAIN_DEPTH) is False
    assert p.is_plain({"k": 1}, depth=p.MAX_PLAIN_DEPTH) is False
    assert p.is_plain("scalar", depth=p.MAX_PLAIN_DEPTH + 10) is True  # scalars at any depth
    assert p.is_plain([[1]], depth=p.MAX_PLAIN_DEPTH - 2) is True
    assert p.is_plain([[1]], depth=p.MAX_PLAIN_DEPTH - 1) is False


def test_one_non_plain_member_keeps_the_whole_container_in_the_worker() -> None:
    assert p.is_plain([1, 2, object()]) is False
    assert p.is_plain((object(),)) is False
    assert p.is_plain([1, 2, 3]) is True and p.is_plain(()) is True and p.is_plain([]) is True
    assert p.is_plain({"a": 1, "b": object()}) is False
    assert p.is_plain({"a": 1, "b": [2, 3]}) is True and p.is_plain({}) is True


def test_dicts_travel_only_with_string_keys() -> None:
    assert p.is_plain({1: "x"}) is False
    assert p.is_plain({"a": 1, 2: "b"}) is False
    assert p.is_plain({("a",): 1}) is False
    assert p.is_plain({"a": 1.5, "b": None}) is True



def test_subclasses_of_plain_types_stay_in_the_worker() -> None:
    """Unpickled in the parent, a subclass would import its module there: perhaps the native library itself."""
    assert p.is_plain(collections.Counter("abracadabra")) is False      # a dict subclass (str keys)
    assert p.is_plain(collections.OrderedDict(a=[1, 2])) is False
    assert p.is_plain(signal.SIGINT) is False                          # an IntEnum
    assert p.is_plain(collections.namedtuple("Point", "x y")(1, 2)) is False
    assert p.is_plain([1, signal.SIGINT]) is False and p.is_plain({"a": (1, True)}) is True


# ---------------------------------------------------------------- protocol: errors rebuilt in the parent
@pytest.mark.parametrize("name", sorted(p.KNOWN_ERRORS))
def test_a_known_error_comes_back_as_itself_with_its_message(name: str) -> None:
    error = p.rebuild_error(name, "the library said no")
    assert type(error) is p.KNOWN_ERRORS[name] and type(error).__name__ == name
    assert error.args == ("the library said no",)


def test_the_known_errors_are_exactly_the_builtin_ones_a_library_raises() -> None:
    assert sorted(p.KNOWN_ERRORS) == ["AttributeError", "ConnectionError", "ImportError", "IndexError", "KeyError",
                                      "ModuleNotFoundError", "OSError", "RuntimeError", "TimeoutError", "TypeError",
                                      "ValueError"]


@pytest.mark.parametrize("name", ["JSONDecodeError", "RuntimeException", "ZeroDivisionError", "Exception", ""])
def test_any_other_error_is_a_runtime_error_naming_its_type(name: str) -> None:
    error = p.rebuild_error(name, "boom: at line 3")
    assert type(error) is RuntimeError
    assert error.args == (f"{name}: boom: at line 3",)


def test_message_kinds_and_operations_are_distinct_wire_words() -> None:
    # the parent and the worker (another interpreter, possibly another cellcal) agree on these words
    assert (p.IMPORT, p.CALL, p.DROP, p.CLOSE) == ("import", "call", "drop", "close")
    assert (p.VALUE, p.REF, p.ERROR) == ("value", "ref", "error")
    assert p.MAX_MESSAGE_BYTES == 1_048_576 and p.MAX_ERROR_CHARS == 2000




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


def test_an_unreadable_reply_stops_the_arm_too(guarded: NativeHost, stops: list[str]) -> None:
    """A reply over the size bound: the worker is killed with the device's connections, so the arm is stopped."""
    builtins = guarded.module("builtins")
    pid = guarded.pid
    assert pid is not None
    with pytest.raises(DeviceConnectionError) as info:
        builtins.bytes(p.MAX_MESSAGE_BYTES + 1)
    assert type(info.value) is DeviceConnectionError
    assert str(info.value) == ("ur 10.0.0.2: the ur_rtde worker sent an unreadable reply to bytes (bad message "
                               "length); it was stopped; the arm was told to stop")
    assert stops == ["stop"]
    assert _soon(lambda: _state(pid) in ("Z", ""))
    with pytest.raises(NativeCrashError, match=r"died earlier \(exited\); connect again$"):
        builtins.len(b"")
    assert stops == ["stop"]                              # once


def test_garbage_from_a_worker_that_has_died_is_its_crash(guarded: NativeHost, stops: list[str]) -> None:
    # the worker leaves a forked child holding the socket, which writes an oversized header once the worker is dead
    code = ("import os, struct, sys, time\n"
            "if os.fork() == 0:\n"
            "    time.sleep(0.3); os.write(int(sys.argv[-1]), struct.pack('!i', 2 << 20)); os._exit(0)\n"
            "os._exit(7)\n")
    with pytest.raises(NativeCrashError) as info:
        guarded.module("builtins").exec(code, {})
    assert str(info.value) == (f"ur 10.0.0.2: the ur_rtde worker process died during exec (exit status 7); {GONE}; "
                               f"the arm was told to stop")
    assert stops == ["stop"]


# ---------------------------------------------------------------- host: a dead worker
NATIVE, OUTSIDE = "a crash in native code", "killed from outside"


@pytest.mark.parametrize(("signum", "name", "how"), [
    (signal.SIGSEGV, "SIGSEGV", NATIVE), (signal.SIGABRT, "SIGABRT", NATIVE), (signal.SIGBUS, "SIGBUS", NATIVE),
    (signal.SIGFPE, "SIGFPE", NATIVE), (signal.SIGILL, "SIGILL", NATIVE), (signal.SIGKILL, "SIGKILL", OUTSIDE),
    (signal.SIGTERM, "SIGTERM", OUTSIDE), (signal.SIGRTMIN + 1, f"signal {signal.SIGRTMIN + 1}", OUTSIDE)])
def test_a_worker_ended_by_a_signal_is_a_crash_naming_the_signal_and_the_arm_is_stopped_once(
        guarded: NativeHost, stops: list[str], signum: int, name: str, how: str) -> None:
    os_ = guarded.module("os")
    pid = guarded.pid
    assert pid is not None
    os.kill(pid, signum)
    assert _soon(lambda: _state(pid) == "Z")
    with pytest.raises(NativeCrashError) as info:
        os_.getpid()
    assert str(info.value) == (f"ur 10.0.0.2: the ur_rtde worker process died during getpid ({name}, {how}); "
                               f"{GONE}; the arm was told to stop")
    assert (info.value.backend, info.value.signal_name) == ("ur", name)
    with pytest.raises(NativeCrashError) as later:
        guarded.module("os")
    assert str(later.value) == f"ur 10.0.0.2: the ur_rtde worker process died earlier ({name}); connect again"
    assert (later.value.backend, later.value.signal_name) == ("ur", name)
    assert stops == ["stop"] and _state(pid) == ""


@pytest.mark.parametrize("status", [0, 3])
def test_a_worker_that_exits_mid_call_is_a_crash_told_once_in_the_debug_log(
        host: NativeHost, caplog: pytest.LogCaptureFixture, status: int) -> None:
    os_ = host.module("os")
    with caplog.at_level(logging.DEBUG, logger="cellcal.devices.isolation.host"), \
            pytest.raises(NativeCrashError) as info:
        os_._exit(status)
    message = f"ur 10.0.0.2: the ur_rtde worker process died during _exit (exit status {status}); {GONE}"
    assert str(info.value) == message                    # no hook: nothing after the last clause
    assert (info.value.backend, info.value.signal_name) == ("ur", "")
    assert [r.getMessage() for r in caplog.records] == [message]
    with pytest.raises(NativeCrashError) as later:
        os_.getpid()
    assert str(later.value) == "ur 10.0.0.2: the ur_rtde worker process died earlier (exited); connect again"


def test_a_failing_crash_hook_is_reported_and_does_not_mask_the_crash() -> None:
    calls: list[int] = []

    def hook() -> str:
        calls.append(1)
        raise ConnectionRefusedError("dashboard refused")

    h = _new(on_crash=hook)
    h.start(10.0)
    try:
        os_ = h.module("os")
        with pytest.raises(NativeCrashError) as info:
            os_.abort()
        assert str(info.value).endswith(f"(SIGABRT, {NATIVE}); {GONE}; stopping the arm failed (dashboard refused)")
        with pytest.raises(NativeCrashError, match="died earlier"):
            os_.getpid()
        assert calls == [1]
    finally:
        h.close(1.0)


def test_a_worker_that_closes_its_end_but_lives_on_is_reported_after_one_second(host: NativeHost) -> None:
    code = "import os, sys, time; os.close(int(sys.argv[-1])); time.sleep(30)"
    t0 = time.monotonic()
    with pytest.raises(NativeCrashError) as info:
        host.module("builtins").exec(code, {})
    assert 1.0 <= time.monotonic() - t0 < 4.0            # the exit status is waited for 1 s, not the 30 s
    assert str(info.value) == f"ur 10.0.0.2: the ur_rtde worker process died during exec (its pipe closed); {GONE}"
    assert info.value.signal_name == ""
    pid = host.pid
    assert pid is not None
    host.close(0.1)                                       # still there: killed
    assert _state(pid) == ""


# ---------------------------------------------------------------- host: deadlines
def test_a_call_outside_any_deadline_is_bounded_by_the_default_timeout() -> None:
    assert _new().default_timeout_s == 5.0
    h = _new(default_timeout_s=0.3)
    h.start(10.0)
    try:
        sleep = h.module("time").sleep
        t0 = time.monotonic()
        with pytest.raises(DeviceTimeoutError) as info:
            sleep(30.0)
        assert 0.3 <= time.monotonic() - t0 < 3.3             # the default timeout, not the 30 s sleep
        assert str(info.value) == "ur 10.0.0.2: sleep did not finish within 0.3 s"
    finally:
        h.close(0.5)


def test_nested_deadlines_bound_and_name_their_calls_and_restore_the_outer_one(host: NativeHost) -> None:
    remote_time, operator = host.module("time"), host.module("operator")
    # the bounds leave more than a second for a busy machine: the wrong ends lie 1.3 s (the settle's sleep) and
    # 1.5 s (the outer deadline counted from the call, which starts after that sleep) beyond the right ones
    t0 = time.monotonic()
    with host.deadline(2.5, "calibrate"):
        with pytest.raises(DeviceTimeoutError) as inner, host.deadline(0.2, "settle"):
            remote_time.sleep(1.5)
        assert str(inner.value) == "ur 10.0.0.2: settle (sleep) did not finish within 0.2 s"
        assert 0.2 <= time.monotonic() - t0 < 1.4
        assert operator.add(1, 2) == 3                   # waits out the late reply, within the outer deadline
        with pytest.raises(DeviceTimeoutError) as outer:
            remote_time.sleep(2.5)
        assert 2.5 <= time.monotonic() - t0 < 3.9         # the outer deadline, counted from its start
        assert str(outer.value) == "ur 10.0.0.2: calibrate (sleep) did not finish within 2.5 s"
        with pytest.raises(DeviceTimeoutError) as same, host.deadline(0.1, "sleep"):
            remote_time.sleep(0.5)                        # a deadline named as the call: named once
        assert str(same.value) == "ur 10.0.0.2: sleep did not finish within 0.1 s"
    assert operator.mul(4, 5) == 20                      # outside: the default 5 s waits out both sleeps


def test_a_deadline_already_past_fails_at_once_and_the_worker_serves_on(host: NativeHost) -> None:
    getpid = host.module("os").getpid
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeoutError) as info, host.deadline(-2.0, "read"):
        getpid()
    assert time.monotonic() - t0 < 3.0                   # at once (with room for a busy machine)
    assert str(info.value) == "ur 10.0.0.2: read (getpid) did not finish within 0 s"
    with host.deadline(0.5, "read"):
        assert getpid() == host.pid


def test_bounded_runs_its_calls_under_one_deadline(host: NativeHost) -> None:
    operator, remote_time = host.module("operator"), host.module("time")
    assert host.bounded(lambda: (operator.add(1, 2), operator.mul(2, 3)), 1.0, "read twice") == (3, 6)
    with pytest.raises(DeviceTimeoutError, match=r"^ur 10.0.0.2: settle \(sleep\) did not finish within 0.2 s$"):
        host.bounded(lambda: remote_time.sleep(1.0), 0.2, "settle")


def test_a_call_waiting_for_another_threads_call_times_out_naming_it(host: NativeHost) -> None:
    remote_time, operator = host.module("time"), host.module("operator")
    sent = host.calls
    other = threading.Thread(target=remote_time.sleep, args=(2.5,))
    other.start()
    try:
        assert _soon(lambda: host.calls > sent)           # the other call is sent: it holds the pipe for 2.5 s
        t0 = time.monotonic()
        with pytest.raises(DeviceTimeoutError) as info, host.deadline(0.2, "read pose"):
            operator.add(1, 2)
        assert 0.2 <= time.monotonic() - t0 < 1.5         # its own deadline, not the other call's end
        assert str(info.value) == "ur 10.0.0.2: read pose (add): another call into ur_rtde has not returned"
    finally:
        other.join(30.0)
    assert operator.add(1, 2) == 3 and host.calls == 4   # the refused call was never sent


# ---------------------------------------------------------------- host: objects dropped
def test_dropped_objects_are_disconnected_if_asked_and_freed_on_the_reaper(host: NativeHost) -> None:
    probe = _probe(host)
    a, b = probe.Device("a"), probe.Device("b")
    keep = probe.Device("keep")
    host.drop(a)
    host.drop(b, disconnect=False)
    assert _soon(lambda: len(probe.log()) == 3)
    assert probe.log() == [("disconnect", "a", "reaper"), ("freed", "a"), ("freed", "b")]
    keep.disconnect()                                     # the others are untouched and still there
    assert probe.log()[-1] == ("disconnect", "keep", "MainThread")


def test_drop_ignores_what_is_not_this_workers_object(host: NativeHost) -> None:
    other = _new()
    other.start(10.0)
    try:
        mine, theirs = _probe(host).Device("mine"), _probe(other).Device("theirs")
        assert repr(mine) == "<Device #3 in the ur_rtde worker>" == repr(theirs)  # the same handle, two workers
        for obj in (theirs, "a string", None, 3):
            host.drop(obj)
        time.sleep(0.2)
        assert host.module("probe").log() == [] and other.module("probe").log() == []
    finally:
        other.close(1.0)


def test_drop_never_raises_on_a_worker_dead_closed_or_already_found_dead(host: NativeHost) -> None:
    probe = _probe(host)
    device = probe.Device("d")
    pid = host.pid
    assert pid is not None
    os.kill(pid, signal.SIGKILL)
    conn = host._conn
    assert conn is not None and _soon(lambda: _closed(pid) and conn.poll(0))  # its end of the socket is closed
    host.drop(device)                                     # not known dead yet: the send fails quietly
    with pytest.raises(NativeCrashError, match=r"\(SIGKILL, killed from outside\)"):
        probe.log()
    host.drop(device)                                     # known dead
    host.close(0.5)
    host.drop(device)                                     # closed


def test_a_late_object_is_freed_without_a_disconnect_and_the_caller_gets_its_own_reply(host: NativeHost) -> None:
    probe = _probe(host)
    with pytest.raises(DeviceTimeoutError), host.deadline(0.2, "open"):
        probe.Device("late", 0.5)                         # overruns; its object comes back later
    assert probe.log() == []                              # this reply, not the late object
    assert _soon(lambda: probe.log() == [("freed", "late")])


def test_a_late_object_from_a_worker_that_no_longer_reads_is_not_this_calls_error(host: NativeHost) -> None:
    # within one call the worker stops reading and sends an older reply (an object): the parent's drop of that
    # object fails (EPIPE) quietly, and the call still gets its own reply
    code = ("import os, pickle, socket, struct, sys\n"
            "s = socket.socket(fileno=os.dup(int(sys.argv[-1])))\n"
            "s.shutdown(socket.SHUT_RD)\n"
            "late = pickle.dumps((0, 'ref', (99, 'Ghost')))\n"
            "s.sendall(struct.pack('!i', len(late)) + late)\n")
    assert host.module("builtins").exec(code, {}) is None


def test_a_late_value_is_discarded(host: NativeHost) -> None:
    builtins = host.module("builtins")
    with pytest.raises(DeviceTimeoutError), host.deadline(0.2, "open"):
        host.module("time").sleep(0.4)
    assert builtins.abs(-3) == 3 and builtins.abs(-4) == 4


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


def test_a_reply_that_does_not_pickle_goes_out_as_an_error_not_as_the_workers_end() -> None:
    """The worker's last guard: a reply pickle refuses becomes an error reply with the same sequence number."""
    from multiprocessing.connection import Pipe
    from types import SimpleNamespace

    from cellcal.devices.isolation.worker import Worker

    ours, theirs = Pipe()
    try:
        Worker._send(SimpleNamespace(conn=theirs), (7, p.VALUE, lambda: 0))  # type: ignore[arg-type]
        seq, kind, (name, message) = pickle.loads(ours.recv_bytes(p.MAX_MESSAGE_BYTES))
        assert (seq, kind) == (7, p.ERROR) and name in ("PicklingError", "AttributeError")  # by Python version
        assert message.startswith("the reply could not be pickled: ") and len(message) <= p.MAX_ERROR_CHARS
        assert str(p.rebuild_error(name, message)).startswith(("the reply could not be pickled", "PicklingError: the"))
    finally:
        ours.close()
        theirs.close()
