"""The simulated xArm-5-like arm: motion, timing, workspace errors, joints, coupling to the camera."""

from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cellcal.devices.arrival import ArrivalTolerance
from cellcal.devices.base import BackendContext
from cellcal.devices.errors import CellcalError, DeviceTimeoutError, MotionError, NotConnectedError, VendorError
from cellcal.devices.pose import Pose
from cellcal.devices.registry import default_registry
from cellcal.sims.arm import (
    ERROR_MEANINGS,
    ERROR_OUT_OF_REACH,
    SimArm,
    SimArmConfig,
    error_meaning,
    forward_position,
    inverse_kinematics,
)
from cellcal.sims.camera import SimCamera, SimCameraConfig
from cellcal.sims.motion import trapezoid_duration, trapezoid_position
from cellcal.sims.scene import Scene
from cellcal.sims.systematic import SystematicConfig
from cellcal.sims.world import SimWorld

DOWN = Rotation.from_euler("x", 180.0, degrees=True)


def make_arm(**cfg: object) -> SimArm:
    world = SimWorld(Scene(), mount=Pose.identity(), flange_pose=Pose(DOWN, np.array([0.3, 0.0, 0.5])), seed=1)
    return SimArm(SimArmConfig(**cfg), world=world)  # type: ignore[arg-type]


def test_trapezoid_profile_formulas() -> None:
    # Long move: cruise reached. 0.2 m at 0.1 m/s, 0.5 m/s^2: 2 s + 0.2 s.
    assert trapezoid_duration(0.2, 0.1, 0.5) == pytest.approx(2.2)
    # Short move: triangle. 0.01 m at 0.5 m/s, 1 m/s^2: 2*sqrt(0.01) = 0.2 s.
    assert trapezoid_duration(0.01, 0.5, 1.0) == pytest.approx(0.2)
    # Position is continuous, monotonic and ends at the distance.
    ts = np.linspace(0.0, 2.2, 221)
    s = np.array([trapezoid_position(t, 0.2, 0.1, 0.5) for t in ts])
    assert s[0] == 0.0 and s[-1] == pytest.approx(0.2)
    assert np.all(np.diff(s) >= -1e-15)
    assert np.max(np.diff(s)) / (ts[1] - ts[0]) == pytest.approx(0.1, rel=1e-6)  # cruise speed
    assert trapezoid_position(1.1, 0.2, 0.1, 0.5) == pytest.approx(0.1)  # symmetric midpoint


@pytest.mark.parametrize("time_scale", [0.0, 0.05])
def test_move_arrives_within_repeatability_and_simulated_time_matches(time_scale: float) -> None:
    arm = make_arm(time_scale=time_scale)
    target = Pose(DOWN * Rotation.from_euler("x", 10.0, degrees=True), np.array([0.35, 0.1, 0.45]))
    with arm:
        t0 = arm.world.clock.elapsed_s
        arm.move_linear(target, speed=0.2, acceleration=1.0, timeout=5.0)
        elapsed = arm.world.clock.elapsed_s - t0
        distance = float(np.linalg.norm(target.translation - [0.3, 0.0, 0.5]))
        assert elapsed == pytest.approx(trapezoid_duration(distance, 0.2, 1.0), abs=1e-12)
        assert arm.last_motion_duration_s == pytest.approx(elapsed)
        assert arm.true_flange_pose().is_close(target, atol_m=1e-12, atol_rad=1e-12)
        reads = np.array([arm.get_pose(timeout=1.0).translation for _ in range(50)])
        err = reads - target.translation
        assert np.max(np.abs(err)) <= 1e-4  # xArm 5: +-0.1 mm
        assert np.std(err) == pytest.approx(0.25e-4, rel=0.3)  # sigma = repeatability / 4, not zero
        assert arm.get_pose(timeout=1.0).angle_to(target) < 1e-12
        assert not arm.is_moving() and arm.motion_progress() == 1.0


def test_real_time_scale_short_move_uses_simulated_clock() -> None:
    arm = make_arm(time_scale=1.0)
    target = Pose(DOWN, np.array([0.305, 0.0, 0.5]))  # 5 mm at 0.05 m/s, 0.5 m/s^2: 0.1 + 0.1 = 0.2 s
    with arm:
        t0 = arm.world.clock.elapsed_s
        arm.move_linear(target, speed=0.05, acceleration=0.5, timeout=5.0)
        assert arm.world.clock.elapsed_s - t0 == pytest.approx(0.2, abs=1e-12)


