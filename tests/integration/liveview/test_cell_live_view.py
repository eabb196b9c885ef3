"""The live view of a cell with several cameras (issue #40): every camera's cloud and plane on its own topics in
one scene, each camera's frame in ``/tf`` (under the flange with its mount, or under the base for a fixed one).

A real Foxglove client (tests/support/foxglove_client.py) against the server; the frames are the simulated
``configs/sim_multi.toml`` cell's 'wrist' (on the flange) and 'above' (fixed 1.2 m over the plane).
"""

from __future__ import annotations

import base64
import time
from typing import Any

import numpy as np
import pytest
from repo_paths import REPO_ROOT
from scipy.spatial.transform import Rotation

pytest.importorskip("foxglove")
pytest.importorskip("websockets")
from foxglove_client import FoxgloveClient

from cellcal.core.calibration.build import build_cell
from cellcal.core.calibration.config import load_config
from cellcal.core.liveview import LiveView, camera_frame_id, track_scene
from cellcal.core.methods.fullframe import fit_full_frame
from cellcal.devices.pose import Pose

TOPICS = {"/cameras/wrist/points", "/cameras/wrist/plane", "/cameras/above/points", "/cameras/above/plane", "/tf",
          "/cellcal/track"}


def _pose(p: dict[str, Any]) -> Pose:
    t, q = p["translation"], p["rotation"]
    return Pose(Rotation.from_quat([q["x"], q["y"], q["z"], q["w"]]), np.array([t["x"], t["y"], t["z"]]))


def test_each_camera_has_its_own_cloud_and_plane_and_its_frame_in_tf() -> None:
    config = load_config(str(REPO_ROOT / "configs" / "sim_multi.toml"))
    cameras, arm = build_cell(config)
    above = next(c for c in config.cameras if c.name == "above")
    assert above.pose_base is not None
    mount = config.mount.pose()
    with arm, cameras["wrist"], cameras["above"]:
        flange = arm.get_pose()
        frames = {name: cameras[name].capture(5.0) for name in ("wrist", "above")}
    fits = {name: fit_full_frame(frame, config.full_frame) for name, frame in frames.items()}
    with LiveView(0, track=True, cameras=["wrist", "above"]) as view:
        view.place_camera(camera_frame_id("above"), above.pose_base)
        with FoxgloveClient(view.url) as client:
            client.wait_for_channels(TOPICS)
            assert set(client.seen.channels) == TOPICS            # no shared cloud or plane topic
            client.subscribe_all()
            deadline = time.monotonic() + 60
            while view.subscriptions < len(client.seen.channels):
                assert time.monotonic() < deadline, view.subscriptions
                time.sleep(0.01)
            view.publish(track_scene(frames["wrist"], fits["wrist"], flange, mount, {"t_s": 0.0},
                                     camera_frame_id=camera_frame_id("wrist")))
            view.publish(track_scene(frames["above"], fits["above"], None, None, {"t_s": 0.0},
                                     camera_frame_id=camera_frame_id("above")))
            seen = client.collect(TOPICS, count=1)
            seen = client.collect({"/tf", "/cellcal/track"}, count=2)
    (wrist_tf, above_tf) = (m for _, m in seen.messages["/tf"])
    (base, on_flange) = wrist_tf["transforms"]
    assert (base["child_frame_id"], on_flange["parent_frame_id"], on_flange["child_frame_id"]) == (
        "flange", "flange", "camera_wrist")
    assert _pose(base).is_close(flange, atol_m=1e-12, atol_rad=1e-9)
    assert _pose(on_flange).is_close(mount, atol_m=1e-12, atol_rad=1e-9)
    (fixed,) = above_tf["transforms"]                           # a fixed camera: under the base, at its pose
    assert (fixed["parent_frame_id"], fixed["child_frame_id"]) == ("base", "camera_above")
    assert _pose(fixed).is_close(above.pose_base, atol_m=1e-12, atol_rad=1e-9)
    for name in ("wrist", "above"):
        (_, cloud), = seen.messages[f"/cameras/{name}/points"]
        assert cloud["frame_id"] == f"camera_{name}"
        n = len(base64.b64decode(cloud["data"])) // 16
        assert n == int(np.count_nonzero(frames[name].valid & np.all(np.isfinite(frames[name].xyz), axis=-1)))
        (_, update), = seen.messages[f"/cameras/{name}/plane"]
        assert update["entities"][0]["frame_id"] == f"camera_{name}"
    assert [m["frame_id"] for _, m in seen.messages["/cellcal/track"]] == ["camera_wrist", "camera_above"]
    # the fixed camera's plane, taken to the base frame through its pose, is the floor (z = 0) to 1 cm
    plane = fits["above"].plane.transformed(above.pose_base)
    assert abs(abs(plane.normal[2]) - 1.0) < 1e-3 and abs(plane.offset_m) < 0.01
