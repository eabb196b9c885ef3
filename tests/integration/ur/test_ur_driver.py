"""The ``ur`` backend through the real ur_rtde against the UR emulator: moves, read-back, and every fault.

Each fault ends as the documented typed error within the call's timeout, the arm is left
stopped, and no thread or file descriptor is left behind. Tests share a connection where
they can: ur_rtde sleeps 0.5 s in every ``disconnect()``, destructors included, so each
close costs a second.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest
from ur_rig import HOME, once_moving, wait_until

from cellcal.devices.errors import (
    DeviceConnectionError,
    DeviceTimeoutError,
    MotionError,
    VendorError,
)
from cellcal.devices.geometry.vendor_poses import pose_from_ur
from cellcal.devices.pose import Pose
from cellcal.drivers.ur.arm import URArm
from cellcal.sims.ur.process import UREmulatorProcess

pytest.importorskip("rtde_control")  # the ur extra

MOVE_TIMEOUT_S = 2.0
#: A fault must end a call within its timeout plus this (a loaded machine's scheduling), s.
SLACK_S = 1.0
#: ur_rtde's release of a failed connection (two destructors of ~0.5 s each) plus slack, s.
RELEASE_S = 2.0


def shifted(pose: Pose, dx: float = 0.0, dy: float = 0.0, dz: float = 0.0) -> Pose:
    return Pose(pose.rotation, pose.translation + np.array([dx, dy, dz]))


@pytest.fixture
def make_arm(emu: UREmulatorProcess) -> Iterator[Callable[..., URArm]]:
    made: list[URArm] = []

    def make(**overrides: Any) -> URArm:
        arm = URArm.from_config({"host": emu.host, "timeout_s": 2.0, "stale_after_s": 0.2,
                                 "poll_interval_s": 0.005, **overrides})
        made.append(arm)
        return arm

    yield make
    for arm in made:
        arm.close()


def commands(emu: UREmulatorProcess, command_id: int) -> int:
    """How many times the control script executed a command (3 moveL, 33 stopL, 29 setTcp)."""
    return int(emu.snapshot()["commands"].get(str(command_id), 0))


def test_connects_moves_and_reads_back_through_ur_rtde(emu: UREmulatorProcess, make_arm: Callable[..., URArm],
                                                       no_leaks: None) -> None:
    set_tcp = commands(emu, 29)
    with make_arm() as arm:
        info = arm.info()
        assert (info.vendor, info.model, info.serial, info.firmware) == (
            "Universal Robots", "UR5", "20235500001", "5.11.0.108249")
        assert arm.status().ok
        assert commands(emu, 29) == set_tcp + 1                    # TCP offset zeroed: poses are the flange's
        assert arm.get_pose().distance_to(HOME) < 1e-4              # read-back noise 0.03 mm
        assert arm.joint_positions().shape == (6,)
        target = Pose.from_xyz_rpy([0.42, -0.03, 0.41], [np.pi, 0.0, 0.3])
        arm.move_linear(target, speed=0.25, acceleration=1.2, timeout=MOVE_TIMEOUT_S)
        truth = pose_from_ur(emu.snapshot()["flange"])
        assert truth.distance_to(target) < 1e-9 and truth.angle_to(target) < 1e-9   # float64 on the wire
        assert arm.get_pose().distance_to(target) < 1e-4
        # a target out of reach: the script's inverse kinematics fail and the program stops
        with pytest.raises(VendorError, match="control script is not running") as err:
            arm.move_linear(Pose.from_xyz_rpy([1.5, 0.0, 0.3], [np.pi, 0, 0]), speed=0.25, acceleration=1.2,
                            timeout=MOVE_TIMEOUT_S)
        assert err.value.code == 1                                 # program state STOPPED
        assert pose_from_ur(emu.snapshot()["flange"]).distance_to(target) < 1e-9
        arm.clear_errors()                                         # uploads the script again
        # a move that overruns its timeout is stopped
        emu.call("set_time_scale", time_scale=1.0)
        stops = commands(emu, 33)
        t0 = time.monotonic()
        with pytest.raises(DeviceTimeoutError, match=r"did not finish within 0\.3 s; the arm was told to stop"):
            arm.move_linear(shifted(target, dx=-0.2), speed=0.05, acceleration=1.0, timeout=0.3)
        assert time.monotonic() - t0 < 0.3 + SLACK_S
        assert commands(emu, 33) == stops + 1 and not emu.snapshot()["moving"]


def test_protective_stops_are_typed_errors_and_clear_errors_recovers(emu: UREmulatorProcess,
                                                                    make_arm: Callable[..., URArm],
                                                                    no_leaks: None) -> None:
    target = shifted(HOME, dy=0.15)
    with make_arm() as arm:
        # moveL would return False: the driver refuses before sending and says why
        emu.call("safety_stop", kind="protective_stop")
        wait_until(lambda: not arm.status().can_move, what="protective stop seen by the driver")
        moves = commands(emu, 3)
        with pytest.raises(VendorError, match="protective stop") as err:
            arm.move_linear(target, speed=0.25, acceleration=1.2, timeout=MOVE_TIMEOUT_S)
        assert (err.value.vendor, err.value.code, commands(emu, 3)) == ("ur", 3, moves)
        arm.clear_errors()
        # a protective stop in the middle of a move
        emu.call("set_unlock_delay", delay_s=0.3)                 # UR refuses to unlock this soon after
        emu.call("safety_stop", kind="protective_stop", at_progress=0.4)
        t0 = time.monotonic()
        with pytest.raises(VendorError, match="protective stop") as err:
            arm.move_linear(target, speed=0.25, acceleration=1.2, timeout=MOVE_TIMEOUT_S)
        assert err.value.code == 3 and time.monotonic() - t0 < MOVE_TIMEOUT_S + SLACK_S
        snap = emu.snapshot()
        assert not snap["moving"] and not snap["program_running"]
        assert 0.02 < pose_from_ur(snap["flange"]).distance_to(HOME) < 0.13     # halted on the way
        status = arm.status()
        assert (status.error_code, status.can_move) == (3, False)
        arm.clear_errors(timeout=3.0)                              # retries the refused unlock, restarts the script
        assert time.monotonic() - t0 >= 0.3 and arm.status().ok
        arm.move_linear(target, speed=0.25, acceleration=1.2, timeout=MOVE_TIMEOUT_S)
        assert pose_from_ur(emu.snapshot()["flange"]).distance_to(target) < 1e-9


def test_emergency_stop_mid_move_needs_a_hand_then_powers_up(emu: UREmulatorProcess,
                                                              make_arm: Callable[..., URArm],
                                                              no_leaks: None) -> None:
    with make_arm(allow_power_on=True) as arm:
        emu.call("safety_stop", kind="emergency_stop", at_progress=0.3)
        with pytest.raises(VendorError, match="emergency stop") as err:
            arm.move_linear(shifted(HOME, dx=-0.1), speed=0.25, acceleration=1.2, timeout=MOVE_TIMEOUT_S)
        assert err.value.code == 7 and not emu.snapshot()["moving"]
        with pytest.raises(VendorError, match="by hand"):
            arm.clear_errors(timeout=2.0)
        emu.call("release_emergency_stop")
        wait_until(lambda: arm.status().message.startswith("robot mode 3 POWER_OFF"), what="e-stop released")
        arm.clear_errors(timeout=3.0)                              # power on, brake release, script
        assert arm.status().ok
        assert [c for c in emu.snapshot()["dashboard_commands"] if c in ("power on", "brake release")] == [
            "power on", "brake release"]


def test_a_control_script_that_never_starts_is_a_timeout(emu: UREmulatorProcess, make_arm: Callable[..., URArm],
                                                          no_leaks: None) -> None:
    emu.call("refuse_script", refuse=True)
    arm = make_arm()
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeoutError, match="control script did not start"):
        arm.connect(timeout=1.0)
    assert time.monotonic() - t0 < 1.0 + RELEASE_S
    assert not arm.connected and emu.snapshot()["programs_received"] >= 1


def test_frozen_receive_streams(emu: UREmulatorProcess, make_arm: Callable[..., URArm], no_leaks: None) -> None:
    with make_arm() as arm:
        # frozen on one connection: detected from the timestamp and replaced
        arm.get_pose()
        assert emu.call("freeze_stream", target="receive") == 1   # the socket stays open, no data
        time.sleep(0.3)                                           # > stale_after_s
        target = shifted(HOME, dz=-0.03)
        arm.move_linear(target, speed=0.25, acceleration=1.2, timeout=MOVE_TIMEOUT_S)
        assert arm.receive_rebuilds == 1 and arm.get_pose().distance_to(target) < 1e-3  # arrival tolerance
        # frozen for every new connection too, in the middle of a move: the move ends stopped
        emu.call("set_time_scale", time_scale=1.0)
        stops = commands(emu, 33)
        injector = once_moving(emu, lambda: emu.call("freeze_stream", target="receive", new_sessions=True))
        t0 = time.monotonic()
        with pytest.raises(MotionError, match=r"contact lost during moveL.*the arm was told to stop"):
            arm.move_linear(shifted(HOME, dy=0.2), speed=0.1, acceleration=1.0, timeout=MOVE_TIMEOUT_S)
        assert time.monotonic() - t0 < MOVE_TIMEOUT_S + SLACK_S
        injector.join()
        assert commands(emu, 33) == stops + 1 and not emu.snapshot()["moving"]
        with pytest.raises(DeviceConnectionError, match="sent no data"):
            arm.get_pose(timeout=0.5)
        # once the controller streams again, the next read finds a new stream by itself
        emu.call("unfreeze_stream")
        assert arm.get_pose().distance_to(pose_from_ur(emu.snapshot()["flange"])) < 1e-4


def test_a_dropped_connection_ends_the_move_and_releases_everything(emu: UREmulatorProcess,
                                                                    make_arm: Callable[..., URArm],
                                                                    no_leaks: None) -> None:
    emu.call("set_time_scale", time_scale=1.0)
    arm = make_arm()
    arm.connect()
    injector = once_moving(emu, lambda: emu.call("drop_connections", refuse_s=-1.0))  # the controller goes away
    t0 = time.monotonic()
    with pytest.raises(MotionError, match="contact lost during moveL"):
        arm.move_linear(shifted(HOME, dy=-0.2), speed=0.1, acceleration=1.0, timeout=MOVE_TIMEOUT_S)
    assert time.monotonic() - t0 < MOVE_TIMEOUT_S + SLACK_S
    injector.join()
    assert not emu.snapshot()["moving"]                           # the program stopped with its link
    time.sleep(0.3)   # > stale_after_s: a read may serve the last package until then
    with pytest.raises(DeviceConnectionError, match=r"reset by peer|closed the connection"):
        arm.get_pose(timeout=0.5)
    arm.close()


def test_local_control_is_refused_at_connect(emu: UREmulatorProcess, make_arm: Callable[..., URArm]) -> None:
    emu.call("set_remote_control", remote=False)
    arm = make_arm()
    with pytest.raises(DeviceConnectionError, match="Remote Control"):
        arm.connect(timeout=2.0)
    assert not arm.connected