def test_non_blocking_motion_progress_and_stop() -> None:
    arm = make_arm(time_scale=1.0)
    start = arm.true_flange_pose()
    target = Pose(DOWN, np.array([0.3, 0.3, 0.5]))  # 0.3 m at 0.1 m/s: 3.1 s of (real) time
    with arm:
        arm.begin_move_linear(target, 0.1, 1.0)
        assert arm.is_moving()
        assert 0.0 <= arm.motion_progress() < 0.5
        deadline = time.monotonic() + 60.0
        while arm.true_flange_pose().distance_to(start) == 0.0:  # under way
            assert time.monotonic() < deadline
            threading.Event().wait(0.005)
        arm.stop(timeout=1.0)
        assert not arm.is_moving()
        halted = arm.true_flange_pose()
        travelled = halted.distance_to(start)
        assert 0.0 < travelled < 0.15  # moved a little along the line (1.5 s from the start), then halted
        np.testing.assert_allclose(halted.translation[[0, 2]], [0.3, 0.5], atol=1e-12)
        assert arm.true_flange_pose().is_close(halted)  # stays put


def test_out_of_workspace_raises_vendor_error_and_clear_errors_recovers() -> None:
    arm = make_arm(time_scale=0.0)
    with arm:
        before = arm.true_flange_pose()
        with pytest.raises(VendorError) as info:
            arm.move_linear(Pose(DOWN, np.array([0.8, 0.0, 0.4])), speed=0.1, acceleration=1.0, timeout=2.0)
        assert info.value.code == ERROR_OUT_OF_REACH == 21 and info.value.vendor == "sim"
        assert arm.true_flange_pose().is_close(before)  # nothing moved
        status = arm.status(timeout=1.0)
        assert status.error_code == 21 and not status.can_move and "Kinematic" in status.message
        # While the error is pending even a reachable move is refused.
        with pytest.raises(VendorError):
            arm.move_linear(Pose(DOWN, np.array([0.3, 0.1, 0.4])), speed=0.1, acceleration=1.0, timeout=2.0)
        arm.clear_errors(timeout=1.0)
        assert arm.status(timeout=1.0).ok
        arm.move_linear(Pose(DOWN, np.array([0.3, 0.1, 0.4])), speed=0.1, acceleration=1.0, timeout=2.0)
        assert arm.true_flange_pose().distance_to(Pose(DOWN, np.array([0.3, 0.1, 0.4]))) < 1e-12
        for bad in ([0.05, 0.0, 0.4], [0.3, 0.0, 0.95], [0.3, 0.0, -0.2]):
            assert arm.workspace_violation(Pose(DOWN, np.array(bad))) is not None
            arm.clear_errors(timeout=1.0)
            with pytest.raises(VendorError):
                arm.move_linear(Pose(DOWN, np.array(bad)), speed=0.1, acceleration=1.0, timeout=2.0)


def test_injected_error_halts_a_blocking_move() -> None:
    arm = make_arm(time_scale=1.0)
    with arm:
        timer = threading.Timer(0.05, arm.set_error, args=(31,))
        timer.start()
        try:
            with pytest.raises(VendorError) as info:
                arm.move_linear(Pose(DOWN, np.array([0.3, 0.3, 0.5])), speed=0.1, acceleration=1.0, timeout=5.0)
        finally:
            timer.join()
        assert info.value.code == 31
        assert not arm.is_moving()


def test_motion_timeout_stops_the_arm() -> None:
    arm = make_arm(time_scale=1.0)
    with arm:
        with pytest.raises(DeviceTimeoutError):
            arm.move_linear(Pose(DOWN, np.array([0.3, 0.3, 0.5])), speed=0.1, acceleration=1.0, timeout=0.05)
        assert not arm.is_moving()


def test_closed_arm_raises_not_connected() -> None:
    arm = make_arm()
    for call in (lambda: arm.get_pose(timeout=1.0), lambda: arm.joint_positions(timeout=1.0),
                 lambda: arm.status(timeout=1.0), lambda: arm.stop(timeout=1.0),
                 lambda: arm.move_linear(Pose(DOWN, np.array([0.3, 0.0, 0.4])), speed=0.1, acceleration=1.0)):
        with pytest.raises(NotConnectedError):
            call()
    arm.connect()
    arm.close()
    with pytest.raises(NotConnectedError):
        arm.get_pose(timeout=1.0)


