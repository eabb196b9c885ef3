"""The plane the user means: a region of interest and an expected plane in the full-frame fit (issue 27)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from tof_frames import ToFSetup, make_frame, scattered_boxes, with_

from cellcal.core.calibration.config import look_at_pose
from cellcal.core.geometry.planes import Plane
from cellcal.core.methods.fullframe import FullFrameSettings, check_gates, fit_full_frame
from cellcal.core.methods.fullframe.expected import ExpectedPlane
from cellcal.core.methods.fullframe.gates import gate_table
from cellcal.devices.errors import CalibrationError, CalibrationQualityError
from cellcal.devices.pose import Pose
from cellcal.devices.types import Frame
from cellcal.sims.camera import SimCamera, SimCameraConfig
from cellcal.sims.scene import Box, Scene
from cellcal.sims.systematic import SystematicConfig
from cellcal.sims.world import SimWorld

UP = np.array([0.0, 0.0, 1.0])
DESK_M = 0.12


def _masked(frame: Frame, valid: np.ndarray, xyz: np.ndarray | None = None) -> Frame:
    xyz = (frame.xyz if xyz is None else xyz).astype(np.float32).copy()
    xyz[~valid] = np.nan
    dist = np.linalg.norm(xyz, axis=-1).astype(np.float32)
    return dataclasses.replace(frame, xyz=xyz, distance=dist, valid=valid & np.isfinite(dist))


def _one_line(info: pytest.ExceptionInfo[BaseException]) -> str:
    text = str(info.value)
    assert "\n" not in text and "Traceback" not in text
    return text


@pytest.fixture(scope="module")
def desk() -> tuple[Frame, Plane, Plane]:
    """The sim's floor with a desk top 12 cm above it hiding about two thirds of the view."""
    scene = Scene(np.zeros(3), UP, (Box((0.35, 0.0), (0.6, 0.8, DESK_M)),))
    # an ideal camera: the desk top's height pinned to 2 mm
    cam = SimCamera(SimCameraConfig(seed=2), world=SimWorld(scene, Pose.identity(), seed=2,
                                                            systematic=SystematicConfig.off()))
    pose = look_at_pose(np.array([0.3, 0.0, 0.0]), UP, 0.9, math.radians(80.0), "x")
    floor = Plane.from_point_normal(np.zeros(3), UP).transformed(pose.inv()).oriented_toward_origin()
    top = Plane.from_point_normal(np.array([0.0, 0.0, DESK_M]), UP).transformed(pose.inv()).oriented_toward_origin()
    return cam.render(pose), floor, top


# ---------------------------------------------------------------------- expected plane
def test_without_expected_the_desk_wins_with_it_the_floor(desk: tuple[Frame, Plane, Plane]) -> None:
    frame, floor, top = desk
    near = ExpectedPlane(floor, math.radians(2.0), 0.02)
    free = fit_full_frame(frame)
    angle, offset = near.departure(free.plane)
    assert offset == pytest.approx(DESK_M, abs=0.002)            # the larger surface: the desk top
    assert "expected_plane" not in free.gates and free.expected_departure is None
    meant = fit_full_frame(frame, expected=near)
    angle, offset = near.departure(meant.plane)
    assert angle < math.radians(0.05) and offset < 0.001           # the floor, within 1 mm
    value, threshold, ok = meant.gates["expected_plane"]
    assert ok and value == pytest.approx(angle) and threshold == near.angle_tolerance_rad
    assert meant.expected_departure == pytest.approx((angle, offset))
    assert meant.to_dict()["expected_departure"]["offset_m"] == pytest.approx(offset)
    # the desk top is the plane the user means there
    on_desk = fit_full_frame(frame, expected=ExpectedPlane(top, math.radians(2.0), 0.02))
    assert ExpectedPlane(top, 0.1, 0.1).departure(on_desk.plane)[1] < 0.001


def test_no_plane_near_the_expected_one_is_a_named_gate_naming_the_nearest(desk: tuple[Frame, Plane, Plane]) -> None:
    frame, floor, _ = desk
    tilted = Plane(floor.normal, floor.offset_m + 0.3)             # 30 cm beyond the floor: nothing there
    with pytest.raises(CalibrationQualityError) as info:
        fit_full_frame(frame, expected=ExpectedPlane(tilted, math.radians(3.0), 0.05))
    text = _one_line(info)
    assert info.value.gate == "expected_plane" and info.value.threshold == pytest.approx(math.radians(3.0))
    assert "no plane within 3 deg and 50 mm of the expected one" in text and "the nearest is" in text
    assert "mm from the camera" in text


