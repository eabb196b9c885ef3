"""The expected plane per pose: ``[reference]`` seen from the camera (arm pose @ mount) with its tolerances."""

from __future__ import annotations

import copy
import math
import tomllib
from importlib import resources
from typing import Any

import numpy as np
import pytest

from cellcal.core.calibration.config import parse_config, plan_flange_poses
from cellcal.core.calibration.region import expected_plane
from cellcal.core.geometry.planes import Plane
from cellcal.core.methods.measure import expected_geometry, expected_plane_document
from cellcal.devices.pose import Pose

SIM: dict[str, Any] = tomllib.loads(resources.files("cellcal.configs").joinpath("sim.toml").read_text())


def test_the_expected_plane_is_the_reference_in_the_camera_frame_of_each_pose() -> None:
    config = parse_config(copy.deepcopy(SIM), "x")
    ref = config.search_reference
    assert ref is not None
    for flange in plan_flange_poses(config):
        camera = flange @ config.mount.pose()
        found = expected_plane(ref, expected_geometry(camera, ref.plane_point_m, ref.plane_normal))
        assert found is not None
        assert found.angle_tolerance_rad == pytest.approx(math.radians(15.0)) and found.offset_tolerance_m == 0.1
        # the table z = 0, taken into the camera frame independently: normal R^T (0, 0, 1), offset = camera z
        n_cam = camera.rotation_matrix.T @ np.array([0.0, 0.0, 1.0])
        assert np.allclose(found.plane.normal, n_cam, atol=1e-12)
        assert found.plane.offset_m == pytest.approx(camera.translation[2], abs=1e-12)
        assert found.plane.offset_m > 0                      # normal toward the camera
        # the table itself is accepted; a box top 0.15 m above it (same normal) is not
        table_cam = Plane.from_point_normal([0, 0, 0], [0, 0, 1]).transformed(camera.inv()).oriented_toward_origin()
        box_top = Plane.from_point_normal([0, 0, 0.15], [0, 0, 1]).transformed(camera.inv()).oriented_toward_origin()
        assert found.accepts(table_cam) and found.departure(table_cam) == pytest.approx((0.0, 0.0), abs=1e-12)
        angle, offset = found.departure(box_top)
        assert angle == pytest.approx(0.0, abs=1e-12) and offset == pytest.approx(0.15, abs=1e-12)
        assert not found.accepts(box_top)


def test_a_plane_tilted_past_the_tolerance_is_refused_and_the_document_says_so() -> None:
    doc = copy.deepcopy(SIM)
    doc["reference"].update(search_tolerance_deg=5.0, search_tolerance_m=0.02)
    config = parse_config(doc, "x")
    camera = plan_flange_poses(config)[0] @ config.mount.pose()
    ref = config.search_reference
    assert ref is not None
    found = expected_plane(ref, expected_geometry(camera, ref.plane_point_m, ref.plane_normal))
    assert found is not None
    # a wall-like plane: the table turned 6 deg about the base x axis through the target (0.3, 0, 0)
    turned = Pose.from_xyz_rpy([0.0, 0.0, 0.0], [math.radians(6.0), 0.0, 0.0])
    tilted = Plane.from_point_normal([0.3, 0.0, 0.0], turned.apply_vector([0.0, 0.0, 1.0]))
    tilted_cam = tilted.transformed(camera.inv()).oriented_toward_origin()
    record = expected_plane_document(found, tilted_cam)
    assert record is not None
    assert record["departure_angle_rad"] == pytest.approx(math.radians(6.0), abs=1e-9)
    assert record["angle_tolerance_rad"] == pytest.approx(math.radians(5.0))
    assert record["offset_tolerance_m"] == 0.02 and record["accepted"] is False
    assert record["plane_cam"] == found.plane.to_dict()
    assert expected_plane_document(None, tilted_cam) is None


def test_no_expected_plane_without_a_search() -> None:
    off = copy.deepcopy(SIM)
    off["reference"]["search"] = False
    config = parse_config(off, "x")
    camera = plan_flange_poses(config)[0] @ config.mount.pose()
    geometry = expected_geometry(camera, (0, 0, 0), (0, 0, 1))
    assert expected_plane(config.search_reference, geometry) is None
    assert expected_plane(parse_config(copy.deepcopy(SIM), "x").search_reference, None) is None
