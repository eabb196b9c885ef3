"""Contract rules every device shares: factory, life cycle, identity, resources.

:func:`lifecycle_checks` builds them for one interface from two small callables: the
operations that must refuse to run while disconnected, and a typical use of a
connected device (a capture, a pose read).
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from cellcal.devices.base import Device
from cellcal.devices.errors import CellcalError, NotConnectedError
from cellcal.devices.types import DeviceInfo

from ._runner import DEFAULT_WATCHDOG_S, Check, ResourceSnapshot, connected, expect, make, raises


@dataclass(frozen=True)
class CommonOptions:
    """Options shared by camera and arm checks.

    Attributes:
        connect_timeout_s: Timeout passed to ``connect()``, seconds.
        short_timeout_s: Timeout of the bounded-time checks, seconds.
        timing_slack_s: How much longer than its timeout a call may take, seconds.
        check_resources: Whether a connect/close cycle must leave no thread or descriptor open.
        watchdog_s: How long any device call may run beyond its own timeout (in total, for a
            call without one) before the kit reports it hung, names the hook and moves on, seconds.
        stalled_factory: Optional zero-argument callable returning a new, unconnected device
            whose link connects but whose device then sends nothing (a stalled emulator or
            fake device). ``*.timeout-bounded`` then also requires every short-timeout call
            on it to raise DeviceTimeoutError in time: an ignored timeout passes against a
            device that answers at once, not against one that does not answer.
    """

    connect_timeout_s: float = 10.0
    short_timeout_s: float = 0.25
    timing_slack_s: float = 2.0
    check_resources: bool = True
    watchdog_s: float = DEFAULT_WATCHDOG_S
    stalled_factory: Callable[[], Any] | None = None

    def _require_positive(self, *names: str) -> None:
        if self.stalled_factory is not None and not callable(self.stalled_factory):
            raise CellcalError(f"{type(self).__name__}.stalled_factory must be a callable returning a new, "
                               f"unconnected device, got {type(self.stalled_factory).__name__}")
        for name in ("connect_timeout_s", "short_timeout_s", "timing_slack_s", "watchdog_s", *names):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value)
                                                                                      and value > 0):
                raise CellcalError(f"{type(self).__name__}.{name} must be a positive number, got {value!r}")


Refusals = Callable[[Any], dict[str, Callable[[], object]]]
Use = Callable[[Any, Any], object]


class _BodyError(Exception):
    """Raised inside a with block to see that __exit__ closes the device."""


@dataclass(frozen=True)
class _SharedRules:
    """The shared rules for one interface; each method is one check ``(factory, options)``.

    Attributes:
        kind: ``"camera"`` or ``"arm"`` (rule prefix and config section name).
        base: The interface, :class:`Camera3D` or :class:`RobotArm`.
        refusals: ``refusals(device)`` -> operations (by name) that must raise
            NotConnectedError while the device is not connected.
        use: ``use(device, options)`` exercises a connected device.
    """

    kind: str
    base: type[Any]
    refusals: Refusals
    use: Use

    def _refuse_all(self, device: Device, when: str) -> None:
        for what, call in self.refusals(device).items():
            raises(NotConnectedError, call, f"{what} {when}")

    def factory_check(self, factory: Callable[[], Device], o: CommonOptions) -> None:
        cls = type(make(factory, self.base))
        expect(isinstance(cls.backend_name, str) and cls.backend_name,
               f"{cls.__name__}.backend_name must be a non-empty string (the name used in configs)")
        expect(dataclasses.is_dataclass(getattr(cls, "Config", None)),
               f"{cls.__name__}.Config must be a dataclass (from_config validates the [{self.kind}] table "
               "against it)")

    def not_connected(self, factory: Callable[[], Device], o: CommonOptions) -> None:
        self._refuse_all(make(factory, self.base), "before connect()")

    def connect_idempotent(self, factory: Callable[[], Device], o: CommonOptions) -> None:
        device = make(factory, self.base)
        try:
            expect(device.connect(o.connect_timeout_s) is device, "connect() must return the device itself")
            expect(device.connected, "connected is False after connect()")
            device.connect(o.connect_timeout_s)
            expect(device.connected, "a second connect() disconnected the device")
            self.use(device, o)  # still usable after the second connect
        finally:
            device.close()
        expect(not device.connected, "connected is True after close()")
        device.close()  # a second close must be a no-op

    def use_after_close(self, factory: Callable[[], Device], o: CommonOptions) -> None:
        with connected(factory, self.base, o.connect_timeout_s) as device:
            self.use(device, o)
        self._refuse_all(device, "after close()")

    def context_manager(self, factory: Callable[[], Device], o: CommonOptions) -> None:
        device = make(factory, self.base)
        with device as inside:
            expect(inside is device, "__enter__ must return the device itself")
            expect(device.connected, "not connected inside the with block")
        expect(not device.connected, "still connected after the with block")
        second = make(factory, self.base)
        with contextlib.suppress(_BodyError), second:
            raise _BodyError
        expect(not second.connected, "an exception inside the with block left the device connected")

    def info(self, factory: Callable[[], Device], o: CommonOptions) -> None:
        with connected(factory, self.base, o.connect_timeout_s) as device:
            value = device.info()
        expect(isinstance(value, DeviceInfo), f"info() returned {type(value).__name__}, not DeviceInfo")
        for name in ("backend", "vendor", "model"):
            field = getattr(value, name)
            expect(isinstance(field, str) and field.strip(), f"DeviceInfo.{name} must be a non-empty string, "
                                                              f"got {field!r}")
        for name in ("serial", "firmware"):
            expect(isinstance(getattr(value, name), str), f"DeviceInfo.{name} must be a string")
        expect(isinstance(value.extra, dict), "DeviceInfo.extra must be a dict")

    def releases_resources(self, factory: Callable[[], Device], o: CommonOptions) -> None:
        if not o.check_resources:
            return
        with connected(factory, self.base, o.connect_timeout_s) as device:  # warm-up: lazy imports, global state
            self.use(device, o)
        before = ResourceSnapshot.take()
        with connected(factory, self.base, o.connect_timeout_s) as device:
            self.use(device, o)
        leaks = before.leaked_since(o.timing_slack_s)
        expect(not leaks, "close() left open: " + ", ".join(leaks))


def lifecycle_checks(kind: str, base: type[Any], refusals: Refusals, use: Use
                     ) -> tuple[tuple[Check[Any, Any], ...], Check[Any, Any]]:
    """The shared rules for one interface.

    Args:
        kind: ``"camera"`` or ``"arm"`` (rule prefix and config section name).
        base: The interface, :class:`Camera3D` or :class:`RobotArm`.
        refusals: ``refusals(device)`` -> operations (by name) that must raise
            NotConnectedError while the device is not connected.
        use: ``use(device, options)`` exercises a connected device.

    Returns:
        ``(first, last)``: the checks that run first (factory, life cycle, info) and the
        resource check that runs last.
    """
    rules = _SharedRules(kind, base, refusals, use)
    name = base.__name__
    first: tuple[Check[Any, Any], ...] = (
        Check(f"{kind}.factory", f"the factory returns an unconnected {name} with backend_name and a Config dataclass",
              rules.factory_check),
        Check(f"{kind}.not-connected", "every operation raises NotConnectedError before connect()",
              rules.not_connected),
        Check(f"{kind}.connect-idempotent", "connect() twice and close() twice are harmless",
              rules.connect_idempotent),
        Check(f"{kind}.use-after-close", "every operation raises NotConnectedError after close()",
              rules.use_after_close),
        Check(f"{kind}.context-manager", "a with block connects and always closes", rules.context_manager),
        Check(f"{kind}.info", "info() returns a DeviceInfo with backend, vendor and model", rules.info),
    )
    last = Check(f"{kind}.releases-resources", "close() leaves no thread or file descriptor open",
                 rules.releases_resources)
    return first, last
