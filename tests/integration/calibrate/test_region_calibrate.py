"""The plane the user means, end to end: a box top seen over a table, found by the expected plane and the region.

The sim cell looks at a 0.36 x 0.28 m box, 0.15 m tall, from 0.46-0.61 m above its top: the
top fills 28-48 % of the image, the table the rest. ``[reference]`` is the box top.
"""

from __future__ import annotations

import copy
import json
import math
import tomllib
from importlib import resources
from typing import Any

import numpy as np
import pytest

from cellcal.core.calibration.calibrator import Calibrator, PoseRecord, build_devices
from cellcal.core.calibration.config import parse_config
from cellcal.core.calibration.region import expected_plane
from cellcal.core.methods.fullframe import FullFrameResult
from cellcal.core.methods.measure import expected_geometry, measure_full_frame
from cellcal.devices.errors import CalibrationError, CalibrationQualityError, ConfigError
from cellcal.devices.geometry.camera_model import project
from cellcal.devices.pose import Pose
from cellcal.devices.types import Frame

SIM: dict[str, Any] = tomllib.loads(resources.files("cellcal.configs").joinpath("sim.toml").read_text())
MOUNT = Pose.from_xyz_rpy(SIM["mount"]["translation_m"], np.radians(SIM["mount"]["rpy_deg"]))
#: The box: footprint centre (0.3, 0) m, 0.36 x 0.28 m, top at z = 0.15 m in the base frame.
CENTRE, SIZE, TOP_M = (0.3, 0.0), (0.36, 0.28, 0.15), 0.15


def box_cell(**tables: dict[str, Any]) -> dict[str, Any]:
    """sim.toml with the box on the table, the reference and the plan's target on its top, plus ``tables``.

    The camera has no systematic depth error and the arm no kinematic error: the tests judge which
    plane the region and the expected plane select, to 1 mm."""
    doc = copy.deepcopy(SIM)
    doc["sim"]["boxes"] = [{"center_xy_m": list(CENTRE), "size_m": list(SIZE)}]
    # which plane the region picks is checked to 1 mm: an ideal camera on an exact arm (ADR 0054, 0055)
    doc["sim"]["systematic"] = {"enabled": False}
    doc["sim"]["arm_errors"] = {"enabled": False}
    doc["reference"]["plane_point_m"] = [0.0, 0.0, TOP_M]
    doc["plan"]["target_m"] = [CENTRE[0], CENTRE[1], TOP_M]
    doc["plan"]["methods"] = ["full_frame"]
    for name, table in tables.items():
        doc[name] = {**doc.get(name, {}), **table}
    return doc


def run(doc: dict[str, Any]) -> dict[str, Any]:
    config = parse_config(doc, "<test>")
    camera, arm = build_devices(config)
    return json.loads(json.dumps(Calibrator(config, camera, arm).run()))     # what result.json holds


def assert_box_top(result: dict[str, Any]) -> None:
    """Every pose found the box top: base-frame plane z = 0.15 m, and the true geometry inside its intervals."""
    for pose in result["poses"]:
        ff = pose["full_frame"]
        normal, offset = np.asarray(ff["plane_base"]["normal"]), ff["plane_base"]["offset_m"]
        assert math.degrees(math.acos(normal[2])) < 0.2 and abs(offset + TOP_M) < 1e-3, (pose["index"], offset)
        true = expected_geometry(Pose.from_dict(pose["commanded_flange_pose"]) @ MOUNT, [0, 0, TOP_M], [0, 0, 1])
        lo, hi = ff["height_ci_m"]
        assert lo <= true.height_m <= hi, (pose["index"], lo, true.height_m, hi)
        for key, value in (("tilt_x", true.tilt_x_rad), ("tilt_y", true.tilt_y_rad)):
            lo, hi = ff[f"{key}_ci_deg"]
            assert lo <= math.degrees(value) <= hi, (pose["index"], key, lo, math.degrees(value), hi)
        assert ff["passed"] is True


Captured = list[tuple[PoseRecord, list[Frame]]]


@pytest.fixture(scope="module")
def captured() -> Captured:
    """The box cell's frames at each plan pose, with the pose records (only a grid method runs)."""
    out: Captured = []
    doc = box_cell(plan={"methods": ["plane_fit"], "perimeters_px": [20]})
    config = parse_config(doc, "<test>")
    camera, arm = build_devices(config)
    Calibrator(config, camera, arm, observer=lambda rec, frames, _res: out.append((rec, list(frames)))).run()
    return out


def base_offset_m(result: FullFrameResult, record: PoseRecord) -> float:
    """The fitted plane's offset in the base frame (normal up): minus its height above the table, metres."""
    plane = result.plane.transformed(record.camera)
    return float(plane.offset_m) * (1.0 if plane.normal[2] > 0 else -1.0)


