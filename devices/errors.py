"""The one exception tree of cellcal: one ``except CellcalError`` catches every error it raises on purpose::

    CellcalError
    ├── ConfigError                 bad configuration file / section / key
    ├── RegistryError               unknown or duplicate backend name
    ├── MissingDependencyError      a backend's optional extra is not installed
    ├── DeviceError                 anything a device did or failed to do
    │   ├── DeviceConnectionError   could not connect, or the link dropped
    │   ├── DeviceTimeoutError      an I/O call exceeded its timeout
    │   │   └── BackendOverrunError a backend call overran its timeout and was abandoned
    │   ├── NotConnectedError       device used before connect() / after close()
    │   ├── ProtocolError           malformed bytes on a vendor wire
    │   ├── FrameSyncError          two images of one capture came from different captures
    │   ├── VendorError             the device reported an error code
    │   └── MotionError             a move unconfirmed, or not arrived (arm stopped)
    ├── UsbBackendMissingError      pyusb found no native USB library (libusb-1.0)
    ├── MonitorError                a monitored camera keeps failing
    ├── SafetyError                 a command outside the safety envelope
    ├── CalibrationError            bad input to, or failure of, a calibration
    │   ├── CalibrationQualityError a result failed a quality gate
    │   └── FrameError              a Frame's arrays do not have its intrinsics' shape or dtypes
    ├── RecordingError              a recording cannot be written or replayed
    │   ├── RecordingFileError      (also a ConfigError) unreadable or foreign file
    │   ├── ReplayMismatchError     (also a DeviceError) replay asked for something else
    │   ├── ReplayExhaustedError    (also a DeviceError) replay ran out of data
    │   └── RecordingWriteError     (also an OutputError) the recording could not be written
    ├── OutputError                 an output cannot be written (disk full, I/O error, locked)
    └── ConformanceError            (also an AssertionError) a backend broke a contract rule

Messages are one line and name what was wrong, so the CLI prints ``str(err)`` as-is.
"""

from __future__ import annotations

import builtins
from typing import Any

from .readable import quantity_pair


class CellcalError(Exception):
    """Root of every error raised by cellcal."""


class ConfigError(CellcalError, ValueError):
    """A configuration value is missing, unknown, of the wrong type or out of range.

    Args:
        message: What was expected.
        source: The file (or other origin) of the configuration, if known.
        key: Dotted key path inside the document, e.g. ``"arm.speed_m_s"``.
    """

    def __init__(self, message: str, *, source: str | None = None, key: str | None = None):
        self.source = source
        self.key = key
        self.reason = message
        parts = []
        if source:
            parts.append(str(source))
        if key:
            parts.append(f"key '{key}'")
        prefix = ": ".join(parts)
        super().__init__(f"{prefix}: {message}" if prefix else message)


class RegistryError(CellcalError):
    """A backend name is unknown, registered twice, or its entry point fails to load."""


class MissingDependencyError(CellcalError, ImportError):
    """A backend needs an optional dependency (an extra) that is not installed.

    Args:
        what: The missing module or SDK, e.g. ``"depthai"``.
        extra: The extra that installs it, e.g. ``"oak"``.
        package: The distribution that declares the extra (a vendor package names its own).
        reason: Why it cannot be installed here (no wheel for this Python or platform); replaces
            the install hint when given.
    """

    def __init__(self, what: str, extra: str, *, package: str = "cellcal", reason: str | None = None):
        self.extra = extra
        self.package = package
        self.reason = reason
        if reason:
            super().__init__(f"{what} is not available for this Python: {reason}")
        else:
            super().__init__(f"{what} is not installed; install it with: pip install '{package}[{extra}]'")


class DeviceError(CellcalError):
    """Base of all device-side failures."""


class DeviceConnectionError(DeviceError, builtins.ConnectionError):
    """Connecting failed, or an established link to a device was lost."""


class NativeCrashError(DeviceConnectionError):
    """The worker process running a backend's native library died (a segfault, an abort).

    cellcal itself is unharmed; every connection the library held is gone with the process.

    Args:
        message: One line naming the backend, the call and how the process ended.
        backend: The backend's name, e.g. ``"ur"``.
        signal_name: The signal that ended the process (``"SIGSEGV"``), or "" for an exit status.
    """

    def __init__(self, message: str, *, backend: str = "", signal_name: str = ""):
        super().__init__(message)
        self.backend = backend
        self.signal_name = signal_name


class DeviceTimeoutError(DeviceError, builtins.TimeoutError):
    """A device I/O call did not complete within its timeout."""


class BackendOverrunError(DeviceTimeoutError):
    """A backend call did not return within its timeout plus a grace period; the caller abandoned it.

    Raised by callers that do not trust a backend to honour its timeout (the calibrator,
    the monitor). The message names the backend and the call.
    """


class NotConnectedError(DeviceError):
    """A device was used before ``connect()`` or after ``close()``."""


