"""Machinery shared by the camera and arm conformance checks (no pytest needed).

A check ``check(factory, options)`` builds its own devices from ``factory`` (a zero-argument
callable returning a new, unconnected device), uses and closes them, and raises :class:`Violation`
(through :func:`expect` / :func:`raises`) on a breach; :func:`run_check` turns that, or any
unexpected exception of the backend, into a :class:`CheckResult` naming the rule and the backend.
"""

from __future__ import annotations

import contextlib
import functools
import math
import os
import sys
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

from cellcal.devices.base import Device
from cellcal.devices.errors import CellcalError, ConformanceError, DeviceTimeoutError, FrameError

from .watchdog import HookHung, run_watched

D = TypeVar("D", bound=Device)
O = TypeVar("O")  # noqa: E741 - options type

#: The rule that reports a malformed Frame; the other rules skip when capture() cannot build one.
FRAME_LAYOUT_RULE = "camera.frame-layout"
#: Default allowance of a device call beyond its own timeout before the watchdog gives up on it, seconds.
DEFAULT_WATCHDOG_S = 10.0

#: Timeout values every public I/O method must reject with a CellcalError naming "timeout".
BAD_TIMEOUTS: tuple[Any, ...] = (0, 0.0, -1.0, math.nan, math.inf, -math.inf, True, "1")


class Violation(Exception):  # noqa: N818 - internal signal, never escapes the runner
    """Raised inside a check when the backend breaks the rule under test."""


@dataclass(frozen=True)
class Check(Generic[D, O]):
    """One contract rule and the function that checks it.

    Attributes:
        rule: Stable identifier, e.g. ``"camera.frame-units"``.
        summary: The rule in one sentence.
        func: ``func(factory, options)``; raises :class:`Violation` on a breach.
    """

    rule: str
    summary: str
    func: Callable[[Callable[[], D], O], None]


@dataclass(frozen=True)
class CheckResult:
    """Outcome of one check.

    Attributes:
        rule: The contract rule checked.
        summary: The rule in one sentence.
        backend: Backend name (``backend_name`` of the device class).
        passed: Whether the backend honoured the rule (False when skipped).
        detail: What was wrong, or why the rule was skipped ("" when passed).
        duration_s: Wall time the check took, seconds.
        skipped: The rule could not be checked because an earlier failure, reported under
            its own rule, makes it meaningless (a malformed frame, a hung device).
    """

    rule: str
    summary: str
    backend: str
    passed: bool
    detail: str = ""
    duration_s: float = 0.0
    skipped: bool = False

    @property
    def message(self) -> str:
        """One line: backend, rule, and what went wrong (or "ok", or why it was skipped)."""
        if self.passed:
            return f"{self.backend}: {self.rule}: ok"
        if self.skipped:
            return f"{self.backend}: {self.rule}: skipped: {self.detail}"
        return f"{self.backend}: contract rule {self.rule} ({self.summary}) violated: {self.detail}"


@dataclass
class ConformanceReport:
    """All check results for one backend.

    Attributes:
        kind: ``"camera"`` or ``"arm"``.
        backend: Backend name.
        results: One entry per check run, in order.
    """

    kind: str
    backend: str
    results: list[CheckResult] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        """True when no check failed (a skipped check follows a failure reported under another rule)."""
        return not self.failures

    @property
    def failures(self) -> list[CheckResult]:
        """The failed checks (not the skipped ones)."""
        return [r for r in self.results if not (r.passed or r.skipped)]

    def raise_for_failures(self) -> None:
        """Raise :class:`ConformanceError` listing every failed rule, if any failed."""
        bad = self.failures
        if bad:
            lines = [f"{self.backend}: {len(bad)} of {len(self.results)} {self.kind} contract checks failed"]
            lines += [f"  - {r.message}" for r in bad]
            raise ConformanceError("\n".join(lines), bad)

    def __str__(self) -> str:
        passed = sum(r.passed for r in self.results)
        skipped = sum(r.skipped for r in self.results)
        head = (f"{self.kind} backend {self.backend}: {passed}/{len(self.results)} contract checks passed"
                + (f", {skipped} skipped" if skipped else ""))
        return "\n".join([head, *(f"  {_verdict(r)} {r.rule}" + ("" if r.passed else f": {r.detail}")
                                  for r in self.results)])


def _verdict(r: CheckResult) -> str:
    return "PASS" if r.passed else "SKIP" if r.skipped else "FAIL"


# ---------------------------------------------------------------- helpers for checks
def expect(condition: Any, detail: str) -> None:
    """Raise :class:`Violation` with ``detail`` unless ``condition`` is true."""
    if not condition:
        raise Violation(detail)


