"""A watchdog over each device call a check makes: a hook that never returns cannot hang the kit.

:func:`run_watched` runs one check in a worker thread and looks at the worker's stack
every few milliseconds. The innermost frame whose ``self`` is a cellcal device is the
call under way (a backend hook such as ``_capture``, or the base class's public method
around it). A call may run for its own ``timeout`` argument plus ``watchdog_s``
(``watchdog_s`` alone when it takes no timeout); past that the worker is abandoned (a
hung call cannot be cancelled) and :class:`HookHung` names the hook and the time.
"""

from __future__ import annotations

import math
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from types import FrameType
from typing import Any, TypeGuard

from cellcal.devices.base import Device

#: How often the watchdog looks at the worker's stack, seconds.
POLL_S = 0.02


class HookHung(Exception):  # noqa: N818 - internal signal, never escapes the runner
    """A device call under a check did not return within its allowance.

    Attributes:
        device_class: The class of the device whose call hung.
        hook: ``Class.method`` of the call, e.g. ``"AcmeZ1Camera._capture"``.
        entry: The public method it was called through (``"capture"``), or "".
        timeout_s: The timeout the call was given, seconds, or None.
        elapsed_s: How long it had run when abandoned, seconds.
    """

    def __init__(self, device_class: type, hook: str, entry: str, timeout_s: float | None, elapsed_s: float,
                 watchdog_s: float):
        self.device_class = device_class
        self.hook = hook
        self.entry = entry
        self.timeout_s = timeout_s
        self.elapsed_s = elapsed_s
        via = f" (called through {entry}())" if entry and entry != hook.rpartition(".")[2] else ""
        allowance = (f"its timeout {timeout_s:g} s + {watchdog_s:g} s" if timeout_s is not None
                     else f"{watchdog_s:g} s")
        super().__init__(f"hook {hook}{via} did not return after {elapsed_s:.1f} s (allowed: {allowance}); "
                         "the kit abandoned it")


@dataclass
class _Call:
    """The device call the worker is in, as first seen by the watchdog."""

    frame: FrameType
    seen_at: float
    device: Device
    entry: str

    def timeout(self) -> float | None:
        value = _local(self.frame, "timeout")
        ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value > 0
        return float(value) if ok else None

    def hook(self) -> str:
        return f"{type(self.device).__name__}.{self.frame.f_code.co_name}"


def _local(frame: FrameType, name: str) -> Any:
    try:
        return frame.f_locals.get(name)
    except Exception:  # a frame finishing under us
        return None


def _is_device(obj: object) -> TypeGuard[Device]:
    """``isinstance(obj, Device)``; False for an object caught half-built (a mock's ``__class__``
    can raise while another thread constructs it)."""
    try:
        return isinstance(obj, Device)
    except Exception:
        return False


def _device_call(frame: FrameType | None) -> tuple[FrameType, Device, str] | None:
    """The innermost frame running a method of a device, its device, and the outermost such method's name."""
    inner: tuple[FrameType, Device] | None = None
    entry = ""
    while frame is not None:
        owner = _local(frame, "self")
        if _is_device(owner):
            if inner is None:
                inner = (frame, owner)
            entry = frame.f_code.co_name
        frame = frame.f_back
    return None if inner is None else (inner[0], inner[1], entry)


def run_watched(fn: Callable[[], None], name: str, watchdog_s: float) -> None:
    """Run ``fn()`` in a worker thread under the watchdog; re-raise what it raised.

    Args:
        fn: The check (raises on a breach).
        name: Worker thread name (shows in thread dumps and leak reports).
        watchdog_s: Allowance of each device call beyond its own timeout, seconds.

    Raises:
        HookHung: If a device call overran its allowance (the worker keeps running, abandoned).
        BaseException: Whatever ``fn`` raised.
    """
    outcome: list[BaseException] = []

    def work() -> None:
        try:
            fn()
        except BaseException as exc:  # handed to the caller below
            outcome.append(exc)

    worker = threading.Thread(target=work, name=name, daemon=True)
    worker.start()
    current: _Call | None = None
    while True:
        worker.join(POLL_S)
        if not worker.is_alive():
            break
        current = _watch(worker, current, watchdog_s)
    if outcome:
        raise outcome[0]


def _watch(worker: threading.Thread, current: _Call | None, watchdog_s: float) -> _Call | None:
    """One look at the worker: the call it is in now; raise :class:`HookHung` if that call overran."""
    found = _device_call(sys._current_frames().get(worker.ident or -1))
    now = time.monotonic()
    if found is None:
        return None
    frame, device, entry = found
    if current is None or current.frame is not frame:
        return _Call(frame, now, device, entry)
    timeout = current.timeout()
    elapsed = now - current.seen_at
    if elapsed > (timeout or 0.0) + watchdog_s:
        raise HookHung(type(device), current.hook(), current.entry, timeout, elapsed, watchdog_s)
    return current
