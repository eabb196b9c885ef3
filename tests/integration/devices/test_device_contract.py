"""Every built-in backend passes the vendor conformance kit (cellcal.testing).

The simulated and emulated backends run through the pytest classes (one test per
contract rule); the UR and OAK backends run through the function API against their
vendor SDKs replaced by strict autospecs (the fakes of tests/unit/drivers/ur/test_ur.py and
tests/unit/drivers/oak/test_oak.py).
"""

from __future__ import annotations

import itertools
import tomllib
from collections.abc import Callable, Iterator
from importlib import resources
from typing import Any

import numpy as np
import pytest

from cellcal.devices import BackendContext, Camera3D, RobotArm, default_registry
from cellcal.testing import (
    ARM_RULES,
    CAMERA_RULES,
    ArmConformance,
    ArmOptions,
    CameraConformance,
    CameraOptions,
    ScenePlane,
    check_arm,
    check_camera,
)

SIM_DOC: dict[str, Any] = tomllib.loads(resources.files("cellcal.configs").joinpath("sim.toml").read_text())
#: The simulated camera's declared range (sims/camera.py defaults: min_range_m, max_range_m).
SIM_RANGE_M = (0.1, 4.0)
#: What the simulated camera sees without a plan: the table (base z = 0) straight below it, 0.44 m away (the
#: simulated arm's start pose with sim.toml's [mount]).
SIM_SCENE = ScenePlane(normal=(0.0, 0.0, 1.0), axis_distance_m=0.44)


def context(section: str) -> BackendContext:
    return BackendContext(source="<sim.toml>", section=section, document=SIM_DOC, shared={}, seed=3)


def sim_camera(name: str) -> Camera3D:
    return default_registry().create_camera({**SIM_DOC["camera"], "backend": name}, context("camera"))


def sim_arm(name: str) -> RobotArm:
    return default_registry().create_arm({**SIM_DOC["arm"], "backend": name}, context("arm"))


# ---------------------------------------------------------------- simulators and emulators (pytest classes)
class TestSimCamera(CameraConformance):
    options = CameraOptions(distance_range_m=SIM_RANGE_M, scene_plane=SIM_SCENE)

    def make_camera(self) -> Camera3D:
        return sim_camera("sim")


class TestO3REmulatedCamera(CameraConformance):
    options = CameraOptions(distance_range_m=SIM_RANGE_M, scene_plane=SIM_SCENE)

    def make_camera(self) -> Camera3D:
        return sim_camera("o3r-emulated")


class TestSimArm(ArmConformance):
    options = ArmOptions(joint_count=5)

    def make_arm(self) -> RobotArm:
        return sim_arm("sim")


class TestXArmEmulatedArm(ArmConformance):
    options = ArmOptions(joint_count=5)

    @pytest.fixture
    def arm_factory(self) -> Callable[[], RobotArm]:  # the fixture form of the factory
        return lambda: sim_arm("xarm-emulated")


# ---------------------------------------------------------------- UR over mocked ur_rtde (function API)
@pytest.fixture
def ur_factory(mocker: Any) -> Callable[[], RobotArm]:
    test_ur = pytest.importorskip("test_ur")  # skips with it when ur_rtde is not installed
    ctl = test_ur.FakeController()
    mocker.patch.object(test_ur.rtde_receive, "RTDEReceiveInterface", side_effect=ctl.make_receive)
    mocker.patch.object(test_ur.rtde_control, "RTDEControlInterface", side_effect=ctl.make_control)
    mocker.patch.object(test_ur.dashboard_client, "DashboardClient", side_effect=ctl.make_dashboard)
    mocker.patch("cellcal.drivers.ur.dashboard.read_greeting", side_effect=ctl.greeting)  # no socket either

    def make() -> RobotArm:
        arm = test_ur.URArm.from_config({"backend": "ur", "host": test_ur.HOST, "stale_after_s": 0.05,
                                         "isolate": False})
        clock = test_ur.FakeClock()
        arm._clock, arm._sleep = clock, clock.sleep
        arm._probe = ctl.probe          # the connect's plain-socket stream probe: the fake answers, no socket
        return arm

    make.moves = ctl.moves  # type: ignore[attr-defined]
    return make


def test_ur_backend_passes_the_kit(ur_factory: Callable[[], RobotArm]) -> None:
    report = check_arm(ur_factory, ArmOptions(joint_count=6))
    assert report.backend == "ur" and [r.rule for r in report.results] == list(ARM_RULES)
    assert report.ok
    # the round trip really went through the mocked RTDE control interface: there and back, in metres
    moves = ur_factory.moves  # type: ignore[attr-defined]
    assert len(moves) == 6  # the round trip (there and back) and the arrival rule's four moves
    np.testing.assert_allclose(np.subtract(moves[0][0][:3], moves[1][0][:3]), [0.0, 0.0, 0.02], atol=1e-12)


# ---------------------------------------------------------------- OAK over mocked depthai (function API)
@pytest.fixture
def oak_factory(mocker: Any) -> Iterator[Callable[[], Camera3D]]:
    test_oak = pytest.importorskip("test_oak")  # skips with it when depthai is not installed
    dai = test_oak.dai
    seq = itertools.count(1)
    depth = np.full((test_oak.H, test_oak.W), 1200, np.uint16)
    depth[:4, :6] = 0                                     # a patch of invalid pixels

    class StreamingQueue(dai.MessageQueue):  # the real host queue; the device "sends" a frame per read
        def tryGetAll(self) -> list[Any]:  # noqa: N802 - depthai's name
            self.send(test_oak.depth_message(depth, next(seq)))
            return list(super().tryGetAll())

    class StreamingOak(test_oak.FakeOak):
        """A fresh depth queue per pipeline, so one fake serves many connect/close cycles."""

        def output(self) -> Any:
            out = test_oak.strict_autospec(dai.Node.Output)
            out.createOutputQueue.side_effect = lambda maxSize=16, blocking=False: StreamingQueue(
                "depth", maxSize, blocking)
            return out

    fake = StreamingOak()
    mocker.patch.object(dai, "Device", side_effect=fake.open)
    mocker.patch.object(dai, "Pipeline", side_effect=fake.make_pipeline)
    yield lambda: test_oak.OakCamera.from_config({"backend": "oak", "device_id": test_oak.DEVICE_ID,
                                                  "width": test_oak.W, "height": test_oak.H, "isolate": False})


def test_oak_backend_passes_the_kit(oak_factory: Callable[[], Camera3D]) -> None:
    # the fake's 64x40 output holds the grid up to 17 px (a cell with it says so in [plan]); its depth is one
    # noise-free level, which calibrate's stereo fit rightly refuses (it sits on one disparity step)
    options = CameraOptions(distance_range_m=(0.2, 10.0), perimeters_px=(10, 17),
                            scene_reason="the mocked depthai sends one noise-free depth for every pixel")
    report = check_camera(oak_factory, options)
    assert report.backend == "oak" and [r.rule for r in report.results] == list(CAMERA_RULES)
    assert report.ok

