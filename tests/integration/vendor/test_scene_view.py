"""The public scene view agrees with what cellcal's own simulated camera sees, pose after pose.

A vendor's fake device renders from :class:`~cellcal.devices.scene_view.SceneSnapshot`;
here the snapshot is checked against the simulated ToF camera (noise, artefacts and
quantisation off) mounted on the same simulated arm: every pixel on the plane has the
snapshot's range, every box pixel is nearer, and the camera pose is the world's.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from cellcal.devices import BackendContext, Pose, default_registry
from cellcal.devices.scene_view import SCENE_VIEW_KEY, SceneSnapshot, scene_view

DOCUMENT: dict[str, Any] = {
    "mount": {"translation_m": [0.0, 0.04, 0.06], "rpy_deg": [0.0, 0.0, 90.0]},
    "sim": {"boxes": [{"center_xy_m": [0.3, 0.02], "size_m": [0.08, 0.06, 0.05], "yaw_deg": 20.0}],
            "artefacts": {"mixed_pixels": False, "multipath": False, "amplitude_noise": False,
                          "temperature_drift": False},
            "systematic": {"enabled": False}},   # an ideal camera: the range is the geometry's (ADR 0054)
}


def _cell() -> tuple[BackendContext, Any, Any]:
    shared: dict[str, Any] = {}
    registry = default_registry()

    def ctx(section: str) -> BackendContext:
        return BackendContext(section=section, document=DOCUMENT, shared=shared, seed=3)

    camera = registry.create_camera({"backend": "sim", "noise": False, "quantisation_m": 0.0}, ctx("camera"))
    arm = registry.create_arm({"backend": "sim", "time_scale": 0.0}, ctx("arm"))
    return ctx("camera"), camera, arm


def test_outside_a_simulated_cell_there_is_no_scene_view() -> None:
    assert scene_view(None) is None and scene_view(BackendContext()) is None
    assert scene_view(BackendContext(shared={SCENE_VIEW_KEY: object()})) is None   # not a SceneView


@pytest.mark.parametrize("xyz_rpy", [((0.3, 0.0, 0.45), (180.0, 0.0, 0.0)), ((0.25, 0.08, 0.5), (165.0, 10.0, 30.0)),
                                     ((0.35, -0.05, 0.4), (200.0, -12.0, -80.0))])
def test_the_snapshot_matches_the_simulated_camera(xyz_rpy: tuple[tuple[float, ...], tuple[float, ...]]) -> None:
    context, camera, arm = _cell()
    with camera, arm:
        target = Pose.from_xyz_rpy(np.asarray(xyz_rpy[0]), np.radians(xyz_rpy[1]))
        arm.move_linear(target, speed=0.3, acceleration=1.5, timeout=10.0)
        view = scene_view(context)
        assert view is not None
        snap = view.view_from_camera()
        frame = camera.capture(2.0)
    assert isinstance(snap, SceneSnapshot)
    assert snap.camera_pose.is_close(arm.world.camera_pose(), atol_m=1e-12, atol_rad=1e-12)
    # the plane z = 0, seen from the camera: at the camera's height, its normal the base z axis turned
    base_z_in_camera = snap.camera_pose.inv().apply_vector([0.0, 0.0, 1.0])
    assert snap.plane_distance_m == pytest.approx(snap.camera_pose.as_xyz_rpy()[2], abs=1e-12)
    assert snap.plane_normal @ base_z_in_camera == pytest.approx(1.0, abs=1e-12)   # facing the camera (above it)
    # every valid pixel: on the plane at the snapshot's range, or on the box in front of it
    v = frame.valid
    dist = frame.distance[v].astype(np.float64)
    rays = frame.xyz[v].astype(np.float64) / dist[:, None]
    t_plane = snap.plane_range(rays)
    on_plane = np.abs(t_plane - dist) < 1e-4
    assert on_plane.mean() > 0.5
    assert np.all(dist[~on_plane] < t_plane[~on_plane] - 1e-3)    # occluded by the box: nearer than the plane
    # the box's centre, in the camera frame, lies in front of the plane and of the camera
    (box,) = snap.boxes
    assert box.centre_m[2] > 0 and snap.plane_range(box.centre_m / np.linalg.norm(box.centre_m)) > \
        np.linalg.norm(box.centre_m)
    assert box.size_m == (0.08, 0.06, 0.05)
