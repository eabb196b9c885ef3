"""The stereo seam: triangulating frames go to ``fit_disparity``; region, gates and result are shared (issue 27)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cellcal.core.calibration.config import look_at_pose
from cellcal.core.geometry.planes import Plane
from cellcal.core.methods.fullframe import check_gates, fit_full_frame
from cellcal.core.methods.fullframe.expected import ExpectedPlane
from cellcal.devices.pose import Pose
from cellcal.devices.types import Frame
from cellcal.sims.scene import Scene
from cellcal.sims.stereo import SimStereoCamera, SimStereoConfig
from cellcal.sims.systematic import SystematicConfig
from cellcal.sims.world import SimWorld

UP = np.array([0.0, 0.0, 1.0])


def _stereo(bits: int) -> tuple[Frame, Plane]:
    pose = look_at_pose(np.array([0.3, 0.0, 0.0]), UP, 0.7, math.radians(80.0), "x")
    cam = SimStereoCamera(SimStereoConfig(width=320, height=200, subpixel_bits=bits),
                          world=SimWorld(Scene(), Pose.identity(), flange_pose=pose, seed=3,
                                         systematic=SystematicConfig.off()))  # the noise model's intervals
    truth = Plane.from_point_normal(np.zeros(3), UP).transformed(pose.inv()).oriented_toward_origin()
    return cam.render(pose), truth


@pytest.mark.parametrize("bits", [0, 3])
def test_stereo_frames_are_fitted_in_disparity_with_the_shared_gates(bits: int) -> None:
    frame, truth = _stereo(bits)
    assert frame.measurement.triangulating
    res = fit_full_frame(frame)
    check_gates(res)
    assert res.native_space == "disparity" and res.to_dict()["native_space"] == "disparity"
    assert res.to_dict()["measurement"]["kind"] == "stereo"
    assert res.residual_floor_m > 0 and res.lock_on == ""
    err = abs(res.tilt_x_rad - truth.tilt_about_x_rad())
    assert err < 4.0 * res.tilt_x_sigma_rad                       # within its interval's reach
    assert math.isnan(res.multipath.value)                        # no radial range bias in disparity space


def test_stereo_region_and_expected_plane_pass_through_the_seam() -> None:
    frame, truth = _stereo(3)
    h, w = frame.shape
    region = np.zeros((h, w), bool)
    region[:, : w // 2] = True
    res = fit_full_frame(frame, region=region, expected=ExpectedPlane(truth, math.radians(2.0), 0.02))
    check_gates(res)
    assert not res.inlier_mask[:, w // 2:].any() and res.region_pixels == region.sum()
    assert res.valid_fraction == np.count_nonzero(frame.valid & region) / region.sum()
    angle, offset = res.expected_departure
    assert res.gates["expected_plane"] == (angle, math.radians(2.0), True) and offset < 0.005
