"""Life cycle shared by every device: connect/close, context manager, timeouts.

The public methods of :class:`Device` and its two interfaces are *template
methods*: they check the life cycle and the arguments once, here, then call the
backend's underscore method. A backend therefore only writes the vendor-specific
part, and cannot forget a contract rule (a closed device raising
:class:`NotConnectedError`, a timeout that must be positive and finite, ...).
"""

from __future__ import annotations

import contextlib
import math
import threading
from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any, ClassVar, Literal, Self

from .config import parse_section
from .errors import CellcalError, NotConnectedError
from .types import DeviceInfo

if TYPE_CHECKING:
    from .pose import Pose


@dataclass(frozen=True)
class CameraPlacement:
    """Where a camera of a cell of several is configured to stand (``[[cameras]]``; ADR 0061).

    Attributes:
        name: The camera's name.
        on: ``"flange"`` (carried by the arm) or ``"base"`` (fixed in the cell).
        pose: ``T_flange_camera`` on the flange, ``T_base_camera`` fixed: the configured (nominal) pose;
            a simulated camera stands there unless its ``[sim]`` truth says otherwise.
    """

    name: str
    on: Literal["flange", "base"]
    pose: Pose


@dataclass
class BackendContext:
    """What a backend factory gets besides its own config section.

    Attributes:
        source: File the configuration came from (for error messages), or None.
        section: Name of the backend's section in the document, e.g. ``"camera"``.
        document: The whole configuration document (read-only by convention); simulated
            backends read their shared ``[sim]`` table from it.
        shared: Objects shared between the backends built from one document (e.g. the
            simulated world that couples a simulated camera to a simulated arm).
        seed: Seed for any randomness, from the document's ``[cell] seed``.
        placement: A camera of ``[[cameras]]`` other than the one the document's ``[camera]`` and
            ``[mount]`` describe: where it is configured to stand (None: that one camera).
        camera_names: Every camera of the cell (``[[cameras]]``' names; empty when unknown), e.g. for a
            simulator to check the names of its truths.
    """

    source: str | None = None
    section: str = ""
    document: Mapping[str, Any] = field(default_factory=dict)
    shared: dict[str, Any] = field(default_factory=dict)
    seed: int = 0
    placement: CameraPlacement | None = None
    camera_names: tuple[str, ...] = ()

    @property
    def base_dir(self) -> Path:
        """Directory of the configuration file (relative paths in it resolve from here)."""
        return Path(self.source).resolve().parent if self.source else Path.cwd()


class Device(ABC):
    """Base of :class:`Camera3D` and :class:`RobotArm`.

    Subclasses set :attr:`backend_name` and a ``Config`` dataclass, implement
    :meth:`_connect`, :meth:`_close` and :meth:`_info`, and take
    ``(config, context)`` in their constructor.

    Attributes:
        default_timeout_s: Timeout used when an I/O call is given ``timeout=None``.
    """

    backend_name: ClassVar[str] = ""
    Config: ClassVar[type[Any]]
    #: The backend calls a native (C/C++) library that can crash the process: it runs that library
    #: in a worker process (:class:`~cellcal.devices.isolation.NativeHost`) so a crash is a
    #: :class:`~cellcal.devices.errors.NativeCrashError` (ADR 0038).
    wraps_native_code: ClassVar[bool] = False
    default_timeout_s: float = 2.0

    def __init__(self) -> None:
        self._connected = False
        self._lifecycle_lock = threading.RLock()

    # ------------------------------------------------------------ config factory
    @classmethod
    def from_config(cls, section: Mapping[str, Any] | None, context: BackendContext | None = None) -> Self:
        """Validate ``section`` against ``cls.Config`` and build the (unconnected) device.

        Raises:
            ConfigError: On unknown, missing or wrong-typed keys, naming them.
        """
        context = context or BackendContext()
        config = parse_section(cls.Config, section, where=context.section, source=context.source,
                               ignore=("backend",))
        return cls(config, context)  # type: ignore[call-arg]

    @classmethod
    def unavailable_reason(cls) -> str | None:
        """Why this backend cannot be used on this machine (a missing SDK), or None if it can.

        Must be cheap (``importlib.util.find_spec``, never an SDK import): ``cellcal devices``
        calls it for every backend it lists.
        """
        return None

    @classmethod
    def discover(cls, timeout: float = 2.0) -> list[DeviceInfo] | None:
        """Devices of this backend that can be reached now (``cellcal devices --scan``).

        Args:
            timeout: Seconds to spend looking.

        Returns:
            The devices found (possibly empty), or None when this backend has no way
            to discover devices (the default).

        Raises:
            MissingDependencyError: If discovery needs an extra that is not installed.
        """
        return None

    # ------------------------------------------------------------ life cycle
    @property
    def connected(self) -> bool:
        """Whether the device is connected and usable."""
        return self._connected

    @property
    def connect_timeout_s(self) -> float:
        """Seconds a caller should give :meth:`connect`: :attr:`default_timeout_s`, more for a backend that
        first starts what it talks to (an emulator process)."""
        return float(self.default_timeout_s)

    def connect(self, timeout: float | None = None) -> Self:
        """Connect to the device; a no-op when already connected.

        Args:
            timeout: Seconds to wait for the device; None uses :attr:`connect_timeout_s`.

        Returns:
            The device itself, so ``cam = Backend(...).connect()`` reads naturally.

        Raises:
            DeviceConnectionError: If the device cannot be reached.
            DeviceTimeoutError: If it does not answer within the timeout.
        """
        with self._lifecycle_lock:
            if not self._connected:
                t = self.connect_timeout_s if timeout is None else self._resolve_timeout(timeout)
                try:
                    self._connect(t)
                except BaseException:
                    with contextlib.suppress(Exception):  # best effort; the first error matters
                        self._close()
                    raise
                self._connected = True
        return self

    def close(self) -> None:
        """Release the device; safe to call more than once."""
        with self._lifecycle_lock:
            if self._connected:
                self._connected = False
                self._close()

    def __enter__(self) -> Self:
        return self.connect()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def info(self) -> DeviceInfo:
        """Identity of the connected device.

        Raises:
            NotConnectedError: If the device is not connected.
        """
        self._require_connected("info")
        return self._info()

    # ------------------------------------------------------------ helpers for subclasses
    def _require_connected(self, operation: str) -> None:
        if not self._connected:
            name = self.backend_name or type(self).__name__
            raise NotConnectedError(f"{name}: cannot {operation}: device is not connected (call connect() first)")

    def _resolve_timeout(self, timeout: float | None) -> float:
        if timeout is None:
            return float(self.default_timeout_s)
        if isinstance(timeout, bool) or not isinstance(timeout, (int, float)):
            raise CellcalError(f"timeout must be a number of seconds, got {timeout!r}")
        if not (math.isfinite(timeout) and timeout > 0):
            raise CellcalError(f"timeout must be a positive finite number of seconds, got {timeout!r}")
        return float(timeout)

    # ------------------------------------------------------------ backend hooks
    @abstractmethod
    def _connect(self, timeout: float) -> None:
        """Open the link to the device within ``timeout`` seconds."""

    @abstractmethod
    def _close(self) -> None:
        """Release every resource (threads, sockets, ports); must not raise."""

    @abstractmethod
    def _info(self) -> DeviceInfo:
        """Return the identity of the connected device."""
