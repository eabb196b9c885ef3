"""UR backend over ur_rtde, mocked at the library boundary with the real classes' signatures.

A small controller model (:class:`FakeController`) plays the robot: it advances its
RTDE timestamp, carries out asynchronous ``moveL`` over a few polls, and can be
protective-stopped mid-motion or lose its receive stream. The RTDE interfaces handed
to the backend are strict autospecs of the real ``rtde_control.RTDEControlInterface``,
``rtde_receive.RTDEReceiveInterface`` and ``dashboard_client.DashboardClient``. These
tests pin the driver's decisions on exact call sequences; the real conversation with
ur_rtde is tested against the emulator in tests/integration/ur/.
"""

from __future__ import annotations

import math
import re
import sys
import threading
from typing import Any

import numpy as np
import pytest
from repo_paths import REPO_ROOT

pytest.importorskip("rtde_control")
import dashboard_client
import rtde_control
import rtde_receive
from _vendor_autospec import pybind_signatures, strict_autospec
from scipy.spatial.transform import Rotation

from cellcal.devices.base import BackendContext
from cellcal.devices.errors import (
    ConfigError,
    DeviceConnectionError,
    DeviceTimeoutError,
    MissingDependencyError,
    MotionError,
    ProtocolError,
    SafetyError,
    VendorError,
)
from cellcal.devices.geometry.vendor_poses import pose_from_xarm, pose_to_ur, pose_to_xarm
from cellcal.devices.pose import Pose
from cellcal.devices.registry import default_registry
from cellcal.drivers.ur.arm import URArm
from cellcal.drivers.ur.codes import FLAG_NO_WAIT

HOST = "192.168.56.101"
# The real classes, kept before the fixtures patch the module attributes.
REAL_CONTROL = rtde_control.RTDEControlInterface
REAL_RECEIVE = rtde_receive.RTDEReceiveInterface
REAL_DASHBOARD = dashboard_client.DashboardClient
REAL_ASYNC_STATUS = rtde_control.AsyncOperationStatus


class FakeClock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t

    def sleep(self, dt: float) -> None:
        self.t += dt


