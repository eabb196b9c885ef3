"""XArmArm <-> XArmEmulator over a real pty, backed by the SimArm."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from leaks import open_fds

from cellcal.devices.base import BackendContext
from cellcal.devices.errors import (
    ConfigError,
    DeviceConnectionError,
    DeviceTimeoutError,
    MotionError,
    ProtocolError,
    SafetyError,
    VendorError,
)
from cellcal.devices.pose import Pose
from cellcal.devices.registry import default_registry
from cellcal.drivers.xarm.arm import XArmArm
from cellcal.drivers.xarm.protocol import encode_request, parse_reply
from cellcal.drivers.xarm.registers import Reg, encode_move_line
from cellcal.sims.arm import SimArm, SimArmConfig
from cellcal.sims.xarm.backend import EmulatedXArmArm
from cellcal.sims.xarm.emulator import XArmEmulator
from cellcal.sims.xarm.wire import Command, RequestReader, modbus_crc, read_line_move, reply_frame


@pytest.fixture
def leak_check() -> Iterator[None]:
    threads = set(threading.enumerate())
    fds = open_fds()
    yield
    extra = [t for t in threading.enumerate() if t not in threads]
    assert not extra, f"leaked threads: {extra}"
    leaked = open_fds() - fds
    assert not leaked, f"leaked file descriptors: {sorted(leaked)}"


def _make(time_scale: float = 0.002, repeatability_m: float = 0.0,
          **driver: object) -> tuple[SimArm, XArmEmulator, XArmArm]:
    sim = SimArm(SimArmConfig(time_scale=time_scale, repeatability_m=repeatability_m, seed=3),
                      BackendContext()).connect()
    emu = XArmEmulator(sim, axes=5)
    path = emu.start()
    cfg = XArmArm.Config(port=path, axes=5, poll_interval_s=0.005, **driver)  # type: ignore[arg-type]
    return sim, emu, XArmArm(cfg)


@pytest.fixture
def rig(leak_check: None) -> Iterator[tuple[SimArm, XArmEmulator, XArmArm]]:
    sim, emu, drv = _make()
    drv.connect()
    yield sim, emu, drv
    drv.close()
    emu.close()
    sim.close()


def _down(x: float, y: float, z: float, yaw: float = 0.0) -> Pose:
    return Pose.from_xyz_rpy([x, y, z], [np.pi, 0.0, yaw])


def test_connect_reads_version_and_enables(rig: tuple[SimArm, XArmEmulator, XArmArm]) -> None:
    _sim, emu, drv = rig
    info = drv.info()
    assert (info.vendor, info.model, info.firmware, info.serial) == ("UFACTORY", "xArm 5", "2.5.0", "XS1305EMU0001")
    assert info.extra["move_line_layout"] == "common"
    assert drv.status().ok
    state = emu.controller_state()
    assert state["enabled"] and state["ready"] and state["mode"] == 0 and state["state"] == 2


def test_pose_and_joints_round_trip_exactly(rig: tuple[SimArm, XArmEmulator, XArmArm]) -> None:
    sim, emu, drv = rig
    drv.move_linear(_down(0.32, -0.07, 0.41, 0.3), speed=0.2, acceleration=2.0)
    pose = drv.get_pose()
    wire = np.asarray(emu.last_reported_pose)
    assert np.abs(pose.translation * 1000.0 - wire[:3]).max() < 1e-4  # mm
    assert np.abs(pose.rotation.as_euler("xyz") - wire[3:]).max() < 1e-6  # rad
    true = sim.true_flange_pose()
    assert np.abs(pose.translation - true.translation).max() * 1000.0 < 1e-4
    assert pose.angle_to(true) < 1e-6
    np.testing.assert_allclose(drv.joint_positions(), sim.joint_positions(), atol=1e-6)
    assert drv.joint_positions().shape == (5,)


def test_plan_of_moves_ends_where_commanded_within_repeatability(leak_check: None) -> None:
    sim, emu, drv = _make(repeatability_m=0.0001)
    with drv:
        plan = [_down(0.30, 0.00, 0.45), _down(0.40, 0.10, 0.30, 0.5), _down(0.25, -0.15, 0.55, -0.4),
                Pose.from_xyz_rpy([0.35, 0.05, 0.50], [np.pi - 0.3, 0.2, 0.1])]
        for target in plan:
            drv.move_linear(target, speed=0.3, acceleration=2.0)
            reading = drv.get_pose()
            assert reading.distance_to(target) <= sim.config.repeatability_m
            assert reading.angle_to(target) < 1e-6
            assert sim.true_flange_pose().distance_to(target) < 1e-6  # float32 on the wire
        assert emu.requests[Reg.MOVE_LINE] == len(plan)
    emu.close()
    sim.close()


def test_out_of_workspace_latches_error_and_recover_clears_it(
        rig: tuple[SimArm, XArmEmulator, XArmArm]) -> None:
    sim, _emu, drv = rig
    start = sim.true_flange_pose()
    with pytest.raises(VendorError) as err:
        drv.move_linear(_down(1.5, 0.0, 0.3), speed=0.2, acceleration=2.0)
    assert (err.value.vendor, err.value.code) == ("xarm", 21)
    assert sim.true_flange_pose().distance_to(start) == 0.0
    status = drv.status()
    assert status.error_code == 21 and not status.can_move and "kinematic" in status.message
    with pytest.raises(VendorError):  # still latched: nothing is cleared silently
        drv.move_linear(_down(0.3, 0.0, 0.4), speed=0.2, acceleration=2.0)
    drv.recover()
    assert drv.status().ok
    drv.move_linear(_down(0.3, 0.0, 0.4), speed=0.2, acceleration=2.0)
    assert sim.true_flange_pose().distance_to(_down(0.3, 0.0, 0.4)) < 1e-6


def test_error_raised_mid_move_is_a_vendor_error(leak_check: None) -> None:
    sim, emu, drv = _make(time_scale=0.3)
    with drv:
        emu.fail_next_move(31, after_polls=3)
        target = _down(0.30, 0.20, 0.30)
        with pytest.raises(VendorError) as err:
            drv.move_linear(target, speed=0.2, acceleration=2.0, timeout=10.0)
        assert err.value.code == 31 and "collision" in err.value.meaning
        assert not sim.is_moving()
        assert sim.true_flange_pose().distance_to(target) > 1e-3  # halted on the way
        drv.recover()
        drv.move_linear(target, speed=1.0, acceleration=20.0, timeout=10.0)
        assert sim.true_flange_pose().distance_to(target) < 1e-6
    emu.close()
    sim.close()


def test_motion_timeout_stops_the_arm(leak_check: None) -> None:
    sim, emu, drv = _make(time_scale=1.0)
    with drv:
        target = _down(0.30, -0.25, 0.30)
        with pytest.raises(DeviceTimeoutError):
            drv.move_linear(target, speed=0.05, acceleration=1.0, timeout=0.2)
        assert not sim.is_moving()
        assert sim.true_flange_pose().distance_to(target) > 0.01
        status = drv.status()
        assert not status.can_move  # stopped: explicit recovery needed
        with pytest.raises(VendorError) as err:
            drv.move_linear(target, speed=0.05, acceleration=1.0, timeout=0.2)
        assert err.value.code == 9
        drv.recover()
        assert drv.status().ok
    emu.close()
    sim.close()


@pytest.mark.parametrize("kind", ["corrupt_crc", "drop", "truncate", "stall", "lag"])
def test_single_fault_on_a_read_is_retried_successfully(kind: str, rig: tuple[SimArm, XArmEmulator, XArmArm]) -> None:
    sim, emu, drv = rig
    before = dict(drv.transport.stats)
    emu.inject(kind, register=Reg.GET_TCP_POSE, stall_s=0.7)  # stall longer than the 0.5 s reply timeout
    pose = drv.get_pose()
    assert pose.distance_to(sim.true_flange_pose()) < 1e-6
    retries = drv.transport.stats["retries"] - before["retries"]
    # a stalled or lagging reply comes late, in the second attempt's wait, next to that attempt's own reply:
    # taken alone it is the reply of the same read; both at once are out of step, and a third attempt is made
    assert retries == 1 or (kind in ("stall", "lag") and retries == 2)
    assert emu.pending_faults() == 0
    # the line is in step afterwards: a move and a read work with no further retries
    drv.move_linear(_down(0.33, 0.02, 0.42), speed=0.3, acceleration=2.0)
    assert drv.get_pose().distance_to(_down(0.33, 0.02, 0.42)) < 1e-6
    assert drv.transport.stats["retries"] - before["retries"] == retries
    assert emu.requests[Reg.MOVE_LINE] == 1


def test_short_stall_needs_no_retry(rig: tuple[SimArm, XArmEmulator, XArmArm]) -> None:
    _sim, emu, drv = rig
    emu.inject("stall", register=Reg.GET_STATE, stall_s=0.1)
    assert drv.status().ok
    assert drv.transport.stats["retries"] == 0


def test_persistent_faults_give_documented_errors(rig: tuple[SimArm, XArmEmulator, XArmArm]) -> None:
    _sim, emu, drv = rig
    attempts = drv.config.retries + 1
    emu.inject("corrupt_crc", count=attempts, register=Reg.GET_TCP_POSE)
    with pytest.raises(ProtocolError, match="CRC"):
        drv.get_pose()
    emu.inject("drop", count=attempts, register=Reg.GET_JOINT_POS)
    with pytest.raises(DeviceTimeoutError):
        drv.joint_positions()
    assert emu.pending_faults() == 0
    assert drv.status().ok  # recovered by itself once the line is clean


@pytest.mark.parametrize("kind", ["drop", "corrupt_crc", "truncate", "stall", "lag"])
def test_unconfirmed_move_is_never_resent(kind: str, leak_check: None) -> None:
    """A MOVE_LINE whose reply is lost, garbled, cut, late or one request behind: MotionError, sent once."""
    sim, emu, drv = _make(time_scale=1.0, reply_timeout_s=0.2, stop_timeout_s=1.0)
    with drv:
        start, target = sim.true_flange_pose(), _down(0.36, -0.04, 0.38)
        emu.inject(kind, register=Reg.MOVE_LINE, stall_s=0.3)  # the stalled reply comes 0.1 s after the timeout
        t0 = time.monotonic()
        with pytest.raises(MotionError, match=r"MOVE_LINE to .* was not confirmed") as err:
            drv.move_linear(target, speed=0.05, acceleration=2.0, timeout=5.0)  # 2.8 s of motion
        elapsed = time.monotonic() - t0
        assert emu.requests[Reg.MOVE_LINE] == 1, "a motion command was sent twice"
        assert "the command was not sent again" in str(err.value)
        # the move took effect (real time: it is still under way), so the arm was stopped short of the target
        assert emu.stop_requests >= 1 and not sim.is_moving()
        assert sim.true_flange_pose().distance_to(start) > 1e-3 and sim.true_flange_pose().distance_to(target) > 1e-3
        assert elapsed <= 0.2 + 1.0 + 1.0  # reply timeout + stop budget + slack for a busy machine
        drv.recover()
        drv.move_linear(target, speed=1.0, acceleration=20.0, timeout=5.0)  # in step again
        assert sim.true_flange_pose().distance_to(target) < 1e-6
        assert emu.requests[Reg.MOVE_LINE] == 2
    emu.close()
    sim.close()


def test_lagging_replies_from_the_move_on_end_in_motion_error(leak_check: None) -> None:
    sim, emu, drv = _make(time_scale=0.5, reply_timeout_s=0.1, stop_timeout_s=1.0)
    with drv:
        emu.inject("lag", count=10_000, register=None)  # every reply from the pose read before MOVE_LINE on
        t0 = time.monotonic()
        with pytest.raises(MotionError, match=r"does not belong to register 21 \(MOVE_LINE\)"):
            drv.move_linear(_down(0.36, -0.04, 0.38), speed=0.3, acceleration=2.0, timeout=3.0)
        assert time.monotonic() - t0 <= 3.0 + 1.0
        assert emu.requests[Reg.MOVE_LINE] == 1 and emu.stop_requests >= 1
    emu.close()
    sim.close()


@pytest.mark.parametrize(("fault", "value", "expected"), [
    ("stop_short_m", 0.07, r"is 70\.0\d\d mm and 0\.0000 deg from the target"),
    ("pose_jump_m", 0.05, "the reported pose is not steady"),
    ("stale_reads", True, "pose reads 1 and 2 of 2 at rest differ by 1[45]"),
])
def test_sim_arm_faults_through_the_emulator_are_motion_errors(fault: str, value: object, expected: str,
                                                               leak_check: None) -> None:
    sim, emu, drv = _make()
    with drv:
        start, target = sim.true_flange_pose(), _down(0.36, -0.04, 0.38)  # 140 mm from the start
        setattr(sim.faults, fault, value)
        with pytest.raises(MotionError, match=expected) as err:
            drv.move_linear(target, speed=0.3, acceleration=2.0, timeout=5.0)
        assert "reported done" in str(err.value) and "the arm was told to stop" in str(err.value)
        assert emu.requests[Reg.MOVE_LINE] == 1 and emu.stop_requests == 1
        if fault == "stop_short_m":
            assert sim.true_flange_pose().distance_to(target) == pytest.approx(0.07, abs=1e-6)
        else:
            assert sim.true_flange_pose().distance_to(target) < 1e-6
        assert start.distance_to(target) == pytest.approx(0.14, abs=1e-3)
    emu.close()
    sim.close()


@pytest.mark.parametrize(("firmware", "layout"), [((1, 10, 0), "legacy"), ((1, 11, 100), "common")])
def test_move_line_layout_follows_the_firmware_version(firmware: tuple[int, int, int], layout: str,
                                                       leak_check: None) -> None:
    sim = SimArm(SimArmConfig(time_scale=0.0, repeatability_m=0.0), BackendContext()).connect()
    with XArmEmulator(sim, axes=5, firmware=firmware, robot_sn="XS1305E1", box_sn="AC1305E1") as emu, \
            XArmArm(XArmArm.Config(port=emu.path, axes=5)) as drv:
        assert drv.info().extra["move_line_layout"] == layout
        target = _down(0.28, 0.12, 0.35, -0.6)
        drv.move_linear(target, speed=0.3, acceleration=2.0)
        assert sim.true_flange_pose().distance_to(target) < 1e-6
        assert sim.true_flange_pose().angle_to(target) < 1e-6
    sim.close()


def test_driver_limits_and_config() -> None:
    with pytest.raises(ConfigError):
        XArmArm.from_config({"axes": 4})
    with pytest.raises(ConfigError):
        XArmArm.from_config({"default_speed_m_s": 0.9, "max_speed_m_s": 0.5})
    cfg = XArmArm.from_config({"port": "loop://", "baudrate": 115200}).config
    assert (cfg.port, cfg.baudrate, cfg.axes) == ("loop://", 115200, 6)
    assert XArmArm.Config().baudrate == 2_000_000


def test_speed_limit_is_a_safety_error(rig: tuple[SimArm, XArmEmulator, XArmArm]) -> None:
    sim, emu, drv = rig
    start = sim.true_flange_pose()
    with pytest.raises(SafetyError):
        drv.move_linear(_down(0.3, 0.1, 0.4), speed=1.5, acceleration=2.0)
    assert emu.requests.get(Reg.MOVE_LINE, 0) == 0
    assert sim.true_flange_pose().distance_to(start) == 0.0


def test_wrong_axis_count_refuses_to_connect(leak_check: None) -> None:
    sim, emu, _drv = _make()
    drv = XArmArm(XArmArm.Config(port=emu.path, axes=7))
    with pytest.raises(DeviceConnectionError, match="7 axes"):
        drv.connect()
    assert not drv.connected
    emu.close()
    sim.close()


def test_missing_port_is_a_connection_error() -> None:
    drv = XArmArm(XArmArm.Config(port="/dev/does-not-exist-xarm"))
    with pytest.raises(DeviceConnectionError):
        drv.connect()


def test_loop_url_without_an_arm_times_out() -> None:
    # loop:// echoes the request back: the reply parser skips it (wrong header) and no reply comes.
    drv = XArmArm(XArmArm.Config(port="loop://", reply_timeout_s=0.05, retries=1))
    with pytest.raises((DeviceTimeoutError, ProtocolError)):
        drv.connect(timeout=0.5)
    assert not drv.connected


def test_emulated_backend_from_registry_shares_the_world(leak_check: None) -> None:
    ctx = BackendContext(section="arm", document={"sim": {}}, seed=7)
    arm = default_registry().create_arm({"backend": "xarm-emulated", "time_scale": 0.001}, ctx)
    assert isinstance(arm, EmulatedXArmArm)
    with pytest.raises(ConfigError):
        default_registry().create_arm({"backend": "xarm-emulated", "bogus": 1}, ctx)
    with arm:
        assert arm.path.startswith("/dev/")
        target = _down(0.31, 0.05, 0.47, 0.2)
        arm.move_linear(target, speed=0.3, acceleration=2.0)
        world = ctx.shared["sim.world"]
        assert world.arm.flange_pose().distance_to(target) < 1e-6
        assert arm.get_pose().distance_to(target) <= arm.sim_arm.config.repeatability_m
        assert arm.info().backend == "xarm-emulated"
        assert arm.driver is not None and arm.driver.backend_name == "xarm"  # the registry's xarm driver
    assert arm.emulator is None and arm.driver is None


# ---------------------------------------------------------------- the emulator's own wire code vs the driver's
def test_emulator_wire_reads_the_spec_example_and_skips_junk() -> None:
    assert modbus_crc(b"123456789") == 0x4B37  # the CRC-16/MODBUS check value
    reader = RequestReader()
    # protocols.md D1: get-version is AA 55 01 01 F1 BC; junk before it, one byte at a time.
    stream = b"\x00\xaa\x13" + bytes.fromhex("AA 55 01 01 F1 BC")
    got = [cmd for byte in stream for cmd in reader.feed(bytes([byte]))]
    assert got == [Command(1, b"")]
    assert reader.skipped_bytes == 3 and reader.bad_frames == 0
    assert reader.feed(bytes.fromhex("AA 55 01 01 F1 BD")) == []  # CRC off by one bit
    assert reader.bad_frames == 1
    assert reader.feed(bytes.fromhex("AA 55 01 0D")) == []  # GET_STATE, CRC not yet arrived
    assert len(reader.feed(encode_request(13)[4:])) == 1  # the rest of a good frame completes one


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 255), st.binary(max_size=60)), min_size=1, max_size=5),
       st.integers(1, 17))
def test_driver_requests_reach_the_emulator_reader_intact(frames: list[tuple[int, bytes]], chunk: int) -> None:
    stream = b"".join(encode_request(reg, params) for reg, params in frames)
    reader = RequestReader()
    got = [cmd for i in range(0, len(stream), chunk) for cmd in reader.feed(stream[i:i + chunk])]
    assert got == [Command(reg, params) for reg, params in frames]
    assert reader.bad_frames == 0 and reader.skipped_bytes == 0


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 255), st.binary(max_size=48))
def test_emulator_replies_parse_in_the_driver(flags: int, data: bytes) -> None:
    reply = parse_reply(reply_frame(flags, data))
    assert (reply.state, reply.data) == (flags, data)


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(-1000, 1000, width=32), min_size=6, max_size=6),
       st.floats(0.125, 1000, width=32), st.floats(0.125, 50000, width=32), st.booleans())
def test_driver_move_line_reads_back_in_the_emulator(pose: list[float], speed: float, acc: float,
                                                     common: bool) -> None:
    move = read_line_move(encode_move_line(pose, speed, acc, common=common))
    assert move is not None
    assert (list(move.pose), move.speed_mm_s, move.acc_mm_s2, move.common) == (pose, speed, acc, common)
    assert (move.coord, move.axis_angle, move.only_check) == (0, False, 0)
    assert move.radius_mm == (-1.0 if common else None)
    assert read_line_move(encode_move_line(pose, speed, acc, common=common)[:-4]) is None  # fits no layout