class ProtocolError(DeviceError):
    """Bytes received from a device do not follow its wire protocol.

    Args:
        message: What was wrong.
        offset: Byte offset in the message or stream where it was detected.
    """

    def __init__(self, message: str, *, offset: int | None = None):
        self.offset = offset
        super().__init__(f"{message} (at byte offset {offset})" if offset is not None else message)


class FrameSyncError(DeviceError):
    """Images a device sent as one capture (e.g. depth and its grey image) belong to different captures."""


class VendorError(DeviceError):
    """The device reported an error through its own error-code channel.

    Args:
        vendor: Short vendor/backend name, e.g. ``"xarm"``.
        code: The vendor's numeric error code.
        meaning: Human-readable meaning of the code.
    """

    def __init__(self, vendor: str, code: int, meaning: str):
        self.vendor = vendor
        self.code = code
        self.meaning = meaning
        super().__init__(f"{vendor} error {code}: {meaning}")


class SafetyError(CellcalError):
    """A motion command lies outside the configured safety envelope; nothing moved."""


class CalibrationError(CellcalError, ValueError):
    """Bad input to a calibration computation, or a calibration that cannot be computed."""


class CalibrationQualityError(CalibrationError):
    """A calibration result failed a quality gate.

    The attributes keep SI units; the message shows a length in millimetres and an angle in
    degrees, with as many digits as it takes for the value and the threshold to read differently.

    Args:
        gate: Name of the gate, e.g. ``"inlier_fraction"``.
        value: The measured value, in ``unit``.
        threshold: The configured threshold it failed, in ``unit``.
        message: Optional extra explanation.
        unit: The SI unit of ``value`` and ``threshold``: ``"m"``, ``"rad"``, or ``""`` for a
            plain number (a fraction, a ratio, a count).
    """

    def __init__(self, gate: str, value: float, threshold: float, message: str = "", *, unit: str = ""):
        self.gate = gate
        self.value = value
        self.threshold = threshold
        self.unit = unit
        shown, limit = quantity_pair(value, threshold, unit, digits=6)
        text = f"quality gate '{gate}' failed: {shown} vs threshold {limit}"
        super().__init__(f"{text}; {message}" if message else text)


class FrameError(CalibrationError):
    """A :class:`~cellcal.devices.types.Frame` was built from arrays of the wrong shape or dtype.

    A ``CalibrationError`` (what ``Frame`` raised before this class existed), so existing
    handlers still catch it; the conformance kit reports it under ``camera.frame-layout``.
    """


class UsbBackendMissingError(CellcalError):
    """``pyusb`` is installed but found no native USB library (libusb-1.0)."""


class MonitorError(CellcalError):
    """A monitored camera keeps failing (capture timeouts or no plane in its frames)."""


class RecordingError(CellcalError):
    """A recording cannot be written, or a replay cannot go on."""


class RecordingFileError(RecordingError, ConfigError):
    """A recording file is missing, unreadable, truncated, corrupt or of another format."""


class ReplayMismatchError(RecordingError, DeviceError):
    """The replayed session asked for something else than the recorded one did."""


class ReplayExhaustedError(RecordingError, DeviceError):
    """The replayed session asked for more data than the recording holds."""


class ConformanceError(CellcalError, AssertionError):
    """One or more contract rules of the conformance kit (:mod:`cellcal.testing`) were violated.

    Derives from ``AssertionError`` so pytest reports it as a test failure.

    Attributes:
        failures: The failed checks (``cellcal.testing.CheckResult`` objects).
    """

    def __init__(self, message: str, failures: list[Any]):
        self.failures = failures
        super().__init__(message)


class OutputError(CellcalError):
    """An output (result file, resume journal, recording, output lock) cannot be written.

    Args:
        message: What failed, naming the path.
        errno: The operating system's error number, if the cause was an ``OSError``.

    :attr:`bad_path` tells the two kinds apart: the path itself cannot be used (no
    such directory, not a directory, no permission, read-only file system — the
    command line must change; exit status 2), or the environment failed while
    writing (disk full, I/O error, another run holds the output; exit status 1).
    """

    def __init__(self, message: str, *, errno: int | None = None):
        self.errno = errno
        super().__init__(message)

    @property
    def bad_path(self) -> bool:
        """Whether the path cannot be used at all (rather than the writing failing)."""
        import errno as e

        return self.errno in {e.EACCES, e.EPERM, e.EROFS, e.ENOTDIR, e.EISDIR, e.ENOENT, e.ENAMETOOLONG,
                              e.ELOOP, e.EEXIST, e.EINVAL}


class RecordingWriteError(RecordingError, OutputError):
    """A recording cannot be written (an :class:`OutputError` of the recorder)."""


class MotionError(DeviceError):
    """A motion did not happen as commanded, or cannot be confirmed: the arm may not be where it was sent.

    Raised when a motion command got no valid reply (it is never resent), when contact was
    lost while the arm moved, or when the read-back pose of a finished move is not at the
    target or not steady. The arm has been told to stop whenever its state was in doubt.
    """