def test_the_expected_plane_takes_the_box_top_not_the_table(captured: Captured) -> None:
    """Over the whole image the fit takes the table; near the expected box top, the box top.

    The flatness gate then names the table as a planar region off the fitted plane: a box
    top and a table are no single plane, which is what a region is for (below).
    """
    config = parse_config(box_cell(), "<test>")
    assert len(captured) == 3
    for record, frames in captured:
        _, whole = measure_full_frame(frames, check=False)
        assert abs(base_offset_m(whole, record)) < 1e-3                              # the table, z = 0
        search = expected_plane(config.search_reference, record.expected)
        assert search is not None and not search.accepts(whole.plane)
        _, found = measure_full_frame(frames, check=False, expected_plane=search)
        assert abs(base_offset_m(found, record) + TOP_M) < 1e-3                      # the box top, z = 0.15 m
        true = expected_geometry(record.commanded @ MOUNT, [0, 0, TOP_M], [0, 0, 1])
        assert found.height_ci_m[0] <= true.height_m <= found.height_ci_m[1]
        assert found.tilt_x_ci_rad[0] <= true.tilt_x_rad <= found.tilt_x_ci_rad[1]
        assert found.tilt_y_ci_rad[0] <= true.tilt_y_rad <= found.tilt_y_ci_rad[1]
        assert found.gates["expected_plane"][2] is True and found.gates["flatness"][2] is False
        assert whole.gates["flatness"][2] is False                                   # (the box top, off the table)


def test_a_reference_where_no_plane_is_fails_the_expected_plane_gate() -> None:
    """The cell believes the plane is 75 mm up, halfway between the table and the box top, within 50 mm of neither."""
    doc = box_cell(reference={"plane_point_m": [0.0, 0.0, 0.075], "search_tolerance_m": 0.05})
    with pytest.raises(CalibrationQualityError) as info:
        run(doc)
    assert info.value.gate == "expected_plane" and "plan pose 1" in str(info.value)


def test_a_base_frame_box_region_counts_the_gates_over_the_box_top() -> None:
    """Default gates: over the whole image the box top is a minority plane; over the region it is all there is."""
    inset = 0.015                           # metres inside the top's edges, clear of mixed pixels
    region = {"box_min_m": [CENTRE[0] - SIZE[0] / 2 + inset, CENTRE[1] - SIZE[1] / 2 + inset, TOP_M - 0.01],
              "box_max_m": [CENTRE[0] + SIZE[0] / 2 - inset, CENTRE[1] + SIZE[1] / 2 - inset, TOP_M + 0.01]}
    result = run(box_cell(region=region))
    assert_box_top(result)
    for pose in result["poses"]:
        ff = pose["full_frame"]
        assert ff["region"]["box_min_m"] == region["box_min_m"] and ff["region"]["polygon_px"] is None
        assert 0.2 < ff["region"]["fraction_of_image"] < 0.45                      # a part of the image ...
        assert ff["gates"]["valid_fraction"]["value"] > 0.95                        # ... nearly all valid,
        assert ff["gates"]["coverage"]["value"] > 0.9                               # and covered
        assert ff["n_points"] <= ff["region"]["n_pixels"]
    with pytest.raises(CalibrationQualityError) as info:          # the same over the image: not one plane
        run(box_cell())
    assert info.value.gate == "flatness" and "plan pose 1" in str(info.value)


def test_a_pixel_polygon_around_the_box_top_finds_it_without_the_search(captured: Captured) -> None:
    """One pose; the polygon is the box top projected into that pose's image, 15 mm inside its edges."""
    record = captured[0][0]
    camera, intrinsics = record.camera, record.intrinsics
    assert intrinsics is not None
    inset = 0.015
    corners = np.array([[CENTRE[0] + sx * (SIZE[0] / 2 - inset), CENTRE[1] + sy * (SIZE[1] / 2 - inset), TOP_M]
                        for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1))])
    polygon = project(intrinsics, camera.inv().apply(corners)).round(1).tolist()
    doc = box_cell(region={"polygon_px": polygon}, reference={"search": False})
    doc["plan"]["heights_m"] = [SIM["plan"]["heights_m"][0]]
    result = run(doc)
    assert_box_top(result)
    ff = result["poses"][0]["full_frame"]
    assert ff["region"]["polygon_px"] == polygon and ff["expected_plane"] is None
    assert ff["gates"]["valid_fraction"]["value"] > 0.95 and ff["gates"]["coverage"]["value"] > 0.9


def test_a_region_out_of_view_or_far_outside_the_image_stops_the_run_naming_it() -> None:
    behind = box_cell(region={"box_min_m": [-0.6, -0.4, 0.0], "box_max_m": [-0.5, -0.3, 0.2]})   # behind the arm
    with pytest.raises(CalibrationError) as info:
        run(behind)
    assert str(info.value).startswith("plan pose 1: the region of interest ([region]: base-frame box "
                                      "[-600, -400, 0]..[-500, -300, 200] mm) holds no pixel of the 224x172 image")
    far = box_cell(region={"polygon_px": [[10, 10], [100, 10], [100, 900]]})
    with pytest.raises(ConfigError) as cfg:
        run(far)
    assert str(cfg.value).startswith("<test>: key 'region.polygon_px[2]': vertex (100, 900) px lies more than one "
                                     "image size outside the 224x172 depth image")