class FakeController:
    """The robot side: state read by the receive mocks, changed by the control mocks."""

    def __init__(self) -> None:
        self.timestamp = 50.0
        self.pose = [0.30, -0.10, 0.45, math.pi, 0.0, 0.0]
        self.q = [0.0, -1.57, 1.2, -1.2, -1.57, 0.3]
        self.safety = 1
        self.robot = 7
        self.program = True
        self.motion: list[float] | None = None
        self.polls_left = 0
        self.pstop_at_poll: int | None = None
        self.moves: list[tuple[list[float], float, float, bool]] = []
        self.tcp: list[float] | None = None
        self.receives: list[Any] = []
        self.stops: list[float] = []
        self.uploads = 0
        self.probes = 0
        self.operation = 0
        self.control_flags: list[Any] = []

    def greeting(self, host: str, port: int, timeout: float) -> str:
        """The dashboard server's first line (the link's plain-socket look before ur_rtde connects)."""
        assert host == HOST and timeout > 0
        return "Connected: Universal Robots Dashboard Server"

    # -- receive side
    def make_receive(self, *args: Any, **kwargs: Any) -> Any:
        for sig in pybind_signatures(REAL_RECEIVE.__init__):
            sig.bind(None, *args, **kwargs)  # raises TypeError on a wrong constructor call
            break
        r = strict_autospec(REAL_RECEIVE)
        r.dead = False
        r.frozen_ts = None

        def timestamp() -> float:
            if r.dead:
                return r.frozen_ts
            self.timestamp += 0.002
            return self.timestamp

        r.getTimestamp.side_effect = timestamp
        r.getActualTCPPose.side_effect = lambda: list(self.pose)
        r.getActualQ.side_effect = lambda: list(self.q)
        r.getSafetyMode.side_effect = lambda: self.safety
        r.getRobotMode.side_effect = lambda: self.robot
        r.getRuntimeState.side_effect = lambda: 2 if self.program else 1
        r.getRobotStatus.side_effect = lambda: (1 if self.robot in (5, 7) else 0) | (2 if self.program else 0)
        r.isProtectiveStopped.side_effect = lambda: self.safety == 3
        r.isEmergencyStopped.side_effect = lambda: self.safety in (6, 7)
        r.isConnected.return_value = True  # a stale interface keeps saying True
        self.receives.append(r)
        return r

    def kill_stream(self, r: Any) -> None:
        r.frozen_ts = self.timestamp
        r.dead = True

    def probe(self, host: str, timeout: float) -> float:
        """Stands in for the driver's plain-socket stream probe (``URArm._probe``)."""
        assert host == HOST and timeout > 0
        self.probes += 1
        return self.timestamp

    # -- control side
    def make_control(self, hostname: str, *args: Any, **kwargs: Any) -> Any:
        assert hostname == HOST
        for sig in pybind_signatures(REAL_CONTROL.__init__):
            sig.bind(None, hostname, *args, **kwargs)  # raises TypeError on a wrong constructor call
            break
        self.control_flags.append(kwargs.get("flags"))
        c = strict_autospec(REAL_CONTROL)
        c.isConnected.return_value = True

        def move_l(pose: list[float], speed: float = 0.25, acceleration: float = 1.2,
                   asynchronous: bool = False) -> bool:
            self.moves.append((list(pose), speed, acceleration, asynchronous))
            if not self.program or self.safety != 1 or self.robot != 7:
                return False
            self.motion, self.polls_left = list(pose), 3
            self.operation += 1
            return True

        def progress() -> Any:
            status = strict_autospec(REAL_ASYNC_STATUS)
            if self.motion is not None:
                if self.pstop_at_poll is not None:
                    self.pstop_at_poll -= 1
                    if self.pstop_at_poll == 0:  # protective stop: motion halts, script stops
                        self.safety, self.program, self.motion = 3, False, None
                        self.pstop_at_poll = None
                if self.motion is not None:
                    self.polls_left -= 1
                    if self.polls_left <= 0:
                        self.pose, self.motion = self.motion, None
            status.isAsyncOperationRunning.return_value = self.motion is not None
            status.operationId.return_value = self.operation
            return status

        def set_tcp(offset: list[float]) -> bool:
            self.tcp = list(offset)
            return True

        def reupload() -> bool:  # ur_rtde 1.6.5 returns at once; the program shows up in the stream later
            self.uploads += 1
            if self.safety == 1 and self.robot == 7:
                self.program = True
            return True

        c.moveL.side_effect = move_l
        c.getAsyncOperationProgressEx.side_effect = progress
        c.setTcp.side_effect = set_tcp
        c.isProgramRunning.side_effect = lambda: self.program
        c.reuploadScript.side_effect = reupload
        c.stopL.side_effect = lambda a=10.0, asynchronous=False: self.stops.append(a)
        return c

    # -- dashboard
    def make_dashboard(self, hostname: str, port: int = 29999, verbose: bool = False) -> Any:
        d = strict_autospec(REAL_DASHBOARD)
        d.isConnected.return_value = True
        d.isInRemoteControl.return_value = True
        d.getRobotModel.return_value = "UR5"
        d.getSerialNumber.return_value = "20235500123"
        d.polyscopeVersion.return_value = "URSoftware 5.15.0"

        def unlock() -> None:
            if self.safety == 3:
                self.safety = 1

        d.unlockProtectiveStop.side_effect = unlock
        return d


@pytest.fixture
def ctl() -> FakeController:
    return FakeController()


@pytest.fixture
def vendor(mocker: Any, ctl: FakeController) -> FakeController:
    mocker.patch.object(rtde_receive, "RTDEReceiveInterface", side_effect=ctl.make_receive)
    mocker.patch.object(rtde_control, "RTDEControlInterface", side_effect=ctl.make_control)
    mocker.patch.object(dashboard_client, "DashboardClient", side_effect=ctl.make_dashboard)
    # the controller's greeting, which the link reads with a plain socket before ur_rtde's client connects
    mocker.patch("cellcal.drivers.ur.dashboard.read_greeting", side_effect=ctl.greeting)
    return ctl


@pytest.fixture
def robot(vendor: FakeController) -> Any:
    arm = URArm.from_config({"backend": "ur", "host": HOST, "stale_after_s": 0.05, "isolate": False})
    clock = FakeClock()
    arm._clock, arm._sleep, arm._probe = clock, clock.sleep, vendor.probe
    arm.connect(timeout=2.0)
    yield arm
    arm.close()