def raises(expected: type[BaseException] | tuple[type[BaseException], ...], fn: Callable[[], Any], what: str,
           *, contains: str | None = None) -> BaseException:
    """Call ``fn`` and require it to raise ``expected`` (optionally naming ``contains``).

    Returns:
        The exception raised.

    Raises:
        Violation: If nothing was raised, something else was raised, or the message
            does not contain ``contains`` (case-insensitive).
    """
    names = (expected,) if isinstance(expected, type) else expected
    wanted = " or ".join(e.__name__ for e in names)
    try:
        fn()
    except expected as exc:
        if contains is not None and contains.lower() not in str(exc).lower():
            raise Violation(f"{what} raised {type(exc).__name__} without naming {contains!r}: {exc}") from None
        return exc
    except Exception as exc:
        raise Violation(f"{what} raised {type(exc).__name__} ({exc}) instead of {wanted}") from None
    raise Violation(f"{what} did not raise {wanted}")


def backend_label(device_or_class: Any) -> str:
    """The name a report uses for a backend: ``backend_name``, else the class name."""
    cls = device_or_class if isinstance(device_or_class, type) else type(device_or_class)
    return str(getattr(cls, "backend_name", "") or cls.__name__)


def make(factory: Callable[[], D], base: type[Any]) -> D:
    """Call the factory and require a new, unconnected device of the right interface."""
    device = factory()
    expect(isinstance(device, base),
           f"the factory returned {type(device).__name__}, not a {base.__name__} subclass")
    expect(not device.connected, "the factory must return an unconnected device (connected is True)")
    return device


@contextlib.contextmanager
def connected(factory: Callable[[], D], base: type[Any], timeout: float) -> Iterator[D]:
    """A fresh device from ``factory``, connected for the ``with`` block and closed after it."""
    device = make(factory, base)
    try:
        device.connect(timeout)
        yield device
    finally:
        device.close()


def timed(fn: Callable[[], Any]) -> tuple[float, Any, BaseException | None]:
    """Run ``fn``; return ``(elapsed_s, result, exception)`` (exception None on success).

    A :class:`FrameError` propagates: a malformed frame is not a timing question.
    """
    t0 = time.monotonic()
    try:
        result = fn()
    except FrameError:
        raise
    except Exception as exc:
        return time.monotonic() - t0, None, exc
    return time.monotonic() - t0, result, None


def check_bad_timeouts(calls: dict[str, Callable[[Any], Any]]) -> None:
    """Every ``calls[name](bad)`` must raise a CellcalError that names the timeout."""
    for name, call in calls.items():
        for bad in BAD_TIMEOUTS:
            raises(CellcalError, functools.partial(call, bad), f"{name}(timeout={bad!r})", contains="timeout")


def check_bad_connect_timeouts(factory: Callable[[], Any], base: type[Any], kind: str) -> None:
    """``connect(bad)`` on a fresh device must raise (see :func:`check_bad_timeouts`) and leave it unconnected."""
    device = make(factory, base)
    try:
        check_bad_timeouts({"connect": device.connect})
        expect(not device.connected, f"connect() with a rejected timeout left the {kind} connected")
    finally:
        device.close()


def check_stalled(o: Any, base: type[Any], calls: Callable[[Any], dict[str, Callable[[], object]]]) -> None:
    """With ``o.stalled_factory``: every short-timeout call on a stalled device raises DeviceTimeoutError in time.

    Args:
        o: The options (``stalled_factory``, ``short_timeout_s``, ``timing_slack_s``, ``connect_timeout_s``).
        base: The interface the stalled device must implement.
        calls: ``calls(device)`` -> the calls (by name) made with ``o.short_timeout_s``.
    """
    if o.stalled_factory is None:
        return
    limit = o.short_timeout_s + o.timing_slack_s
    with connected(o.stalled_factory, base, o.connect_timeout_s) as device:
        for name, call in calls(device).items():
            elapsed, value, exc = timed(call)
            what = f"against a stalled device (it sends nothing), {name} with timeout {o.short_timeout_s:g} s"
            got = f"returned {type(value).__name__}" if exc is None else f"raised {type(exc).__name__} ({exc})"
            expect(isinstance(exc, DeviceTimeoutError), f"{what} {got}, expected DeviceTimeoutError")
            expect(elapsed <= limit, f"{what} took {elapsed:.3g} s (more than timeout + {o.timing_slack_s:g} s "
                                     "slack): the timeout is not honoured")


# ---------------------------------------------------------------- resource accounting
def _descriptors() -> dict[int, str]:
    """Open file descriptors of this process and what they point to (Linux; {} elsewhere)."""
    base = "/proc/self/fd"
    if not os.path.isdir(base):
        return {}
    out: dict[int, str] = {}
    for name in os.listdir(base):
        with contextlib.suppress(OSError):
            out[int(name)] = os.readlink(os.path.join(base, name))
    return out


@dataclass
class ResourceSnapshot:
    """Threads and file descriptors alive at one moment."""

    threads: set[threading.Thread]
    descriptors: dict[int, str]

    @classmethod
    def take(cls) -> ResourceSnapshot:
        """Snapshot the current process."""
        return cls(set(threading.enumerate()), _descriptors())

    def leaked_since(self, grace_s: float) -> list[str]:
        """Threads and descriptors opened since this snapshot and still open after ``grace_s``.

        Threads get up to ``grace_s`` (in total) to finish before they count as leaked.
        """
        deadline = time.monotonic() + grace_s
        new_threads = [t for t in threading.enumerate() if t not in self.threads and t.is_alive()]
        for t in new_threads:
            t.join(max(0.0, deadline - time.monotonic()))
        leaks = [f"thread {t.name!r}" for t in new_threads if t.is_alive()]
        now = _descriptors()
        leaks += [f"file descriptor {fd} -> {target}" for fd, target in sorted(now.items())
                  if self.descriptors.get(fd) != target and not target.startswith("/proc/")]
        return leaks


