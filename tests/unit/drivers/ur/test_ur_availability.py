"""Where ur_rtde has no wheel (CPython 3.13, macOS, aarch64) the backend says so plainly.

These run on every interpreter: the checks take the platform and version as arguments,
and a missing ur_rtde is made real by blocking its import (``sys.modules[name] = None``).
"""

from __future__ import annotations

import pytest

from cellcal.core.cli import main
from cellcal.devices.errors import MissingDependencyError
from cellcal.devices.registry import default_registry
from cellcal.drivers.ur import availability


@pytest.mark.parametrize(("system", "machine", "version", "has_wheel"), [
    ("Linux", "x86_64", (3, 11), True),
    ("Linux", "x86_64", (3, 12), True),
    ("Windows", "AMD64", (3, 12), True),
    ("Linux", "x86_64", (3, 13), False),
    ("Linux", "aarch64", (3, 12), False),
    ("Darwin", "arm64", (3, 12), False),
])
def test_wheel_matrix_matches_the_extras_markers(system: str, machine: str, version: tuple[int, int],
                                                 has_wheel: bool) -> None:
    reason = availability.no_wheel_reason(system, machine, version)
    assert (reason is None) == has_wheel
    if reason:
        assert f"not for CPython {version[0]}.{version[1]} on {system} {machine}" in reason


@pytest.fixture
def no_ur_rtde(monkeypatch: pytest.MonkeyPatch) -> None:
    """This interpreter as one without a ur-rtde wheel, and ur_rtde not importable."""
    monkeypatch.setattr(availability, "WHEEL_PYTHONS", frozenset())
    for name in ("rtde_control", "rtde_receive"):
        monkeypatch.setitem(__import__("sys").modules, name, None)
    monkeypatch.setattr(availability.importlib.util, "find_spec",
                        lambda name, *a: None if name.startswith("rtde_") else _real_find_spec(name, *a))


_real_find_spec = availability.importlib.util.find_spec


@pytest.mark.usefixtures("no_ur_rtde")
def test_connect_says_not_available_for_this_python() -> None:
    arm = default_registry().create_arm({"backend": "ur", "host": "127.0.0.1"})
    with pytest.raises(MissingDependencyError, match=r"^ur_rtde is not available for this Python: ur-rtde 1\.6"):
        arm.connect(timeout=1.0)


@pytest.mark.usefixtures("no_ur_rtde")
def test_devices_lists_ur_as_unavailable(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["devices"]) == 0
    line = next(ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("  ur "))
    assert "(unavailable: ur_rtde is not available for this Python:" in line