def test_connect_sets_tcp_to_flange_and_reads_identity(robot: URArm, ctl: FakeController) -> None:
    assert ctl.tcp == [0.0] * 6
    info = robot.info()
    assert (info.vendor, info.model, info.serial) == ("Universal Robots", "UR5", "20235500123")


def test_pose_and_joints_from_the_receive_interface(robot: URArm, ctl: FakeController) -> None:
    pose = robot.get_pose()
    np.testing.assert_allclose(pose.translation, [0.30, -0.10, 0.45])
    assert pose.rotation.magnitude() == pytest.approx(math.pi)
    np.testing.assert_allclose(robot.joint_positions(), ctl.q)


def test_ur_and_xarm_conversions_agree_on_one_physical_pose(robot: URArm, ctl: FakeController) -> None:
    physical = Pose(Rotation.from_euler("xyz", [0.4, -0.7, 2.1]), np.array([0.412, -0.088, 0.305]))
    ctl.pose = [float(v) for v in pose_to_ur(physical)]   # what the UR controller reports
    from_ur = robot.get_pose()
    xarm_wire = pose_to_xarm(physical)                     # what an xArm would report (mm, rad)
    from_xarm = pose_from_xarm(xarm_wire)
    assert from_ur.is_close(physical, atol_m=1e-12, atol_rad=1e-12)
    assert from_xarm.is_close(from_ur, atol_m=1e-12, atol_rad=1e-12)
    np.testing.assert_allclose(xarm_wire[:3], np.asarray(ctl.pose[:3]) * 1000.0, atol=1e-9)
    np.testing.assert_allclose(Rotation.from_rotvec(ctl.pose[3:]).as_matrix(),
                               Rotation.from_euler("xyz", xarm_wire[3:]).as_matrix(), atol=1e-12)
    # and the command sent to the arm is the same UR vector
    robot.move_linear(physical, speed=0.2, acceleration=1.0)
    np.testing.assert_allclose(ctl.moves[-1][0], pose_to_ur(physical), atol=1e-12)
    assert ctl.moves[-1][1:] == (0.2, 1.0, True)


def test_move_linear_arrives(robot: URArm, ctl: FakeController) -> None:
    target = Pose.from_xyz_rotvec([0.35, 0.05, 0.40], [math.pi, 0.0, 0.0])
    robot.move_linear(target, speed=0.25, acceleration=1.2, timeout=5.0)
    assert robot.get_pose().is_close(target, atol_m=1e-12, atol_rad=1e-12)


@pytest.mark.parametrize(("speed", "acc", "what"), [(3.5, 1.0, "speed 3.5 m/s"), (0.2, 151.0, "acceleration 151")])
def test_limits_beyond_ur_are_rejected_before_moving(robot: URArm, ctl: FakeController,
                                                      speed: float, acc: float, what: str) -> None:
    with pytest.raises(SafetyError, match=what):
        robot.move_linear(Pose.from_xyz_rotvec([0.3, 0, 0.4], [math.pi, 0, 0]), speed=speed, acceleration=acc)
    assert ctl.moves == []


def test_protective_stop_in_the_middle_of_a_plan(robot: URArm, ctl: FakeController) -> None:
    plan = [Pose.from_xyz_rotvec([0.30 + 0.02 * i, 0.0, 0.40], [math.pi, 0.0, 0.0]) for i in range(4)]
    robot.move_linear(plan[0], speed=0.2, acceleration=1.0)
    ctl.pstop_at_poll = 2                               # the arm hits something during move 2
    with pytest.raises(VendorError, match="protective stop") as err:
        robot.move_linear(plan[1], speed=0.2, acceleration=1.0)
    assert err.value.code == 3
    assert not robot.status().can_move and robot.status().error_code == 3
    # the next move is refused before anything is sent, the reason read from the receive interface
    with pytest.raises(VendorError, match="protective stop"):
        robot.move_linear(plan[2], speed=0.2, acceleration=1.0)
    assert len(ctl.moves) == 2
    robot.clear_errors()                                # unlock + re-upload the control script
    assert robot.status().ok and ctl.program and ctl.uploads == 2
    robot.move_linear(plan[3], speed=0.2, acceleration=1.0)
    assert robot.get_pose().is_close(plan[3], atol_m=1e-12, atol_rad=1e-12)