def test_joint_positions_reproduce_the_flange_and_are_continuous() -> None:
    arm = make_arm(time_scale=0.0)
    with arm:
        q = arm.joint_positions(timeout=1.0)
        assert q.shape == (5,)
        np.testing.assert_allclose(forward_position(q), [0.3, 0.0, 0.5], atol=1e-12)
    # Along a sweep of the base through +-180 deg the joints move in small steps.
    prev = None
    steps = []
    for yaw in np.radians(np.linspace(0.0, 400.0, 201)):
        p = Pose(Rotation.from_euler("z", yaw) * DOWN, np.array([0.4 * math.cos(yaw), 0.4 * math.sin(yaw), 0.3]))
        q = inverse_kinematics(p, prev)
        np.testing.assert_allclose(forward_position(q), p.translation, atol=1e-12)
        if prev is not None:
            steps.append(np.max(np.abs(q - prev)))
        prev = q
    assert max(steps) < math.radians(5.0)


def test_camera_follows_the_arm() -> None:
    world = SimWorld(Scene(), mount=Pose(Rotation.identity(), np.array([0.0, 0.0, 0.03])),
                     flange_pose=Pose(DOWN, np.array([0.3, 0.0, 0.5])), seed=2,
                     systematic=SystematicConfig.off())  # an ideal camera: the exact distance
    arm = SimArm(SimArmConfig(time_scale=0.0), world=world)
    cam = SimCamera(SimCameraConfig(noise=False, quantisation_m=0.0, distortion=False), world=world)
    with arm, cam:
        centre = cam.capture(timeout=1.0).distance[85:87, 111:113].mean()
        assert centre == pytest.approx(0.47, abs=1e-5)  # flange 0.5 m minus the 3 cm mount
        # Raise by 0.2 m and tilt 20 deg about the flange x axis: distance along the axis = h / cos(20).
        target = Pose(DOWN * Rotation.from_euler("x", 20.0, degrees=True), np.array([0.3, 0.0, 0.7]))
        arm.move_linear(target, speed=0.2, acceleration=1.0, timeout=5.0)
        frame = cam.capture(timeout=1.0)
        cam_pose = target @ world.mount
        expected = cam_pose.translation[2] / math.cos(math.radians(20.0))
        assert frame.distance[85:87, 111:113].mean() == pytest.approx(expected, abs=2e-4)


def test_registered_as_sim_backends_sharing_one_world() -> None:
    reg = default_registry()
    assert reg.get("camera", "sim") is SimCamera
    assert reg.get("arm", "sim") is SimArm
    doc = {"sim": {"seed": 3}, "arm": {"backend": "sim", "time_scale": 0.0}, "camera": {"backend": "sim"}}
    ctx = BackendContext(source="cell.toml", document=doc)
    arm = reg.create_arm(doc["arm"], ctx)
    cam = reg.create_camera(doc["camera"], ctx)
    assert isinstance(arm, SimArm) and isinstance(cam, SimCamera)
    assert arm.world is cam.world and arm.world.seed == 3
    with arm, cam:  # moving the arm is seen by the camera built from the same document
        d0 = float(np.nanmedian(cam.capture(timeout=1.0).distance))
        arm.move_linear(Pose(DOWN, np.array([0.3, 0.0, 0.6])), speed=0.2, acceleration=1.0, timeout=5.0)
        d1 = float(np.nanmedian(cam.capture(timeout=1.0).distance))
    assert d1 - d0 == pytest.approx(0.1 * d0 / 0.5, abs=3e-3)


def test_inconsistent_arm_config_is_a_config_error() -> None:
    from cellcal.devices.errors import ConfigError

    with pytest.raises(ConfigError, match="reach_m"):
        SimArm.from_config({"reach_m": 0.1, "min_radius_m": 0.2}, BackendContext(section="arm"))
    with pytest.raises(ConfigError, match=r"arm\.time_scale"):
        SimArm.from_config({"time_scale": -1.0}, BackendContext(section="arm"))


