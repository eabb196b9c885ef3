"""Pinned behaviour of the native-isolation host when a call goes wrong (issue #32): a worker that dies (a signal,
an exit, a closed pipe, an unreadable reply, garbage after its death) is a crash named once in the user's words
that stops the arm once; deadlines bound and name their calls; objects dropped, or coming back after their call
gave up, are freed in the worker without an error here.

The helpers are those of test_isolation_host_pinned.py; the fixtures (``host``, ``stops``, ``guarded``) are in
this folder's conftest.py.
"""

from __future__ import annotations

import logging
import os
import signal
import threading
import time

import pytest
from test_isolation_host_pinned import GONE, _closed, _new, _probe, _soon, _state

from cellcal.devices.errors import DeviceConnectionError, DeviceTimeoutError, NativeCrashError
from cellcal.devices.isolation import NativeHost
from cellcal.devices.isolation import protocol as p


# ---------------------------------------------------------------- host: an unreadable reply, garbage from the dead
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