def test_false_return_explained_when_script_stopped(robot: URArm, ctl: FakeController) -> None:
    ctl.program = False                                 # someone pressed stop on the pendant
    with pytest.raises(VendorError, match=r"control script is not running.*STOPPED"):
        robot.move_linear(Pose.from_xyz_rotvec([0.3, 0, 0.4], [math.pi, 0, 0]), speed=0.1, acceleration=1.0)


def test_emergency_stop_cannot_be_cleared_remotely(robot: URArm, ctl: FakeController) -> None:
    ctl.safety = 7
    with pytest.raises(VendorError, match="emergency stop") as err:
        robot.clear_errors()
    assert err.value.code == 7


def test_stale_receive_stream_is_rebuilt(robot: URArm, ctl: FakeController) -> None:
    first = ctl.receives[-1]
    robot.get_pose()
    ctl.kill_stream(first)                              # values freeze, isConnected() stays True
    ctl.pose = [0.31, -0.1, 0.45, math.pi, 0.0, 0.0]    # the arm has moved meanwhile
    robot._sleep(0.2)                                   # longer than stale_after_s
    pose = robot.get_pose()
    assert robot.receive_rebuilds == 1 and ctl.probes == 2   # at connect, and before rebuilding
    assert ctl.receives[-1] is not first and first.disconnect.called
    assert pose.translation[0] == pytest.approx(0.31)


def test_fresh_stream_not_rebuilt(robot: URArm) -> None:
    for _ in range(5):
        robot._sleep(1.0)
        robot.get_pose()
    assert robot.receive_rebuilds == 0


def test_motion_timeout_stops_the_arm(robot: URArm, ctl: FakeController) -> None:
    robot._control.getAsyncOperationProgressEx.side_effect = lambda: _running_status(True)
    with pytest.raises(DeviceTimeoutError, match="did not finish"):
        robot.move_linear(Pose.from_xyz_rotvec([0.3, 0, 0.4], [math.pi, 0, 0]), speed=0.1,
                          acceleration=1.0, timeout=0.5)
    assert ctl.stops == [10.0]


def _running_status(running: bool) -> Any:
    status = strict_autospec(REAL_ASYNC_STATUS)
    status.isAsyncOperationRunning.return_value = running
    status.operationId.return_value = 99
    return status


def test_no_command_on_a_control_link_that_reports_itself_down(robot: URArm, ctl: FakeController) -> None:
    # ur_rtde 1.6.5 blocks forever in moveL / stopL once its control link has dropped
    robot._control.isConnected.return_value = False
    with pytest.raises(DeviceConnectionError, match="control connection is lost"):
        robot.move_linear(Pose.from_xyz_rotvec([0.3, 0, 0.4], [math.pi, 0, 0]), speed=0.1, acceleration=1.0)
    with pytest.raises(DeviceConnectionError, match="control connection is lost"):
        robot.stop()
    assert ctl.moves == [] and ctl.stops == []


def test_a_control_link_lost_at_the_status_read_of_a_move_is_contact_lost_and_never_a_second_move(
        robot: URArm, ctl: FakeController) -> None:
    """The link goes between the wait's link check and its status read: the same MotionError as anywhere else
    in the wait (it escaped as a bare DeviceConnectionError), the move not sent again."""
    looks_after_move = []

    def connected() -> bool:
        if ctl.moves:
            looks_after_move.append(1)
        return len(looks_after_move) < 2  # up for the wait's link check, down at the status read after it

    robot._control.isConnected.side_effect = connected
    with pytest.raises(MotionError, match=r"contact lost during moveL.*read the motion state.*not sent again"):
        robot.move_linear(Pose.from_xyz_rotvec([0.3, 0, 0.4], [math.pi, 0, 0]), speed=0.1, acceleration=1.0)
    assert len(ctl.moves) == 1


def test_remote_control_off_is_reported(vendor: FakeController, mocker: Any) -> None:
    mocker.patch.object(rtde_control, "RTDEControlInterface",
                        side_effect=RuntimeError("ur_rtde: Please enable remote control on the robot!"))
    arm = URArm.from_config({"host": HOST, "isolate": False})
    arm._probe = vendor.probe                            # connect asks the stream first
    with pytest.raises(DeviceConnectionError, match="Remote Control"):
        arm.connect(timeout=2.0)
    assert not arm.connected
    assert vendor.receives[0].disconnect.called          # the half-open connection is released


