"""The ACME R1 arm backend: the cellcal conformance kit against it, plus its own promises.

Run against the installed package (``pip install ".[test]"`` then ``pytest``): the entry
point test needs the distribution's metadata, as cellcal itself does.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from cellcal.devices import DeviceTimeoutError, Pose, VendorError, default_registry
from cellcal.testing import ARM_RULES, ArmConformance, ArmOptions, check_arm

from acme_cellcal.arm import AcmeR1Arm
from acme_cellcal.r1_controller import ERR_UNREACHABLE

#: Motion of the stand-in controller 100x faster than real time.
FAST = {"time_scale": 0.01}


def make_r1(**keys: object) -> AcmeR1Arm:
    """An unconnected ``acme-r1`` arm, built from a config table as cellcal would."""
    return AcmeR1Arm.from_config({**FAST, **keys})


# ---------------------------------------------------------------- the kit, one test per contract rule
class TestAcmeR1Conformance(ArmConformance):
    """Every arm contract rule against the R1 (a six-axis arm: six joints)."""

    options = ArmOptions(joint_count=6, max_reach_m=0.85)

    def make_arm(self) -> AcmeR1Arm:
        return make_r1()


def test_kit_function_api_passes_too() -> None:
    report = check_arm(make_r1, ArmOptions(joint_count=6), quiet=True)
    assert report.ok and report.backend == "acme-r1" and len(report.results) == len(ARM_RULES)


# ---------------------------------------------------------------- the arm's own promises
def test_registered_through_the_entry_point() -> None:
    registry = default_registry()
    assert registry.get("arm", "acme-r1") is AcmeR1Arm
    (entry,) = [e for e in registry.entries("arm") if e.name == "acme-r1"]
    assert entry.origin == "cellcal-acme-camera 0.1.0" and entry.target == "acme_cellcal.arm:AcmeR1Arm"


def test_the_controllers_millimetres_and_degrees_become_metres_and_radians() -> None:
    with make_r1() as arm:
        home = arm.get_pose(1.0)                       # the R1 starts at (400, 0, 500) mm, roll 180 deg
        assert np.allclose(home.translation, [0.4, 0.0, 0.5], atol=1e-12)
        assert math.degrees(home.angle_to(Pose.from_xyz_rpy([0.4, 0.0, 0.5], [math.pi, 0.0, 0.0]))) < 1e-9
        target = Pose.from_xyz_rpy([0.35, 0.1, 0.45], [math.pi, 0.0, math.radians(30.0)])
        arm.move_linear(target, speed=0.25, acceleration=2.5, timeout=5.0)
        reached = arm.get_pose(1.0)
        assert reached.distance_to(target) < 1e-9 and reached.angle_to(target) < 1e-9
        joints = arm.joint_positions(1.0)
        assert joints.shape == (6,) and math.degrees(joints[0]) == pytest.approx(math.degrees(math.atan2(0.1, 0.35)))


def test_a_move_out_of_reach_is_the_controllers_error_and_nothing_moves() -> None:
    with make_r1() as arm:
        start = arm.get_pose(1.0)
        with pytest.raises(VendorError, match="out of reach") as info:
            arm.move_linear(Pose.from_xyz_rpy([0.9, 0.0, 0.5], [math.pi, 0.0, 0.0]), speed=0.25, acceleration=2.5)
        assert info.value.code == ERR_UNREACHABLE
        assert arm.get_pose(1.0).distance_to(start) == 0.0
        assert arm.status(1.0).error_code == ERR_UNREACHABLE and not arm.status(1.0).can_move
        arm.clear_errors(1.0)
        assert arm.status(1.0).ok


def test_a_move_longer_than_its_timeout_is_stopped_on_the_way() -> None:
    with AcmeR1Arm.from_config({"time_scale": 1.0}) as arm:   # real time: 0.2 m at 0.05 m/s takes 5 s
        start = arm.get_pose(1.0)
        target = Pose(start.rotation, start.translation + np.array([0.0, 0.2, 0.0]))
        with pytest.raises(DeviceTimeoutError, match=r"did not finish within 0\.2 s; the arm was told to stop"):
            arm.move_linear(target, speed=0.05, acceleration=0.5, timeout=0.2)
        stopped = arm.get_pose(1.0)
        assert 0.0 < stopped.distance_to(start) < 0.02       # it had started, and stopped far from the target
        assert arm.get_pose(1.0).distance_to(stopped) == 0.0  # and stays there
