"""``[sim] camera_on_arm = false``: a camera that stays put while the arm moves (a rig error to detect)."""

from __future__ import annotations

from typing import Any

import numpy as np

from cellcal.devices.base import BackendContext
from cellcal.devices.pose import Pose
from cellcal.sims.camera import SimCamera, SimCameraConfig
from cellcal.sims.world import world_from_context

MOUNT = {"translation_m": [0.0, 0.04, 0.06], "rpy_deg": [0.0, 0.0, 90.0]}
ELSEWHERE = Pose.from_xyz_rpy([0.45, 0.1, 0.35], np.radians([170.0, 10.0, 30.0]))


def _world(sim: dict[str, Any]) -> Any:
    return world_from_context(BackendContext(document={"sim": sim, "mount": MOUNT}))


def test_the_camera_stays_at_the_initial_flange_pose_while_the_arm_moves() -> None:
    world = _world({"camera_on_arm": False, "initial_flange_translation_m": [0.3, 0.0, 0.5]})
    start = world.camera_pose()
    world.arm.set_flange_pose(ELSEWHERE)
    assert world.arm.flange_pose().is_close(ELSEWHERE)
    assert world.camera_pose().is_close(start, atol_m=1e-12, atol_rad=1e-12)
    expected = Pose.from_xyz_rpy([0.3, 0.0, 0.5], np.radians([180.0, 0.0, 0.0])) @ world.mount
    assert start.is_close(expected, atol_m=1e-12, atol_rad=1e-12)


def test_by_default_the_camera_rides_on_the_arm() -> None:
    world = _world({})
    world.arm.set_flange_pose(ELSEWHERE)
    # on the true flange: the believed one moved by the arm's kinematic errors ([sim.arm_errors], ADR 0055)
    assert world.camera_pose().is_close(world.true_flange_pose() @ world.mount, atol_m=1e-12, atol_rad=1e-12)
    assert world.camera_pose().is_close(ELSEWHERE @ world.mount, atol_m=3e-3, atol_rad=2e-3)
    ideal = _world({"arm_errors": {"enabled": False}})
    ideal.arm.set_flange_pose(ELSEWHERE)
    assert ideal.camera_pose().is_close(ELSEWHERE @ ideal.mount, atol_m=1e-12, atol_rad=1e-12)


def test_frames_of_a_camera_off_the_arm_do_not_change_with_the_arm() -> None:
    world = _world({"camera_on_arm": False})
    camera = SimCamera(SimCameraConfig(noise=False), world=world).connect()
    before = camera.capture(1.0).xyz
    world.arm.set_flange_pose(ELSEWHERE)
    after = camera.capture(1.0).xyz
    np.testing.assert_array_equal(np.isfinite(before), np.isfinite(after))
    np.testing.assert_allclose(after, before, atol=1e-6, equal_nan=True)  # the same view to 1 micrometre
