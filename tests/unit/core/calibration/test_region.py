"""The region of interest: ``[region]`` parsing, the polygon and base-frame box masks, one pose's mask."""

from __future__ import annotations

import copy
import math
import tomllib
from importlib import resources
from typing import Any

import cv2
import numpy as np
import pytest

from cellcal.core.calibration.config import look_at_pose, parse_config
from cellcal.core.calibration.dryrun import dry_run
from cellcal.core.calibration.region import box_mask, polygon_mask, region_document, region_mask
from cellcal.core.calibration.sections import RegionSection
from cellcal.devices.errors import CalibrationError, ConfigError
from cellcal.devices.geometry.camera_model import pixel_grid_rays, project
from cellcal.devices.pose import Pose
from cellcal.devices.types import Intrinsics
from cellcal.sims.camera import o3r222_intrinsics
from cellcal.sims.scene import Box, Scene

SIM: dict[str, Any] = tomllib.loads(resources.files("cellcal.configs").joinpath("sim.toml").read_text())
PINHOLE = Intrinsics(224, 172, 190.0, 190.0, 111.5, 85.5)


def camera_at(height_m: float, inclination_deg: float, target: tuple[float, float, float] = (0.3, 0.0, 0.0)) -> Pose:
    """A camera (base frame) looking at ``target`` on the table z = 0 from ``height_m`` along its axis."""
    return look_at_pose(np.asarray(target, float), np.array([0.0, 0.0, 1.0]), height_m,
                        math.radians(inclination_deg), "x")


def parse_region(region: dict[str, Any]) -> RegionSection:
    doc = copy.deepcopy(SIM)
    doc["region"] = region
    return parse_config(doc, "cell.toml").region


# ---------------------------------------------------------------------- configuration
@pytest.mark.parametrize(("region", "message"), [
    ({"polygon_px": [[0, 0], [10, 0]]}, "key 'region.polygon_px': needs at least 3 items, got 2"),
    ({"polygon_px": [[0, 0], [10, 0], [20, 0]]}, "key 'region.polygon_px': the polygon encloses 0 px^2"),
    ({"polygon_px": [[0, 0], [10, 0], [10, 1e6]]}, "key 'region.polygon_px[2]': vertex (10, 1e+06) px is beyond"),
    ({"polygon_px": [[0, 0], [10, 0], [10, math.inf]]}, "key 'region.polygon_px[2][1]': expected a finite number"),
    ({"polygon_px": [[0, 0], [10, 0], [10]]}, "key 'region.polygon_px[2]': expected a list of 2 numbers, got 1"),
    ({"box_min_m": [0.0, 0.0, 0.0]}, "key 'region.box_max_m': a base-frame box needs both box_min_m and box_max_m"),
    ({"box_max_m": [0.1, 0.1, 0.1]}, "key 'region.box_min_m': a base-frame box needs both"),
    ({"box_min_m": [0.0, 0.0, 0.0], "box_max_m": [0.1, 0.1, 0.0]},
     "key 'region.box_max_m': must exceed box_min_m on every axis (z: 0 <= 0 m)"),
    ({"box_min_m": [0.0, 0.0, math.nan], "box_max_m": [0.1, 0.1, 0.1]},
     "key 'region.box_min_m[2]': expected a finite number"),
    ({"box_min_m": [0.0, 0.0, -11.0], "box_max_m": [0.1, 0.1, 0.1]}, "key 'region.box_min_m': must be >= -10.0"),
    ({"polygon": [[0, 0], [10, 0], [10, 10]]},
     "key 'region.polygon': unknown key; did you mean 'polygon_px'? (expected one of: box_max_m"),
])
def test_a_bad_region_is_one_line_naming_the_key(region: dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError) as info:
        parse_region(region)
    text = str(info.value)
    assert text.startswith("cell.toml: ") and message in text and "\n" not in text, text