def test_connect_timeout_is_bounded_and_late_connection_released(vendor: FakeController, mocker: Any) -> None:
    release, entered = threading.Event(), threading.Event()
    late: list[Any] = []

    def slow_control(hostname: str, *args: Any, **kwargs: Any) -> Any:
        entered.set()
        release.wait(30.0)
        c = vendor.make_control(hostname, *args, **kwargs)
        late.append(c)
        return c

    mocker.patch.object(rtde_control, "RTDEControlInterface", side_effect=slow_control)
    arm = URArm.from_config({"host": HOST, "isolate": False})
    arm._probe = vendor.probe                            # connect asks the stream first
    arm._host.caller.join = lambda timeout: None          # close() must not wait for the worker here
    # 2 s: the fake steps before the control's constructor (probe, receive, stream) are done long before
    # on a loaded machine (a 0.2 s budget could run out there, and the control was then never asked for)
    with pytest.raises(DeviceTimeoutError, match="did not finish within"):
        arm.connect(timeout=2.0)
    assert entered.is_set()                               # the budget ran out inside the constructor
    release.set()
    for t in threading.enumerate():
        if t.name.startswith(f"ur {HOST}"):
            t.join(5.0)
    assert len(late) == 1 and late[0].disconnect.called


def test_missing_extra_names_it(mocker: Any) -> None:
    mocker.patch.dict(sys.modules, {"rtde_control": None})
    arm = URArm.from_config({"host": HOST, "isolate": False})            # constructing imports nothing
    with pytest.raises(MissingDependencyError, match=r"cellcal\[ur\]"):
        arm.connect(timeout=1.0)


def test_config_validation() -> None:
    with pytest.raises(ConfigError, match="host"):
        URArm.from_config({})
    with pytest.raises(ConfigError, match="max_speed_m_s"):
        URArm.from_config({"host": HOST, "max_speed_m_s": 4.0})
    with pytest.raises(ConfigError, match="max_acceleration_m_s2"):
        URArm.from_config({"host": HOST, "max_acceleration_m_s2": 200.0})
    with pytest.raises(ConfigError, match="unknown key"):
        URArm.from_config({"host": HOST, "speed": 1.0})


def test_registry_builds_unconnected_without_vendor_import(mocker: Any) -> None:
    mocker.patch.dict(sys.modules, {"rtde_control": None, "rtde_receive": None, "dashboard_client": None})
    arm = default_registry().create("arm", {"backend": "ur", "host": HOST}, BackendContext(section="arm"))
    assert isinstance(arm, URArm) and not arm.connected


# ---------------------------------------------------------------- example configs
CONFIGS = REPO_ROOT / "configs"


@pytest.mark.parametrize("name", ["ur_oak.toml", "ur_o3r.toml"])
def test_example_configs_validate_without_touching_hardware(name: str, mocker: Any) -> None:
    from cellcal.core.calibration.config import load_config

    vendor_modules = ("rtde_control", "rtde_receive", "dashboard_client", "depthai", "usb", "usb.core")
    mocker.patch.dict(sys.modules, dict.fromkeys(vendor_modules))   # any vendor import would fail
    cfg = load_config(CONFIGS / name)
    registry = default_registry()
    camera_backend = cfg.camera_section["backend"]
    # built-in backends: registered by this package's entry points and importable without their SDK
    assert camera_backend in registry.names("camera")
    registry.get("camera", camera_backend)
    arm = registry.create("arm", cfg.arm_section, BackendContext(source=cfg.source, section="arm"))
    camera = registry.create("camera", cfg.camera_section, BackendContext(
        source=cfg.source, section="camera", document=cfg.document, seed=cfg.cell.seed))
    assert isinstance(arm, URArm) and not arm.connected and not camera.connected
    assert arm.config.max_speed_m_s <= cfg.safety.max_speed_m_s


