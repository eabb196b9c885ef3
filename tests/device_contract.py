"""Reusable contract checks for Camera3D and RobotArm backends.

Each check takes an *unconnected* device built from its config and exercises the
interface promises: life cycle, timeouts, units, shapes and dtypes.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from cellcal.devices import (
    ArmStatus,
    Camera3D,
    CellcalError,
    DeviceInfo,
    Frame,
    NotConnectedError,
    Pose,
    RobotArm,
)


def check_camera(camera: Camera3D) -> None:
    with pytest.raises(NotConnectedError):
        camera.capture(1.0)
    with pytest.raises(NotConnectedError):
        _ = camera.intrinsics
    camera.connect(5.0)
    try:
        camera.connect(5.0)  # idempotent
        assert camera.connected
        assert isinstance(camera.info(), DeviceInfo)
        intr = camera.intrinsics
        for bad in (0.0, -1.0, math.nan, math.inf):
            with pytest.raises(CellcalError, match="timeout"):
                camera.capture(bad)
        frames = [camera.capture(5.0) for _ in range(3)]
        for f in frames:
            assert isinstance(f, Frame)
            h, w = intr.height, intr.width
            assert f.distance.shape == (h, w) and f.distance.dtype == np.float32
            assert f.xyz.shape == (h, w, 3) and f.xyz.dtype == np.float32
            assert f.valid.dtype == np.bool_ and f.valid.any()
            assert np.all(np.isnan(f.distance[~f.valid]))
            d = f.distance[f.valid]
            assert np.all((d > 0.01) & (d < 50.0)), "distance must be metres"
            np.testing.assert_allclose(np.linalg.norm(f.xyz[f.valid], axis=1), d, rtol=1e-4, atol=1e-4)
            assert np.all(f.xyz[f.valid][:, 2] > 0), "camera frame: +z forward"
            assert f.timestamp > 1e9, "timestamp: seconds since the epoch"
        seqs = [f.sequence for f in frames]
        assert seqs == sorted(seqs) and len(set(seqs)) == 3
    finally:
        camera.close()
        camera.close()  # idempotent
    assert not camera.connected
    with pytest.raises(NotConnectedError):
        camera.capture(1.0)


def check_arm(arm: RobotArm, step_m: float = 0.02) -> None:
    with pytest.raises(NotConnectedError):
        arm.get_pose(1.0)
    with arm:
        arm.connect(5.0)
        assert isinstance(arm.info(), DeviceInfo)
        start = arm.get_pose(5.0)
        assert isinstance(start, Pose)
        assert np.linalg.norm(start.translation) < 3.0, "pose must be metres"
        q = arm.joint_positions(5.0)
        assert q.ndim == 1 and q.size >= 5 and np.all(np.abs(q) <= 2 * math.pi + 1e-9), "joints must be radians"
        status = arm.status(5.0)
        assert isinstance(status, ArmStatus) and status.ok
        target = Pose(start.rotation, start.translation + np.array([0.0, 0.0, step_m]))
        for bad_speed in (0.0, -0.1, math.nan):
            with pytest.raises(CellcalError, match="speed"):
                arm.move_linear(target, speed=bad_speed, acceleration=1.0)
        assert arm.get_pose(5.0).distance_to(start) < 1e-3, "a rejected command must not move the arm"
        arm.move_linear(target, speed=0.1, acceleration=1.0, timeout=30.0)
        reached = arm.get_pose(5.0)
        assert reached.distance_to(target) < 1e-3 and reached.angle_to(target) < 1e-3
        arm.stop(5.0)
        arm.clear_errors(5.0)
    assert not arm.connected
    with pytest.raises(NotConnectedError):
        arm.move_linear(start, speed=0.1, acceleration=1.0)