@pytest.mark.parametrize(("reference", "message"), [
    ({"search_tolerance_deg": 0.0}, "key 'reference.search_tolerance_deg': must be > 0.0"),
    ({"search_tolerance_deg": 91.0}, "key 'reference.search_tolerance_deg': must be <= 90.0"),
    ({"search_tolerance_m": -0.1}, "key 'reference.search_tolerance_m': must be > 0.0"),
    ({"search": 1}, "key 'reference.search': expected a boolean"),
])
def test_bad_search_tolerances_are_one_line_naming_the_key(reference: dict[str, Any], message: str) -> None:
    doc = copy.deepcopy(SIM)
    doc["reference"].update(reference)
    with pytest.raises(ConfigError, match=None) as info:
        parse_config(doc, "cell.toml")
    assert message in str(info.value), str(info.value)


def test_no_region_or_an_empty_one_is_the_whole_image() -> None:
    assert parse_config(copy.deepcopy(SIM), "x").region.whole_image
    empty = parse_region({})
    assert empty.whole_image and region_mask(empty, PINHOLE, camera_at(0.5, 80.0)) is None
    assert region_document(empty, None) is None


def test_the_search_needs_a_reference_a_mount_and_search_on() -> None:
    config = parse_config(copy.deepcopy(SIM), "x")
    assert config.search_reference is config.reference is not None
    assert config.reference.search_tolerance_rad == pytest.approx(math.radians(15.0))   # the defaults
    assert config.reference.search_tolerance_m == 0.1
    no_mount = copy.deepcopy(SIM)
    del no_mount["mount"]
    assert parse_config(no_mount, "x").search_reference is None   # the identity mount predicts nothing
    off = copy.deepcopy(SIM)
    off["reference"]["search"] = False
    assert parse_config(off, "x").search_reference is None


# ---------------------------------------------------------------------- polygon
def test_polygon_mask_holds_the_pixel_centres_inside_and_on_its_edges() -> None:
    square = polygon_mask([[10, 10], [20, 10], [20, 20], [10, 20]], (40, 50))
    rows, cols = np.nonzero(square)
    assert square.shape == (40, 50) and square.sum() == 11 * 11     # columns and rows 10..20
    assert (rows.min(), rows.max(), cols.min(), cols.max()) == (10, 20, 10, 20)
    # an irregular pentagon against OpenCV's point-in-polygon test at every pixel centre
    poly = np.array([[30, 12], [190, 25], [205, 140], [90, 165], [12, 80]], np.float32)
    mask = polygon_mask(poly, (172, 224))
    vv, uu = np.mgrid[0:172, 0:224]
    dist = np.array([cv2.pointPolygonTest(poly, (float(u), float(v)), True) for u, v in
                     zip(uu.ravel(), vv.ravel(), strict=True)]).reshape(172, 224)
    assert np.array_equal(mask[dist >= 1.0], np.ones(int((dist >= 1.0).sum()), bool))     # inside: all in
    assert not mask[dist <= -1.0].any()                                                     # outside: none
    area = cv2.contourArea(poly)
    assert abs(mask.sum() - area) < cv2.arcLength(poly, True)     # the rest is the 1 px band along the edges


def test_a_polygon_reaching_past_the_image_is_clipped_and_one_far_outside_is_refused() -> None:
    camera = camera_at(0.5, 80.0)
    half = parse_region({"polygon_px": [[-50, -50], [300, -50], [300, 85.4], [-50, 85.4]]})
    mask = region_mask(half, PINHOLE, camera)
    assert mask is not None and mask.sum() == 224 * 86              # rows 0..85, every column
    far = parse_region({"polygon_px": [[0, 0], [100, 0], [100, 400]]})
    with pytest.raises(ConfigError) as info:
        region_mask(far, PINHOLE, camera, source="cell.toml")
    assert str(info.value).startswith("cell.toml: key 'region.polygon_px[2]': vertex (100, 400) px lies more than "
                                      "one image size outside the 224x172 depth image")
    outside = parse_region({"polygon_px": [[-100, -100], [-10, -100], [-10, -10]]})
    with pytest.raises(CalibrationError, match="holds no pixel of the 224x172 image"):
        region_mask(outside, PINHOLE, camera)