# ---------------------------------------------------------------- what the real ur_rtde 1.6.5 taught
def test_control_interface_opens_without_waiting_and_the_driver_starts_the_script(robot: URArm,
                                                                                   ctl: FakeController) -> None:
    # ur_rtde's constructors hold the GIL: waiting for the script inside one cannot be timed out
    assert int(REAL_CONTROL.FLAG_NO_WAIT) == FLAG_NO_WAIT and not FLAG_NO_WAIT & int(REAL_CONTROL.FLAG_UPLOAD_SCRIPT)
    assert ctl.control_flags == [FLAG_NO_WAIT]
    assert ctl.uploads == 1 and ctl.tcp == [0.0] * 6


def test_a_script_that_never_runs_is_a_connect_timeout(vendor: FakeController) -> None:
    vendor.robot, vendor.program = 5, False              # IDLE: programs cannot run...
    arm = URArm.from_config({"host": HOST, "isolate": False})
    arm._probe = vendor.probe                            # connect asks the stream first
    clock = FakeClock()
    arm._clock, arm._sleep = clock, clock.sleep
    arm._ready_for_program = lambda receive: True        # ...but the driver is told it can: upload, wait
    with pytest.raises(DeviceTimeoutError, match=r"control script did not start in time \(program state 1 STOPPED"):
        arm.connect(timeout=1.5)
    assert clock.t - 1000.0 == pytest.approx(1.5, abs=0.05) and vendor.uploads == 1 and not arm.connected


def test_connects_in_protective_stop_and_clear_errors_retries_the_refused_unlock(vendor: FakeController) -> None:
    vendor.safety, vendor.program = 3, False             # a protective stop also stops the program
    arm = URArm.from_config({"host": HOST, "isolate": False})
    arm._probe = vendor.probe                            # connect asks the stream first
    clock = FakeClock()
    arm._clock, arm._sleep = clock, clock.sleep
    arm.connect(timeout=2.0)                             # no script yet: status says why
    assert vendor.uploads == 0 and arm.status().error_code == 3
    dash = arm._dash.client
    refusals = iter([RuntimeError("Unlock protective stop failure: Cannot unlock protective stop until 5s after "
                                  "occurrence")] * 3)

    def unlock() -> None:
        error = next(refusals, None)
        if error is not None:
            raise error
        vendor.safety = 1

    dash.unlockProtectiveStop.side_effect = unlock
    arm.clear_errors(timeout=5.0)
    assert dash.unlockProtectiveStop.call_count == 4 and vendor.uploads == 1 and arm.status().ok
    arm.close()


# ---------------------------------------------------------------- bounded controller values (issue #31)
@pytest.mark.parametrize(("pose", "says"), [
    ([1e300, 0.0, 0.4, 0.0, 0.0, 0.0], "reported a position 1e+300 m from the base, beyond the"),
    ([2.0, 0.0, 0.0, 0.0, 0.0, 0.0], "reported a position 2 m from the base, beyond the 1.2 m a UR5"),
    ([0.3, 0.0, 0.4, 40.0, 0.0, 0.0], "reported a rotation vector of 40 rad, not a rotation"),
])
def test_a_pose_no_ur_arm_can_have_is_a_protocol_error(robot: Any, vendor: FakeController, pose: list[float],
                                                       says: str) -> None:
    vendor.pose = pose
    with pytest.raises(ProtocolError, match=re.escape(says)):
        robot.get_pose(timeout=1.0)


@pytest.mark.parametrize("field", ["safety", "robot"])
@pytest.mark.parametrize("value", [949222551, -7, 2.5])
def test_a_mode_outside_the_documented_set_is_a_protocol_error_not_a_stop(robot: Any, vendor: FakeController,
                                                                          field: str, value: float) -> None:
    setattr(vendor, field, value)
    what = "getSafetyMode" if field == "safety" else "getRobotMode"
    with pytest.raises(ProtocolError, match=re.escape(f"ur: {what} reported {value!r}, not one of the documented")):
        robot.status(timeout=1.0)


def test_the_reach_follows_the_model_the_dashboard_names() -> None:
    from cellcal.drivers.ur.limits import REACH_MARGIN_M, reach_m

    assert reach_m("UR3e") == 0.5 and reach_m("UR10") == 1.3 and reach_m("UR20") == 1.75
    assert reach_m("") == reach_m("XR-9") == 1.75  # unknown: the largest known reach
    assert REACH_MARGIN_M < 0.5