# ---------------------------------------------------------------- running checks
class _Skip(BaseException):  # a BaseException so no check's `except Exception` swallows it
    """Raised by the factory wrapper: this backend hung earlier, its rules are not run again."""


#: Device classes whose call hung in this process -> what hung; their remaining rules are skipped
#: (the hung call still holds the device: running more rules would only hang again).
_HUNG: dict[type, str] = {}


class _LabelledFactory:
    """Wraps a factory: remembers the first device's backend name and class; refuses a hung backend."""

    def __init__(self, factory: Callable[[], Any]):
        self.factory = factory
        self.label = ""
        self.device_class: type | None = None

    def __call__(self) -> Any:
        device = self.factory()
        if not self.label:
            self.label = backend_label(device)
            self.device_class = type(device)
        hung = _HUNG.get(type(device))
        if hung is not None:
            raise _Skip(f"not run: {hung}")
        return device


def _outcome(check: Check[Any, Any], labelled: _LabelledFactory, options: Any) -> tuple[bool, bool, str]:
    """Run one check under the watchdog: ``(passed, skipped, detail)``."""
    watchdog_s = float(getattr(options, "watchdog_s", DEFAULT_WATCHDOG_S))
    try:
        run_watched(functools.partial(check.func, labelled, options), f"cellcal-kit {check.rule}", watchdog_s)
    except Violation as v:
        return False, False, str(v)
    except _Skip as skip:
        return False, True, str(skip)
    except HookHung as hung:
        for cls in {hung.device_class, labelled.device_class} - {None}:
            _HUNG[cls] = f"the backend hung under {check.rule} in {hung.hook}"  # type: ignore[index]
        return False, False, f"{hung}; the remaining rules of this backend are skipped"
    except FrameError as exc:
        if check.rule == FRAME_LAYOUT_RULE:
            return False, False, f"the backend could not build a Frame: {exc}"
        return False, True, f"needs a well-formed frame; the backend could not build one (reported under " \
                            f"{FRAME_LAYOUT_RULE})"
    except Exception as exc:  # the backend raised something the rule did not expect
        return False, False, f"unexpected {type(exc).__name__}: {exc}"
    return True, False, ""


def run_check(check: Check[D, O], factory: Callable[[], D], options: O, backend: str | None = None) -> CheckResult:
    """Run one check under the watchdog and describe its outcome (never raises for a backend's fault).

    Every device call the check makes may take its timeout plus ``options.watchdog_s``;
    a call that overruns fails the rule, naming the hook and the time, and the rules run
    after it for the same backend class are skipped (:mod:`.watchdog`).

    Args:
        check: The check.
        factory: Zero-argument callable returning a new, unconnected device.
        options: The check's options.
        backend: Name for the report; None uses the ``backend_name`` of the devices made.
    """
    labelled = _LabelledFactory(factory)
    t0 = time.monotonic()
    passed, skipped, detail = _outcome(check, labelled, options)
    name = backend or labelled.label or str(getattr(factory, "__name__", "backend"))
    return CheckResult(check.rule, check.summary, name, passed, detail, time.monotonic() - t0, skipped)


def run_checks(kind: str, checks: Iterable[Check[D, O]], factory: Callable[[], D], options: O,
               base: type[Any], only: Iterable[str] | None, raise_on_failure: bool,
               quiet: bool = False) -> ConformanceReport:
    """Run ``checks`` (or the ones named in ``only``) against one backend.

    Unless ``quiet``, each rule's name goes to stderr as it starts, so a slow backend
    shows where it is.
    """
    if not callable(factory) or isinstance(factory, Device):
        raise CellcalError(f"check_{kind} needs a factory (a callable returning a new, unconnected "
                           f"{base.__name__}), got {type(factory).__name__}")
    selected = list(checks)
    if only is not None:
        wanted = set(only)
        unknown = wanted - {c.rule for c in selected}
        if unknown:
            raise CellcalError(f"unknown {kind} contract rule(s): {', '.join(sorted(unknown))}")
        selected = [c for c in selected if c.rule in wanted]
    results = []
    for i, check in enumerate(selected, 1):
        if not quiet:
            print(f"cellcal.testing: {kind} rule {i}/{len(selected)} {check.rule} ...", file=sys.stderr, flush=True)
        results.append(run_check(check, factory, options))
    backend = next((r.backend for r in results), "backend")
    report = ConformanceReport(kind, backend, results)
    if raise_on_failure:
        report.raise_for_failures()
    return report


def find_check(checks: Iterable[Check[D, O]], rule: str) -> Check[D, O]:
    """The check for ``rule``."""
    for c in checks:
        if c.rule == rule:
            return c
    raise CellcalError(f"unknown contract rule {rule!r}")