# ---------------------------------------------------------------------- base-frame box
def test_box_mask_is_the_projected_box_on_a_pinhole_camera() -> None:
    """Without distortion the pixels whose ray crosses a convex box are those inside its projected hull."""
    camera = camera_at(0.55, 70.0)
    lo, hi = np.array([0.22, -0.08, 0.0]), np.array([0.36, 0.05, 0.12])
    mask = box_mask(PINHOLE, camera, lo, hi)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    hull = cv2.convexHull(project(PINHOLE, camera.inv().apply(corners)).astype(np.float32))
    vv, uu = np.mgrid[0:172, 0:224]
    dist = np.array([cv2.pointPolygonTest(hull, (float(u), float(v)), True) for u, v in
                     zip(uu.ravel(), vv.ravel(), strict=True)]).reshape(172, 224)
    assert 1000 < mask.sum() < 172 * 224 // 2
    assert mask[dist > 1e-6].all() and not mask[dist < -1e-6].any()


def test_box_mask_matches_the_pixels_that_see_a_simulated_box_through_the_lens() -> None:
    """The sim's ray caster (distorted lens, the box a solid on the table) hits the box on the same pixels."""
    intr = o3r222_intrinsics(k1=-0.06, k2=0.01, p1=0.001)     # the sim camera's barrel distortion and more
    scene = Scene(np.zeros(3), np.array([0.0, 0.0, 1.0]), (Box((0.3, 0.02), (0.12, 0.09, 0.15), 0.0),))
    camera = camera_at(0.6, 75.0)
    rays = pixel_grid_rays(intr).reshape(-1, 3) @ camera.rotation_matrix.T
    _t, _n, _hit, surface = scene.raycast_surfaces(camera.translation, rays)
    sees_box = (surface >= 1).reshape(172, 224)
    lo = scene.plane_to_world([0.3 - 0.06, 0.02 - 0.045, 0.0])
    hi = scene.plane_to_world([0.3 + 0.06, 0.02 + 0.045, 0.15])
    mask = box_mask(intr, camera, lo, hi)
    assert sees_box.sum() > 2000
    assert np.array_equal(mask, sees_box)


def test_a_box_behind_the_camera_holds_nothing_and_one_around_it_everything() -> None:
    camera = camera_at(0.5, 90.0)          # looking straight down from z = 0.5
    above = box_mask(PINHOLE, camera, [0.2, -0.1, 0.6], [0.4, 0.1, 0.7])
    around = box_mask(PINHOLE, camera, [0.0, -0.3, 0.4], [0.6, 0.3, 0.6])
    assert not above.any() and around.all()


def test_polygon_and_box_together_give_the_pixels_in_both() -> None:
    camera = camera_at(0.5, 90.0)
    region = parse_region({"polygon_px": [[0, 0], [111, 0], [111, 171], [0, 171]],
                           "box_min_m": [0.2, -0.1, -0.01], "box_max_m": [0.4, 0.1, 0.01]})
    box = box_mask(PINHOLE, camera, [0.2, -0.1, -0.01], [0.4, 0.1, 0.01])
    mask = region_mask(region, PINHOLE, camera)
    assert mask is not None and 0 < mask.sum() < box.sum()
    assert np.array_equal(mask, box & polygon_mask(region.polygon_px, (172, 224)))
    doc = region_document(region, mask)
    assert doc is not None and doc["n_pixels"] == int(mask.sum())
    assert doc["fraction_of_image"] == pytest.approx(mask.sum() / (172 * 224))
    assert doc["box_min_m"] == [0.2, -0.1, -0.01] and doc["polygon_px"][1] == [111.0, 0.0]


def test_the_dry_run_says_where_the_fit_will_look() -> None:
    doc = copy.deepcopy(SIM)
    doc["region"] = {"box_min_m": [0.1, -0.2, -0.01], "box_max_m": [0.5, 0.2, 0.01]}
    doc["reference"].update(search_tolerance_deg=5.0, search_tolerance_m=0.02)
    out: list[str] = []
    dry_run(parse_config(doc, "x"), emit=out.append)
    assert ("; full-frame fit over the base-frame box [100, -200, -10]..[500, 200, 10] mm, near [reference] "
            "within 5 deg / 20 mm; no device is connected") in out[0]
    doc["reference"]["search"] = False
    del doc["region"]
    out.clear()
    dry_run(parse_config(doc, "x"), emit=out.append)
    assert "; full-frame fit over the whole image, no expected plane;" in out[0]
