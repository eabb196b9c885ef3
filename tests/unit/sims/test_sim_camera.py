"""The simulated O3R222-like camera: geometry, noise model, invalid pixels, seeding, sharing.

The ToF artefacts (mixed pixels, multipath, amplitude noise, drift) are tested in
test_sim_tof_artefacts.py."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cellcal.devices.base import BackendContext
from cellcal.devices.errors import ConfigError, NotConnectedError
from cellcal.devices.geometry.camera_model import pixel_grid_rays, project
from cellcal.devices.pose import Pose
from cellcal.sims.camera import CONF_INVALID, CONF_LOW_AMPLITUDE, CONF_OUT_OF_RANGE, SimCamera, SimCameraConfig
from cellcal.sims.scene import Box, Scene
from cellcal.sims.systematic import SystematicConfig
from cellcal.sims.tof import ArtefactsConfig, datasheet_sigma_m, noise_sigma_m
from cellcal.sims.world import SimWorld, world_from_context

DOWN = Rotation.from_euler("x", 180.0, degrees=True)  # camera z along world -z


def make_camera(camera_pose: Pose, scene: Scene | None = None, world_seed: int = 7,
                artefacts: ArtefactsConfig | None = None, systematic: SystematicConfig | None = None,
                **cfg: object) -> SimCamera:
    # an ideal camera unless a test names its systematic errors (ADR 0054)
    world = SimWorld(scene or Scene(), mount=Pose.identity(), flange_pose=camera_pose, seed=world_seed,
                     artefacts=artefacts, systematic=systematic or SystematicConfig.off())
    return SimCamera(SimCameraConfig(**cfg), world=world)  # type: ignore[arg-type]


def tilted_pose(height_m: float, tilt_deg: float) -> Pose:
    """Camera above the plane z=0, optical axis tilted by tilt_deg from straight down (about camera x)."""
    rot = DOWN * Rotation.from_euler("x", tilt_deg, degrees=True)
    return Pose(rot, np.array([0.0, 0.0, height_m]))


def test_intrinsics_follow_o3r222_field_of_view() -> None:
    cam = make_camera(tilted_pose(0.5, 0.0))
    with cam:
        intr = cam.intrinsics
    assert (intr.width, intr.height) == (224, 172)
    assert intr.fx == pytest.approx(112.0 / math.tan(math.radians(30.0)))  # 193.99 px
    assert intr.fy == pytest.approx(86.0 / math.tan(math.radians(22.5)))  # 207.62 px
    assert (intr.cx, intr.cy) == (111.5, 85.5)
    assert intr.has_distortion and -0.1 <= intr.k1 <= 0.1
    pinhole = make_camera(tilted_pose(0.5, 0.0), distortion=False)
    assert not pinhole.render(tilted_pose(0.5, 0.0)).intrinsics.has_distortion


@pytest.mark.parametrize("distortion", [True, False])
def test_noise_free_xyz_lies_on_plane_and_matches_intrinsics(distortion: bool) -> None:
    pose = tilted_pose(0.55, 10.0)
    cam = make_camera(pose, noise=False, quantisation_m=0.0, distortion=distortion)
    frame = cam.render(pose)
    assert frame.valid.all()
    pts_cam = frame.xyz.reshape(-1, 3).astype(np.float64)
    np.testing.assert_allclose(pose.apply(pts_cam)[:, 2], 0.0, atol=1e-6)
    # XYZ is ray * distance, and projects back onto its own pixel.
    np.testing.assert_allclose(np.linalg.norm(frame.xyz, axis=2), frame.distance, rtol=1e-6)
    vv, uu = np.mgrid[0:172, 0:224]
    uv = project(frame.intrinsics, pts_cam)
    np.testing.assert_allclose(uv, np.column_stack([uu.ravel(), vv.ravel()]), atol=1e-3)
    # The centre pixel's distance follows the tilt: h / cos(tilt) (principal point at pixel 111.5, 85.5).
    centre = cam.render(pose).distance[85:87, 111:113].mean()
    assert centre == pytest.approx(0.55 / math.cos(math.radians(10.0)), abs=2e-3)


def test_quantisation_keeps_points_within_half_a_millimetre() -> None:
    pose = tilted_pose(0.6, 20.0)
    cam = make_camera(pose, noise=False)
    frame = cam.render(pose)
    d = frame.distance[frame.valid].astype(np.float64)
    np.testing.assert_allclose(d * 1000.0, np.round(d * 1000.0), atol=1e-3)  # whole millimetres (float32)
    off_plane = pose.apply(frame.xyz[frame.valid].astype(np.float64))[:, 2]
    assert np.max(np.abs(off_plane)) <= 0.0005 + 1e-6
    assert np.max(np.abs(off_plane)) > 0.0003  # quantisation really happened


@pytest.mark.parametrize(("height_m", "amplitude_noise", "sigma_mm"), [
    # the default amplitude law, set against the real O3R frame (per-pixel F = 2.7 mm, S = 2.24 mm, floor n = 0.9):
    (0.5, True, 2.8458),  # hypot(2.7, 2.24 * sqrt((4 + 0.9) / 1.9) / 4 = 0.90) mm: the per-pixel term dominates
    (1.5, True, 5.0264),  # hypot(2.7, 2.24 * sqrt((0.444 + 0.9) / 1.9) / 0.444 = 4.24) mm
    (0.5, False, 3.2 * 0.5**1.5),  # the data-sheet law
    (1.5, False, 3.2 * 1.5**1.5),
])
def test_noise_statistics_match_documented_model(height_m: float, amplitude_noise: bool, sigma_mm: float) -> None:
    law = noise_sigma_m if amplitude_noise else datasheet_sigma_m
    assert float(law(height_m)) * 1000.0 == pytest.approx(sigma_mm, rel=1e-4)
    pose = tilted_pose(height_m, 0.0)
    arte = ArtefactsConfig(amplitude_noise=amplitude_noise)
    cam = make_camera(pose, world_seed=11, artefacts=arte)
    window = (slice(80, 92), slice(106, 118))  # within ~2 deg of the axis: cos(incidence) > 0.999
    stack = np.array([cam.render(pose).distance[window] for _ in range(40)], dtype=np.float64)
    per_pixel_std = stack.std(axis=0, ddof=1)
    measured_mm = float(np.sqrt(np.mean(per_pixel_std**2))) * 1000.0
    expected_mm = math.sqrt(sigma_mm**2 + 1.0 / 12.0)  # + 1 mm quantisation
    assert measured_mm == pytest.approx(expected_mm, rel=0.06)
    # Unbiased: the mean over frames matches the true distance within 4 standard errors.
    truth = make_camera(pose, noise=False, quantisation_m=0.0, artefacts=arte).render(pose).distance[window]
    bias_mm = float(np.mean(stack.mean(axis=0) - truth)) * 1000.0
    assert abs(bias_mm) < 4 * expected_mm / math.sqrt(stack.size)


@pytest.mark.parametrize("law", [noise_sigma_m, datasheet_sigma_m])
def test_quoted_repeatability_is_met_as_two_sigma(law: object) -> None:
    from cellcal.sims.camera import REPEATABILITY_SIGMAS

    rep = REPEATABILITY_SIGMAS * law(np.array([0.5, 0.99, 1.5, 2.0, 4.0])) * 1000.0  # type: ignore[operator]
    assert np.all(rep[:2] < 7.0)  # < 7 mm under 1 m
    assert 10.0 < rep[2] < 20.0 and 10.0 < rep[3] < 20.0  # ~15 mm at 1-2 m
    assert rep[4] == pytest.approx(51.0, abs=1.0)  # up to 51 mm beyond 4 m


def test_grazing_pixels_are_invalid() -> None:
    # Optical axis 70 deg from the normal: the upper image rows see the plane beyond 80 deg.
    pose = tilted_pose(0.3, 70.0)
    cam = make_camera(pose, noise=False, max_range_m=50.0)
    frame = cam.render(pose)
    rays_world = pose.apply_vector(pixel_grid_rays(frame.intrinsics).reshape(-1, 3))
    angle = np.degrees(np.arccos(np.abs(rays_world[:, 2]))).reshape(172, 224)
    clear = np.abs(angle - 80.0) > 0.05
    expected = (angle < 80.0) & (rays_world[:, 2].reshape(172, 224) < 0)
    assert 0.1 < expected.mean() < 0.9  # the test sees both kinds
    np.testing.assert_array_equal(frame.valid[clear], expected[clear])
    conf = frame.confidence
    assert conf is not None
    grazing = ~expected & clear & (rays_world[:, 2].reshape(172, 224) < 0)
    assert np.all(conf[grazing] & (CONF_INVALID | CONF_LOW_AMPLITUDE) == CONF_INVALID | CONF_LOW_AMPLITUDE)
    assert np.all(np.isnan(frame.distance[~frame.valid])) and np.all(np.isnan(frame.xyz[~frame.valid]))


def test_out_of_range_pixels_are_invalid() -> None:
    pose = tilted_pose(0.5, 0.0)
    cam = make_camera(pose, noise=False, quantisation_m=0.0, min_range_m=0.55)
    frame = cam.render(pose)
    truth = make_camera(pose, noise=False, quantisation_m=0.0).render(pose).distance
    np.testing.assert_array_equal(frame.valid, truth >= 0.55)
    assert 0.1 < frame.valid.mean() < 0.9
    assert frame.confidence is not None
    assert np.all(frame.confidence[~frame.valid] & CONF_OUT_OF_RANGE)
    far = make_camera(pose, noise=False, max_range_m=0.45).render(pose)
    assert not far.valid.any()


def test_box_on_plane_is_seen_at_its_height() -> None:
    scene = Scene(boxes=(Box((0.0, 0.0), (0.1, 0.1, 0.12)),))
    pose = tilted_pose(0.5, 0.0)
    frame = make_camera(pose, scene, noise=False, quantisation_m=0.0).render(pose)
    assert frame.distance[85, 111] == pytest.approx(0.38 / pixel_grid_rays(frame.intrinsics)[85, 111, 2], abs=1e-6)
    assert frame.distance[5, 5] > 0.5  # a corner still sees the plane
    amp = frame.amplitude
    assert amp[85, 111] > amp[5, 5] > 0  # nearer and more head-on is brighter


def test_same_seed_same_frames_other_seed_differs() -> None:
    pose = tilted_pose(0.6, 15.0)
    a, b, c = (make_camera(pose, world_seed=s) for s in (3, 3, 4))
    for _ in range(3):
        fa, fb, fc = a.render(pose), b.render(pose), c.render(pose)
        np.testing.assert_array_equal(fa.distance, fb.distance)
        np.testing.assert_array_equal(fa.valid, fb.valid)
        assert not np.array_equal(fa.distance, fc.distance, equal_nan=True)
    # An explicit config seed overrides the world's seed.
    d = make_camera(pose, world_seed=99, seed=3)
    e = make_camera(pose, world_seed=3)
    np.testing.assert_array_equal(d.render(pose).distance, e.render(pose).distance)


def test_capture_life_cycle_sequence_and_simulated_timestamps() -> None:
    cam = make_camera(tilted_pose(0.5, 0.0), frame_rate_hz=10.0)
    with pytest.raises(NotConnectedError):
        cam.capture(timeout=1.0)
    with cam:
        f1, f2, f3 = (cam.capture(timeout=1.0) for _ in range(3))
        assert cam.info().backend == "sim"
    assert [f.sequence for f in (f1, f2, f3)] == [1, 2, 3]
    assert f2.timestamp - f1.timestamp == pytest.approx(0.1, abs=1e-6)
    assert f3.timestamp - f2.timestamp == pytest.approx(0.1, abs=1e-6)
    assert f1.distance.dtype == np.float32 and f1.xyz.shape == (172, 224, 3)
    with pytest.raises(NotConnectedError):
        cam.capture(timeout=1.0)


def test_backends_built_from_one_document_share_the_world() -> None:
    doc = {
        "sim": {"plane_point_m": [0.0, 0.0, 0.05], "boxes": [{"center_xy_m": [0.3, 0.0], "size_m": [0.1, 0.1, 0.1]}],
                "seed": 5, "systematic": {"enabled": False},  # an ideal camera: exact heights
                "arm_errors": {"enabled": False}},  # and an ideal arm
        "mount": {"translation_m": [0.0, 0.0, 0.02], "rpy_deg": [0.0, 0.0, 0.0], "nominal_only": True},
        "camera": {"backend": "sim", "noise": False, "quantisation_m": 0.0},
    }
    ctx = BackendContext(source="cell.toml", section="camera", document=doc)
    cam = SimCamera.from_config(doc["camera"], ctx)
    assert world_from_context(ctx) is cam.world
    assert cam.world.seed == 5
    assert cam.world.mount.translation.tolist() == [0.0, 0.0, 0.02]
    # Default flange (0.3, 0, 0.5) pointing down, camera 2 cm beyond it, box top at 0.15: 0.33 m.
    frame = cam.render(cam.world.camera_pose())
    assert frame.distance[85:87, 111:113].mean() == pytest.approx(0.33, abs=1e-4)

    with pytest.raises(ConfigError, match=r"camera\.nosie"):
        SimCamera.from_config({"nosie": True}, ctx)
    bad = BackendContext(source="cell.toml", section="camera", document={"sim": {"plane_normal": [0, 0, 0]}})
    with pytest.raises(ConfigError, match="plane_normal"):
        SimCamera.from_config({}, bad)
