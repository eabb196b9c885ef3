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
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

from cellcal.devices.base import Device
from cellcal.devices.errors import CellcalError, ConformanceError

D = TypeVar("D", bound=Device)
O = TypeVar("O")  # noqa: E741 - options type

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
        passed: Whether the backend honoured the rule.
        detail: What was wrong ("" when passed).
        duration_s: Wall time the check took, seconds.
    """

    rule: str
    summary: str
    backend: str
    passed: bool
    detail: str = ""
    duration_s: float = 0.0

    @property
    def message(self) -> str:
        """One line: backend, rule, and what went wrong (or "ok")."""
        if self.passed:
            return f"{self.backend}: {self.rule}: ok"
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
        """True when every check passed."""
        return all(r.passed for r in self.results)

    @property
    def failures(self) -> list[CheckResult]:
        """The failed checks."""
        return [r for r in self.results if not r.passed]

    def raise_for_failures(self) -> None:
        """Raise :class:`ConformanceError` listing every failed rule, if any failed."""
        bad = self.failures
        if bad:
            lines = [f"{self.backend}: {len(bad)} of {len(self.results)} {self.kind} contract checks failed"]
            lines += [f"  - {r.message}" for r in bad]
            raise ConformanceError("\n".join(lines), bad)

    def __str__(self) -> str:
        passed = len(self.results) - len(self.failures)
        head = f"{self.kind} backend {self.backend}: {passed}/{len(self.results)} contract checks passed"
        return "\n".join([head, *(f"  {'PASS' if r.passed else 'FAIL'} {r.rule}"
                                  + ("" if r.passed else f": {r.detail}") for r in self.results)])


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
    """Run ``fn``; return ``(elapsed_s, result, exception)`` (exception None on success)."""
    t0 = time.monotonic()
    try:
        result = fn()
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
class _LabelledFactory:
    """Wraps a factory and remembers the backend name of the first device it made."""

    def __init__(self, factory: Callable[[], Any]):
        self.factory = factory
        self.label = ""

    def __call__(self) -> Any:
        device = self.factory()
        if not self.label:
            self.label = backend_label(device)
        return device


def run_check(check: Check[D, O], factory: Callable[[], D], options: O, backend: str | None = None) -> CheckResult:
    """Run one check and describe its outcome (never raises for a backend's fault).

    Args:
        check: The check.
        factory: Zero-argument callable returning a new, unconnected device.
        options: The check's options.
        backend: Name for the report; None uses the ``backend_name`` of the devices made.
    """
    labelled = _LabelledFactory(factory)
    t0 = time.monotonic()
    passed, detail = True, ""
    try:
        check.func(labelled, options)
    except Violation as v:
        passed, detail = False, str(v)
    except Exception as exc:  # the backend raised something the rule did not expect
        passed, detail = False, f"unexpected {type(exc).__name__}: {exc}"
    name = backend or labelled.label or str(getattr(factory, "__name__", "backend"))
    return CheckResult(check.rule, check.summary, name, passed, detail, time.monotonic() - t0)


def run_checks(kind: str, checks: Iterable[Check[D, O]], factory: Callable[[], D], options: O,
               base: type[Any], only: Iterable[str] | None, raise_on_failure: bool) -> ConformanceReport:
    """Run ``checks`` (or the ones named in ``only``) against one backend."""
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
    results = [run_check(c, factory, options) for c in selected]
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
