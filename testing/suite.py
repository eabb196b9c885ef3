"""The conformance kit as pytest test classes: subclass one per backend and override its factory::

    class TestAcmeZ1(CameraConformance):
        options = CameraOptions(distance_range_m=(0.2, 6.0))

        def make_camera(self):
            return AcmeCamera.from_config({"serial": "Z1-TEST"})
"""

from __future__ import annotations

from collections.abc import Callable
from typing import ClassVar

import pytest

from cellcal.devices.arm import RobotArm
from cellcal.devices.camera import Camera3D

from ._runner import find_check, run_check
from .arm import ARM_CHECKS, ARM_RULES, ArmOptions
from .camera import CAMERA_CHECKS, CAMERA_RULES, CameraOptions


class CameraConformance:
    """Base class of a camera backend's conformance tests (not collected by itself).

    Each contract rule is one test, ``test_contract[<rule>]``, so a failure names the
    rule and ``-k frame-units`` selects one. A backend that needs other fixtures to be
    built (a mocked SDK, a temporary file) overrides the ``camera_factory`` fixture
    instead of :meth:`make_camera`, or sets things up in an autouse fixture of its own.

    Attributes:
        options: What the backend declares (distance range, tolerances).
    """

    options: ClassVar[CameraOptions] = CameraOptions()

    def make_camera(self) -> Camera3D:
        """Return a new, unconnected camera of the backend under test (override this)."""
        raise NotImplementedError(f"{type(self).__name__} must override make_camera() or the camera_factory fixture")

    @pytest.fixture
    def camera_factory(self) -> Callable[[], Camera3D]:
        """Zero-argument callable returning a new, unconnected camera; defaults to :meth:`make_camera`."""
        return self.make_camera

    @pytest.mark.parametrize("rule", CAMERA_RULES)
    def test_contract(self, camera_factory: Callable[[], Camera3D], rule: str) -> None:
        """One camera contract rule against the backend."""
        result = run_check(find_check(CAMERA_CHECKS, rule), camera_factory, self.options)
        if not result.passed:
            pytest.fail(result.message, pytrace=False)


class ArmConformance:
    """Base class of an arm backend's conformance tests (not collected by itself).

    Works like :class:`CameraConformance`, with :meth:`make_arm` / the ``arm_factory`` fixture.

    Attributes:
        options: Round-trip step, tolerances and timeouts for the backend.
    """

    options: ClassVar[ArmOptions] = ArmOptions()

    def make_arm(self) -> RobotArm:
        """Return a new, unconnected arm of the backend under test (override this)."""
        raise NotImplementedError(f"{type(self).__name__} must override make_arm() or the arm_factory fixture")

    @pytest.fixture
    def arm_factory(self) -> Callable[[], RobotArm]:
        """Zero-argument callable returning a new, unconnected arm; defaults to :meth:`make_arm`."""
        return self.make_arm

    @pytest.mark.parametrize("rule", ARM_RULES)
    def test_contract(self, arm_factory: Callable[[], RobotArm], rule: str) -> None:
        """One arm contract rule against the backend."""
        result = run_check(find_check(ARM_CHECKS, rule), arm_factory, self.options)
        if not result.passed:
            pytest.fail(result.message, pytrace=False)

