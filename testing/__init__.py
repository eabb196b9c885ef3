"""cellcal.testing: a conformance kit for Camera3D and RobotArm backends.

Point it at your backend to check it honours the device contract — units, frame
shapes and dtypes, timeouts, errors on use after close, idempotent connect/close,
pose round trips. Two ways to use it:

* plain functions, no pytest needed::

      from cellcal.testing import check_camera, CameraOptions
      report = check_camera(lambda: AcmeCamera.from_config({}), CameraOptions(distance_range_m=(0.2, 6.0)))
      print(report)            # raises ConformanceError (naming rule and backend) on a failure

* pytest test classes, one test per contract rule::

      from cellcal.testing import CameraConformance

      class TestAcme(CameraConformance):
          def make_camera(self):
              return AcmeCamera.from_config({})

The kit imports nothing from cellcal's simulators or drivers. See docs/extending.md.
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
