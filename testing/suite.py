"""The conformance kit as pytest test classes: subclass one per backend and override its factory::

    class TestAcmeZ1(CameraConformance):
        options = CameraOptions(distance_range_m=(0.2, 6.0))

        def make_camera(self):
            return AcmeCamera.from_config({"serial": "Z1-TEST"})

A network camera overrides the ``camera_factory`` fixture instead (it starts the fake
device, e.g. on port 0, and yields a factory pointing at it), and may override
``stalled_camera_factory`` with a factory whose device stops answering.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, ClassVar

import pytest

from cellcal.devices.arm import RobotArm
from cellcal.devices.camera import Camera3D

from ._runner import CheckResult, find_check, run_check
from .arm import ARM_CHECKS, ARM_RULES, ArmOptions
from .camera import CAMERA_CHECKS, CAMERA_RULES
from .camera_options import CameraOptions


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

    @pytest.fixture
    def stalled_camera_factory(self) -> Callable[[], Camera3D] | None:
        """Factory of cameras whose device connects and then sends nothing; None (default) skips that part."""
        return None

    @pytest.mark.parametrize("rule", CAMERA_RULES)
    def test_contract(self, camera_factory: Callable[[], Camera3D],
                      stalled_camera_factory: Callable[[], Camera3D] | None, rule: str) -> None:
        """One camera contract rule against the backend."""
        options = _with_stalled(self.options, stalled_camera_factory)
        _conclude(run_check(find_check(CAMERA_CHECKS, rule), camera_factory, options))


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

    @pytest.fixture
    def stalled_arm_factory(self) -> Callable[[], RobotArm] | None:
        """Factory of arms whose device connects and then sends nothing; None (default) skips that part."""
        return None

    @pytest.mark.parametrize("rule", ARM_RULES)
    def test_contract(self, arm_factory: Callable[[], RobotArm], stalled_arm_factory: Callable[[], RobotArm] | None,
                      rule: str) -> None:
        """One arm contract rule against the backend."""
        options = _with_stalled(self.options, stalled_arm_factory)
        _conclude(run_check(find_check(ARM_CHECKS, rule), arm_factory, options))


def _with_stalled(options: Any, stalled: Callable[[], Any] | None) -> Any:
    """``options`` with the stalled-device factory of the fixture (if it gives one)."""
    return options if stalled is None else dataclasses.replace(options, stalled_factory=stalled)


def _conclude(result: CheckResult) -> None:
    """Turn a check result into the test's outcome: pass, skip (an earlier rule failed) or fail."""
    if result.skipped:
        pytest.skip(result.message)
    if not result.passed:
        pytest.fail(result.message, pytrace=False)

