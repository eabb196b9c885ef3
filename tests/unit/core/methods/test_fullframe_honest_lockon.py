"""A fit on one quantisation level is refused (gate ``residual_floor``); an exact plane is not one (issue 27)."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from cellcal.core.calibration.config import look_at_pose
from cellcal.core.methods.fullframe import check_gates, fit_full_frame
from cellcal.devices.errors import CalibrationQualityError
from cellcal.devices.measurement import UNKNOWN_MODEL
from cellcal.devices.pose import Pose
from cellcal.devices.types import Frame, Intrinsics
from cellcal.sims.camera import SimCamera, SimCameraConfig
from cellcal.sims.scene import Box, Scene
from cellcal.sims.systematic import SystematicConfig
from cellcal.sims.world import SimWorld
from tests.support.repo_paths import TEST_DATA

OAK = TEST_DATA / "real" / "oak"
#: OAK-D: 75 mm baseline; the recordings' nominal pinhole (see tests/data/real/NOTICE.md).
FOCAL_PX, BASELINE_M = 480.0, 0.075


def _depth_frame(z_m: np.ndarray, f: float = FOCAL_PX) -> Frame:
    """A Z-depth image (metres, 0 = none) as a frame with a pinhole at the image centre."""
    h, w = z_m.shape
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    valid = z_m > 0
    z = np.where(valid, z_m, np.nan)
    xyz = np.stack([(u - (w - 1) / 2) / f * z, (v - (h - 1) / 2) / f * z, z], -1).astype(np.float32)
    dist = np.linalg.norm(xyz, axis=-1).astype(np.float32)
    intr = Intrinsics(width=w, height=h, fx=f, fy=f, cx=(w - 1) / 2, cy=(h - 1) / 2)
    return Frame(distance=dist, xyz=xyz, amplitude=np.ones_like(dist), valid=valid, intrinsics=intr,
                 timestamp=0.0, sequence=0)


def _integer_disparity_floor(tilt_deg: float, bits: int) -> Frame:
    """A floor 0.7 m away tilted about x, with an 8 cm box on it, seen by 640x360 stereo with ``bits`` subpixel bits."""
    h, w = 360, 640
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    rx, ry = (u - (w - 1) / 2) / FOCAL_PX, (v - (h - 1) / 2) / FOCAL_PX
    z = 0.7 / (1.0 + ry * math.tan(math.radians(tilt_deg)))
    z = np.where((np.abs(rx) < 0.15) & (np.abs(ry - 0.1) < 0.12), z - 0.08, z)
    step = 2.0 ** -bits
    fb = FOCAL_PX * BASELINE_M
    return _depth_frame(fb / (np.round(fb / z / step) * step))  # Z from the rounded disparity


@pytest.mark.parametrize("tilt_deg", [0.5, 1.0, 3.0])
def test_integer_disparity_lock_on_is_refused(tilt_deg: float) -> None:
    """Depth levels 13.6 mm apart: the fit sits on one level with RMS 0 and tilt 0 (the floor is tilted)."""
    res = fit_full_frame(_integer_disparity_floor(tilt_deg, 0))
    assert res.residual_rms_m < 1e-6 and abs(res.tilt_x_rad) < 1e-6          # what the fit does on its own
    with pytest.raises(CalibrationQualityError) as info:
        check_gates(res)
    text = str(info.value)
    assert info.value.gate == "residual_floor" and "\n" not in text
    assert "sat on one quantisation level" in text and "1 distinct value(s)" in text
    assert res.lock_on and res.to_dict()["lock_on"] == res.lock_on


def test_subpixel_disparity_is_no_lock_on() -> None:
    """With 3 subpixel bits (1.7 mm levels) the fit spans many levels and finds the 3 deg tilt."""
    res = fit_full_frame(_integer_disparity_floor(3.0, 3))
    assert res.lock_on == "" and res.gates["residual_floor"][2]
    assert math.degrees(res.tilt_x_rad) == pytest.approx(3.0, abs=0.05)


@pytest.mark.parametrize("inclination_deg", [90.0, 80.0])
@pytest.mark.parametrize("stated", [True, False])
def test_noise_free_exact_planes_are_no_lock_on(inclination_deg: float, stated: bool) -> None:
    """The sim without noise or quantisation: head-on every pixel has one Z and a residual of exactly 0; at 80 deg
    41 % of the float32 residuals are 0 and the rest ~1e-7 m. Neither is a lock-on, with the sim's model or none."""
    cam = SimCamera(SimCameraConfig(noise=False, quantisation_m=0.0, seed=1),  # an ideal camera: exact planes
                    world=SimWorld(Scene(), Pose.identity(), seed=1, systematic=SystematicConfig.off()))
    pose = look_at_pose(np.array([0.3, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]), 0.6, math.radians(inclination_deg), "x")
    frame = cam.render(pose)
    if not stated:
        frame = dataclasses.replace(frame, measurement=UNKNOWN_MODEL)
    res = fit_full_frame(frame)
    assert res.residual_rms_m < 1e-7 and res.lock_on == ""
    check_gates(res)
    assert math.degrees(res.angle_rad) == pytest.approx(inclination_deg, abs=1e-4)


def test_noise_free_sim_with_boxes_and_its_quantisation_passes() -> None:
    """The sim's default 1 mm range step, noise off, boxes on the table: no lock-on, the residual at its floor."""
    scene = Scene(np.zeros(3), np.array([0.0, 0.0, 1.0]), (Box((0.3, 0.05), (0.08, 0.1, 0.05)),))
    cam = SimCamera(SimCameraConfig(noise=False, seed=4), world=SimWorld(scene, Pose.identity(), seed=4))
    pose = look_at_pose(np.array([0.3, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]), 0.6, math.radians(90.0), "x")
    res = fit_full_frame(cam.render(pose))
    assert res.lock_on == "" and res.residual_floor_m > 0
    assert res.gates["residual_floor"][0] == pytest.approx(1.0, abs=0.1)
    check_gates(res)


def _oak_frames() -> list[Path]:
    paths = sorted(OAK.glob("*_depth.npy"))
    if not paths:
        pytest.skip(f"real OAK frames not found in {OAK} (tests/data/real/oak)")
    return paths


def test_real_oak_frames_never_pass_locked_on() -> None:
    """Seven real OAK frames without subpixel (unknown model): five locked on one level before; none may pass
    locked on, and every lock-on is named by the residual_floor gate."""
    locked = 0
    for path in _oak_frames():
        res = fit_full_frame(_depth_frame(np.load(path).astype(np.float64) / 1000.0))
        if res.residual_rms_m < 1e-6:                                 # sat on one level
            locked += 1
            assert res.lock_on and not res.gates["residual_floor"][2], path.name
            with pytest.raises(CalibrationQualityError) as info:
                check_gates(res)
            assert info.value.gate == "residual_floor", path.name
    assert locked == 5
