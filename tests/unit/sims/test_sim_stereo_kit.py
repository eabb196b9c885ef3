"""The stereo sim camera (``[camera] kind = "stereo"``) passes the vendor conformance kit, one test per rule."""

from __future__ import annotations

import tomllib
from importlib import resources
from typing import Any

from cellcal.devices import BackendContext, Camera3D, default_registry
from cellcal.testing import CameraConformance, CameraOptions, ScenePlane

OAK_DOC: dict[str, Any] = tomllib.loads(resources.files("cellcal.configs").joinpath("sim_oak.toml").read_text())


class TestSimStereoCamera(CameraConformance):
    # at 320 px f·B = 16.5 px·m: Z from f·B / max_disparity_px = 0.17 m (speckle reaches it) to f·B / 1 px
    # without a plan it sees the table straight below it, 0.44 m away
    options = CameraOptions(distance_range_m=(0.17, 20.0), scene_plane=ScenePlane((0.0, 0.0, 1.0), 0.44))

    def make_camera(self) -> Camera3D:
        section = {**OAK_DOC["camera"], "width": 320, "height": 200}  # smaller frames, same camera
        context = BackendContext(source="<sim_oak.toml>", section="camera", document=OAK_DOC, shared={}, seed=3)
        return default_registry().create_camera(section, context)
