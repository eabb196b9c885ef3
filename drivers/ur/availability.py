"""Whether ur_rtde can be used here, and if not, why — without importing it.

ur-rtde 1.6 publishes wheels for CPython 3.11 and 3.12 on Linux x86_64 and Windows only;
elsewhere the ``ur`` extra installs nothing (environment markers in pyproject.toml), so the
backend must say plainly that ur_rtde is not available for this Python.
"""

from __future__ import annotations

import importlib.util
import platform
import sys

from cellcal.devices.errors import MissingDependencyError

#: (system, machine) pairs ur-rtde 1.6 ships wheels for, and the CPython versions it covers.
WHEEL_PLATFORMS = frozenset({("Linux", "x86_64"), ("Windows", "AMD64")})
WHEEL_PYTHONS = frozenset({(3, 11), (3, 12)})


def no_wheel_reason(system: str | None = None, machine: str | None = None,
                    version: tuple[int, int] | None = None) -> str | None:
    """Why no ur-rtde wheel exists for this interpreter, or None if one does.

    Args:
        system: ``platform.system()`` (default: this machine's).
        machine: ``platform.machine()`` (default: this machine's).
        version: (major, minor) of CPython (default: this interpreter's).
    """
    system = system or platform.system()
    machine = machine or platform.machine()
    version = version or (sys.version_info.major, sys.version_info.minor)
    if (system, machine) in WHEEL_PLATFORMS and version in WHEEL_PYTHONS:
        return None
    return (f"ur-rtde 1.6 publishes wheels for CPython 3.11-3.12 on Linux x86_64 and Windows only, "
            f"not for CPython {version[0]}.{version[1]} on {system} {machine}")


def missing_error() -> MissingDependencyError:
    """The error to raise when ``import rtde_control`` fails."""
    return MissingDependencyError("ur_rtde", "ur", reason=no_wheel_reason())


def unavailable_reason() -> str | None:
    """None if ur_rtde is importable; else one line saying why not (for ``cellcal devices``)."""
    if importlib.util.find_spec("rtde_control") is not None:
        return None
    return str(missing_error())
