"""cellcal.testing: the conformance kit for backends, and fake devices for testing cell code.

The kit (docs/adr/0011-conformance-kit.md)::

    from cellcal.testing import CameraOptions, check_camera
    print(check_camera(lambda: AcmeCamera.from_config({}), CameraOptions(distance_range_m=(0.2, 6.0))))

Under pytest, subclass :class:`CameraConformance` / :class:`ArmConformance` instead (see :mod:`.suite`).

Fake devices (docs/testing.md, docs/adr/0033-pytest-plugin.md): :func:`sim_cell`, :func:`sim_camera`,
:func:`sim_arm`, :class:`CellFaults` and the wire emulators :func:`o3r_emulator`, :func:`xarm_emulator`,
:func:`ur_emulator`; the pytest plugin (:mod:`.plugin`) turns them into ``cellcal_*`` fixtures.

Every name loads on first use (PEP 562), so ``import cellcal.testing`` and the pytest plugin cost nothing
until a name is asked for.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # the names as the type checker sees them; at run time they load on first use
    from cellcal.devices.errors import ConformanceError

    from ._runner import Check, CheckResult, ConformanceReport, run_check
    from .arm import ARM_CHECKS, ARM_RULES, ArmOptions, check_arm
    from .camera import CAMERA_CHECKS, CAMERA_RULES, check_camera
    from .camera_options import CameraOptions, ScenePlane
    from .emulators import O3RAddress, URAddress, XArmAddress, o3r_emulator, ur_emulator, xarm_emulator
    from .faults import CellFaults
    from .sim import SimCell, sim_arm, sim_camera, sim_cell
    from .suite import ArmConformance, CameraConformance

#: Public name -> the module (relative to this package, or absolute) that defines it.
_HOMES: dict[str, str] = {
    **dict.fromkeys(("Check", "CheckResult", "ConformanceReport", "run_check"), "._runner"),
    **dict.fromkeys(("ARM_CHECKS", "ARM_RULES", "ArmOptions", "check_arm"), ".arm"),
    **dict.fromkeys(("CAMERA_CHECKS", "CAMERA_RULES", "check_camera"), ".camera"),
    **dict.fromkeys(("CameraOptions", "ScenePlane"), ".camera_options"),
    **dict.fromkeys(("CameraConformance", "ArmConformance"), ".suite"),
    "ConformanceError": "cellcal.devices.errors",
    **dict.fromkeys(("SimCell", "sim_cell", "sim_camera", "sim_arm"), ".sim"),
    **dict.fromkeys(("CellFaults",), ".faults"),
    **dict.fromkeys(("O3RAddress", "XArmAddress", "URAddress", "o3r_emulator", "xarm_emulator", "ur_emulator"),
                    ".emulators"),
}

__all__ = [
    "ARM_CHECKS",
    "ARM_RULES",
    "CAMERA_CHECKS",
    "CAMERA_RULES",
    "ArmConformance",
    "ArmOptions",
    "CameraConformance",
    "CameraOptions",
    "CellFaults",
    "Check",
    "CheckResult",
    "ConformanceError",
    "ConformanceReport",
    "O3RAddress",
    "ScenePlane",
    "SimCell",
    "URAddress",
    "XArmAddress",
    "check_arm",
    "check_camera",
    "o3r_emulator",
    "run_check",
    "sim_arm",
    "sim_camera",
    "sim_cell",
    "ur_emulator",
    "xarm_emulator",
]


def __getattr__(name: str) -> Any:
    """Load ``name`` from its module on first use (the kit needs no pytest, the fakes no kit)."""
    home = _HOMES.get(name)
    if home is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    module = importlib.import_module(home, __name__) if home.startswith(".") else importlib.import_module(home)
    value = getattr(module, name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
