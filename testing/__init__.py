"""cellcal.testing: the conformance kit for Camera3D and RobotArm backends (docs/adr/0011-conformance-kit.md)::

    from cellcal.testing import CameraOptions, check_camera
    print(check_camera(lambda: AcmeCamera.from_config({}), CameraOptions(distance_range_m=(0.2, 6.0))))

Under pytest, subclass :class:`CameraConformance` / :class:`ArmConformance` instead (see :mod:`.suite`).
"""

from __future__ import annotations

from typing import Any

from cellcal.devices.errors import ConformanceError

from ._runner import Check, CheckResult, ConformanceReport, run_check
from .arm import ARM_CHECKS, ARM_RULES, ArmOptions, check_arm
from .camera import CAMERA_CHECKS, CAMERA_RULES, CameraOptions, check_camera

__all__ = [
    "ARM_CHECKS",
    "ARM_RULES",
    "CAMERA_CHECKS",
    "CAMERA_RULES",
    "ArmConformance",
    "ArmOptions",
    "CameraConformance",
    "CameraOptions",
    "Check",
    "CheckResult",
    "ConformanceError",
    "ConformanceReport",
    "check_arm",
    "check_camera",
    "run_check",
]


def __getattr__(name: str) -> Any:
    """The pytest classes load on first use, so the function API works without pytest."""
    if name in ("CameraConformance", "ArmConformance"):
        from . import suite

        return getattr(suite, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