def test_expected_plane_gate_pinned_at_its_tolerances(desk: tuple[Frame, Plane, Plane]) -> None:
    """The final plane's departure against each tolerance: equal passes, the next float below fails."""
    frame, floor, _ = desk
    res = fit_full_frame(frame, expected=ExpectedPlane(floor, math.radians(2.0), 0.02))
    angle, offset = res.expected_departure
    cfg = res.settings
    at = dataclasses.replace(res, expected_tolerance=(angle, offset))
    assert gate_table(cfg, at)["expected_plane"] == (angle, angle, True)
    with pytest.raises(CalibrationQualityError) as info:
        check_gates(at, cfg)
    assert info.value.gate == "flatness"                            # the desk beside the floor: the next gate
    for tol, failed, held in (((np.nextafter(angle, 0.0), offset), " deg beyond the tolerance of ", "its offset"),
                              ((angle, np.nextafter(offset, 0.0)), " mm beyond the tolerance of ", "its angle")):
        with pytest.raises(CalibrationQualityError) as info:
            check_gates(dataclasses.replace(res, expected_tolerance=tol), cfg)
        assert info.value.gate == "expected_plane" and info.value.value == angle
        text = _one_line(info)
        assert "from the expected one, " in text and failed in text and f"({held}, " in text
    assert gate_table(cfg, dataclasses.replace(res, expected_departure=None))["valid_fraction"][2]


# ---------------------------------------------------------------------- region of interest
def test_region_gates_count_only_the_region() -> None:
    """The plane in the left 40 % of the image, junk on the right: the whole image fails, the region passes."""
    frame = make_frame(ToFSetup(), 5)
    h, w = frame.shape
    xyz = frame.xyz.astype(np.float64).copy()
    right = xyz[:, int(0.4 * w):]
    right *= np.random.default_rng(1).uniform(0.4, 0.9, right.shape[:2])[..., None]   # along the same rays
    junk = _masked(frame, frame.valid, xyz)
    with pytest.raises(CalibrationQualityError) as info:
        check_gates(fit_full_frame(junk))
    assert info.value.gate == "inlier_fraction"
    region = np.zeros((h, w), bool)
    region[:, : int(0.4 * w)] = True
    res = fit_full_frame(junk, region=region)
    check_gates(res)
    assert res.valid_fraction == np.count_nonzero(junk.valid & region) / np.count_nonzero(region)
    assert res.region_pixels == np.count_nonzero(region)
    assert res.n_points == np.count_nonzero(junk.valid & region)
    assert not res.inlier_mask[~region].any()                      # pixels outside are ignored
    assert res.coverage == 1.0                                     # over the cells the region covers
    assert res.inlier_fraction > 0.95


def test_region_border_is_not_an_edge_that_eats_the_plane() -> None:
    frame = make_frame(ToFSetup(), 6)
    h, w = frame.shape
    region = np.zeros((h, w), bool)
    region[20:150, 30:170] = True
    res = fit_full_frame(frame, region=region)
    check_gates(res)
    rim = region & ~np.pad(region[1:-1, 1:-1], 1)                  # the region's outermost ring of pixels
    ok = rim & frame.valid
    assert np.count_nonzero(res.inlier_mask & ok) >= 0.95 * np.count_nonzero(ok)


def test_hand_masked_frames_fail_whole_image_gates_but_pass_as_a_region() -> None:
    """A 20 % region: as a hand mask the valid fraction fails; as a region every gate passes."""
    base = ToFSetup()
    frame = make_frame(with_(base, boxes=scattered_boxes(0.2, 3, base)), 3)
    h, w = frame.shape
    region = np.zeros((h, w), bool)
    region[40:120, 60:140] = True                                  # 16.6 % of the image
    with pytest.raises(CalibrationQualityError) as info:
        check_gates(fit_full_frame(_masked(frame, frame.valid & region)))
    assert info.value.gate == "valid_fraction"
    check_gates(fit_full_frame(frame, region=region))


def test_bad_regions_are_one_line_errors() -> None:
    frame = make_frame(ToFSetup(), 1)
    with pytest.raises(CalibrationError, match="bool mask of shape"):
        fit_full_frame(frame, region=np.ones((10, 10), bool))
    with pytest.raises(CalibrationError, match="holds no pixel"):
        fit_full_frame(frame, region=np.zeros(frame.shape, bool))
    tiny = np.zeros(frame.shape, bool)
    tiny[80, 100:110] = True                                       # 10 pixels
    with pytest.raises(CalibrationQualityError) as info:
        fit_full_frame(frame, region=tiny)
    assert info.value.gate == "valid_fraction" and "valid pixel in the region" in _one_line(info)


def test_nothing_left_after_the_clean_up_is_the_same_named_gate_at_any_size() -> None:
    """Valid pixels in 2-px stripes between 3-px invalid stripes: every one lies within the 2-px edge margin.

    15,400 valid pixels (more than the small-frame check sees) used to give a bare CalibrationError."""
    frame = make_frame(ToFSetup(), 2)
    valid = frame.valid.copy()
    valid[:, np.arange(frame.shape[1]) % 5 >= 2] = False
    assert np.count_nonzero(valid) > 4096
    with pytest.raises(CalibrationQualityError) as info:
        fit_full_frame(_masked(frame, valid))
    text = _one_line(info)
    assert info.value.gate == "valid_fraction" and info.value.value < 16 / valid.size
    assert "left after the edge clean-up" in text and "needs 16" in text
    assert info.value.threshold == FullFrameSettings().min_valid_fraction