def test_sim_error_codes_mean_what_the_xarm_driver_says_they_mean() -> None:
    """The sim speaks the xArm controller's codes: each one it knows agrees with the driver's table."""
    from cellcal.drivers.xarm import codes  # tests may see both layers; sims/arm.py may not

    assert set(ERROR_MEANINGS) <= set(codes.ERRORS), "the sim uses a code the xArm table does not have"
    for code, meaning in ERROR_MEANINGS.items():
        assert meaning.casefold() == codes.ERRORS[code].casefold(), code
        assert error_meaning(code) == meaning
    assert ERROR_MEANINGS[ERROR_OUT_OF_REACH] == "Kinematic error (target not reachable)"
    assert error_meaning(99) == "Controller Error 99"  # a code the sim does not know still reads as one


# ---------------------------------------------------------------- switchable faults and the arrival check
FAR = Pose(DOWN, np.array([0.3, 0.14, 0.5]))  # 140 mm from make_arm's start


def test_arm_that_stops_short_fails_the_arrival_check_and_is_stopped() -> None:
    arm = make_arm(time_scale=0.0, repeatability_m=0.0)
    with arm:
        arm.faults.stop_short_m = 0.07
        with pytest.raises(MotionError, match=r"pose read 1 of 2 is 70\.000 mm and 0\.0000 deg from the target "
                                              r"\(tolerance 1 mm / 0\.1 deg\).*the arm was told to stop$"):
            arm.move_linear(FAR, speed=0.5, acceleration=2.0, timeout=5.0)
        assert arm.true_flange_pose().distance_to(FAR) == pytest.approx(0.07, abs=1e-12)
        assert arm.true_flange_pose().translation[1] == pytest.approx(0.07, abs=1e-12)  # on the straight path
        assert arm.stops == 1 and arm.moves_started == 1
        arm.faults.stop_short_m = 0.0
        arm.move_linear(FAR, speed=0.5, acceleration=2.0, timeout=5.0)  # healthy again: arrives
        assert arm.true_flange_pose().distance_to(FAR) == 0.0


def test_jumping_and_lagging_read_backs_fail_the_arrival_check() -> None:
    arm = make_arm(time_scale=0.0, repeatability_m=0.0)
    with arm:
        arm.faults.pose_jump_m = 0.005
        readings = [arm.get_pose() for _ in range(20)]
        offsets = [r.distance_to(arm.true_flange_pose()) for r in readings]
        assert offsets == pytest.approx([0.005] * 20, abs=1e-12)
        with pytest.raises(MotionError, match="the reported pose is not steady"):
            arm.move_linear(FAR, speed=0.5, acceleration=2.0, timeout=5.0)
        arm.faults.pose_jump_m = 0.0
        arm.faults.stale_reads = True
        start = arm.true_flange_pose()
        back = Pose(DOWN, np.array([0.3, 0.0, 0.5]))
        # the first read after the move is the one from before it (the target of the move above)
        with pytest.raises(MotionError, match=r"pose reads 1 and 2 of 2 at rest differ by 140\.000 mm"):
            arm.move_linear(back, speed=0.5, acceleration=2.0, timeout=5.0)
        assert start.distance_to(FAR) == 0.0 and arm.true_flange_pose().distance_to(back) == 0.0
        assert arm.stops == 2


def test_arrival_tolerance_fits_the_read_back_noise_and_can_be_configured() -> None:
    assert make_arm().arrival_tolerance == ArrivalTolerance(position_m=1e-3)
    noisy = make_arm(time_scale=0.0, repeatability_m=0.005)  # 5 mm (4 sigma) read-back noise
    assert noisy.arrival_tolerance.position_m == 0.01
    with noisy:
        for _ in range(20):  # two reads 1.25 mm sigma apart per axis stay within 10 mm
            noisy.move_linear(FAR, speed=0.5, acceleration=2.0, timeout=5.0)
            noisy.move_linear(Pose(DOWN, np.array([0.3, 0.0, 0.5])), speed=0.5, acceleration=2.0, timeout=5.0)
        noisy.arrival_tolerance = ArrivalTolerance(position_m=1e-4)  # tighter than the noise: refused
        with pytest.raises(MotionError, match=r"\(tolerance 0\.1 mm / 0\.1 deg\)"):
            noisy.move_linear(FAR, speed=0.5, acceleration=2.0, timeout=5.0)
    with pytest.raises(CellcalError, match=r"ArrivalTolerance\.position_m must be in"):
        ArrivalTolerance(position_m=math.inf)
    with pytest.raises(CellcalError, match="arrival_tolerance must be an ArrivalTolerance"):
        noisy.arrival_tolerance = 0.001  # type: ignore[assignment]
