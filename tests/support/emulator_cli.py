"""A standalone emulator started as a child process: its first stdout line, and stopping it."""

from __future__ import annotations

import selectors
import signal
import subprocess
import time

import pytest


def first_line(proc: subprocess.Popen[str], timeout: float) -> str:
    """The child's first stdout line (its ``ready`` or pty line); fails the test after ``timeout`` s."""
    assert proc.stdout is not None
    with selectors.DefaultSelector() as sel:  # closed here, not whenever the garbage collector runs
        sel.register(proc.stdout, selectors.EVENT_READ)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if sel.select(timeout=0.1):
                return proc.stdout.readline().strip()
            if proc.poll() is not None:
                break
    pytest.fail(f"the emulator printed no first line within {timeout} s")


def stop(proc: subprocess.Popen[str], sig: signal.Signals, timeout: float = 10.0) -> tuple[str, str]:
    """Send ``sig``, wait for the child to end; its remaining (stdout, stderr). Killed if it does not end."""
    proc.send_signal(sig)
    try:
        return proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.communicate()
        raise
