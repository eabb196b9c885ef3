"""The sim's OAK-like stereo camera: the disparity lattice, noise ∝ Z², left-right holes, speckle, its model, seeds."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cellcal.devices.base import BackendContext
from cellcal.devices.errors import ConfigError
from cellcal.devices.pose import Pose
from cellcal.sims.camera import SimCamera
from cellcal.sims.scene import Box, Scene
from cellcal.sims.stereo import SimStereoCamera, SimStereoConfig, occluded_in_other_camera
from cellcal.sims.systematic import SystematicConfig
from cellcal.sims.world import SimWorld

DOWN = Rotation.from_euler("x", 180.0, degrees=True)  # camera z along world -z
#: Small frames keep the tests cheap; the geometry does not depend on the size.
SMALL = {"width": 320, "height": 200}
QUIET = {"noise": False, "speckle_fraction": 0.0}


def looking_down(height_m: float, tilt_deg: float = 0.0) -> Pose:
    """Camera above the plane z = 0, optical axis tilted by ``tilt_deg`` from straight down about camera x."""
    return Pose(DOWN * Rotation.from_euler("x", tilt_deg, degrees=True), np.array([0.0, 0.0, height_m]))


def camera(pose: Pose, scene: Scene | None = None, seed: int = 5, systematic: SystematicConfig | None = None,
           **cfg: object) -> SimStereoCamera:
    # an ideal camera unless a test names its systematic errors (ADR 0054)
    world = SimWorld(scene or Scene(), Pose.identity(), flange_pose=pose, seed=seed,
                     systematic=systematic or SystematicConfig.off())
    return SimStereoCamera(SimStereoConfig(**{**SMALL, **cfg}), world=world)  # type: ignore[arg-type]


def z_of(frame_xyz: np.ndarray) -> np.ndarray:
    return frame_xyz[..., 2].astype(np.float64)


@pytest.mark.parametrize("bits", [0, 3])
def test_inverse_depth_lies_on_the_disparity_lattice(bits: int) -> None:
    pose = looking_down(0.6, 25.0)
    cam = camera(pose, subpixel_bits=bits, speckle_fraction=0.0)
    frame = cam.render(pose)
    cfg = cam.config
    z = z_of(frame.xyz)[frame.valid]
    assert z.size > 0.9 * frame.valid.size
    # 1/Z in units of the lattice step 2^-bits / (f·B): whole numbers
    k = cfg.fb_px_m * 2.0**bits / z
    np.testing.assert_allclose(k, np.round(k), atol=2e-3)
    assert np.unique(np.round(k)).size > 5  # a tilted plane crosses many levels
    # the distance is the norm of XYZ, XYZ lies on the pixel's pinhole ray
    np.testing.assert_allclose(np.linalg.norm(frame.xyz[frame.valid], axis=1), frame.distance[frame.valid], rtol=1e-6)
    v, u = np.nonzero(frame.valid)
    intr = frame.intrinsics
    np.testing.assert_allclose(frame.xyz[v, u, 0] / frame.xyz[v, u, 2], (u - intr.cx) / intr.fx, atol=1e-6)
    assert not intr.has_distortion


def test_depth_noise_grows_with_the_square_of_depth() -> None:
    sigma_d = 0.25
    measured = {}
    for z0 in (0.5, 1.0, 2.0):
        pose = looking_down(z0)
        cam = camera(pose, subpixel_bits=5, disparity_sigma_px=sigma_d, speckle_fraction=0.0)
        z = z_of(cam.render(pose).xyz)
        measured[z0] = float(np.nanstd(z))  # one true Z over the whole fronto-parallel frame
        fb = cam.config.fb_px_m
        # Z²/(f·B) · sqrt(sigma_d² + q²/12) to first order (q = 1/32 px)
        expected = z0**2 / fb * np.sqrt(sigma_d**2 + (2.0**-5) ** 2 / 12.0)
        assert measured[z0] == pytest.approx(expected, rel=0.05)
    # four times the depth, sixteen times the noise
    assert measured[2.0] / measured[0.5] == pytest.approx(16.0, rel=0.08)


def test_subpixel_off_leaves_eight_times_fewer_depth_levels() -> None:
    pose = looking_down(0.6, 30.0)
    levels = {}
    rms = {}
    for bits in (0, 3):
        cam = camera(pose, subpixel_bits=bits, **QUIET)
        frame = cam.render(pose)
        truth = camera(pose, subpixel_bits=8, **QUIET).render(pose)
        both = frame.valid & truth.valid
        z = z_of(frame.xyz)[both]
        levels[bits] = np.unique(np.round(cam.config.fb_px_m / z, 6)).size
        rms[bits] = float(np.sqrt(np.mean((z - z_of(truth.xyz)[both]) ** 2)))
    assert levels[3] / levels[0] == pytest.approx(8.0, rel=0.1)
    # rounding error of the depth: the step Z²/(f·B)·2^-bits over sqrt(12), eight times smaller with 3 bits
    assert rms[0] / rms[3] == pytest.approx(8.0, rel=0.15)
    fb = SimStereoConfig(**SMALL).fb_px_m
    z_mid = 0.6 / np.cos(np.radians(30.0))
    assert rms[0] == pytest.approx(z_mid**2 / fb / np.sqrt(12.0), rel=0.35)


@pytest.mark.parametrize("aligned", ["right", "left"])
def test_left_right_holes_lie_beside_the_box_on_the_side_the_other_camera_cannot_see(aligned: str) -> None:
    pose = looking_down(0.8)
    box = Box((0.0, 0.0), (0.12, 0.12, 0.15))
    cam = camera(pose, Scene(boxes=(box,)), depth_aligned_to=aligned, **QUIET)
    frame = cam.render(pose)
    fb, cx = cam.config.fb_px_m, cam.config.intrinsics().cx
    f = cam.config.focal_px
    row = 100  # through the box's middle
    holes = np.nonzero(~frame.valid[row])[0]
    # the box top (Z 0.65 m) spans |x| <= 0.06 m; its edges in this row
    left_edge, right_edge = cx - f * 0.06 / 0.65, cx + f * 0.06 / 0.65
    width = fb / 0.65 - fb / 0.8  # disparity step, px: the hidden band's width
    assert width == pytest.approx(4.76, abs=0.01)
    assert holes.size == pytest.approx(width, abs=1.5)
    if aligned == "right":  # the other camera at -x: the band right of the box
        assert holes.min() >= right_edge - 1 and holes.max() <= right_edge + width + 1
    else:
        assert holes.max() <= left_edge + 1 and holes.min() >= left_edge - width - 1
    # every hole of the frame is in such a band beside the box, none on the open table
    per_row = (~frame.valid).sum(axis=1)
    rows = np.nonzero(per_row)[0]
    assert rows.size == pytest.approx(f * 0.12 / 0.65, abs=1.5)  # the box's rows
    assert set(per_row[rows].tolist()) <= {int(np.floor(width)), int(np.ceil(width))}
    # without the check the hidden band reads the box top's depth
    fat = camera(pose, Scene(boxes=(box,)), depth_aligned_to=aligned, lr_check=False, **QUIET).render(pose)
    assert fat.valid[row].all()
    np.testing.assert_allclose(z_of(fat.xyz)[row, holes], 0.65, atol=0.002)


def test_occlusion_rule_on_hand_made_rows() -> None:
    # a 10 px disparity step: the far pixels within 10 px on the far side are hidden, nothing else
    d = np.full((1, 40), 20.0)
    d[0, 15:25] = 30.0
    hidden = occluded_in_other_camera(d, other_on_right=True)
    assert np.nonzero(hidden[0])[0].tolist() == list(range(5, 15))
    hidden = occluded_in_other_camera(d, other_on_right=False)
    assert np.nonzero(hidden[0])[0].tolist() == list(range(25, 35))
    # a plane whose disparity changes by less than 1 px per px hides nothing
    ramp = np.linspace(10.0, 45.0, 40)[None, :]
    assert not occluded_in_other_camera(ramp, True).any() and not occluded_in_other_camera(ramp, False).any()


def test_speckle_covers_its_fraction_in_small_blobs_of_wrong_disparity() -> None:
    pose = looking_down(0.7)
    frac = 0.01
    cam = camera(pose, noise=False, speckle_fraction=frac, speckle_disparity_px=20.0)
    fb = cam.config.fb_px_m
    wrong = []
    for _ in range(4):
        frame = cam.render(pose)
        d = np.where(frame.valid, fb / z_of(frame.xyz), np.nan)
        err = np.abs(d - fb / 0.7)
        bad = frame.valid & (err > 0.5)
        wrong.append(bad.sum() + (~frame.valid).sum())  # a blob below the far limit is a hole
        assert np.nanmax(err) <= 20.0 + 0.1
    # blobs overlap a little: a bit under the fraction
    assert np.mean(wrong) / frame.valid.size == pytest.approx(frac, rel=0.2)
    import cv2

    n, _, stats, _ = cv2.connectedComponentsWithStats(bad.astype(np.uint8), connectivity=8)
    assert n > 50 and np.median(stats[1:, 4]) <= 9  # isolated small blobs


def test_near_and_far_limits_are_holes() -> None:
    near = looking_down(0.30)  # f·B / 0.30 = 55 px (320 px wide: f = 220 px)
    cam = camera(near, max_disparity_px=50.0, **QUIET)
    assert not cam.render(near).valid.any()
    assert camera(near, max_disparity_px=60.0, **QUIET).render(near).valid.all()
    far = looking_down(3.0)
    assert not camera(far, max_range_m=2.5, **QUIET).render(far).valid.any()
    assert not camera(far, min_disparity_px=6.0, **QUIET).render(far).valid.any()  # 16.5 / 3 = 5.5 px


def test_the_stated_model_matches_the_config_and_the_frames() -> None:
    section = {"backend": "sim", "kind": "stereo", "width": 320, "height": 200, "baseline_m": 0.05,
               "subpixel_bits": 2, "disparity_sigma_px": 0.15, "speckle_fraction": 0.0}
    world = SimWorld(Scene(), Pose.identity(), flange_pose=looking_down(0.7), seed=3)
    context = BackendContext(section="camera", shared={"sim.world": world})
    cam = SimCamera.from_config(section, context)
    assert isinstance(cam, SimStereoCamera)
    model = cam.measurement_model
    f = 160.0 / np.tan(np.radians(36.0))
    assert (model.kind, model.source, model.subpixel_bits) == ("stereo", "sim", 2)
    assert model.baseline_m == 0.05 and model.disparity_sigma_px == 0.15
    assert model.focal_px == pytest.approx(f)
    with cam:
        frame = cam.capture()
        assert frame.intrinsics.fx == pytest.approx(f)
    assert frame.measurement == model
    # the model's depth step is the spacing of the frame's depth levels at 0.7 m
    z = np.unique(z_of(frame.xyz)[frame.valid])
    step = float(model.depth_step_m(0.7))
    spacing = np.diff(z)[np.abs(z[:-1] - 0.7) < 0.015]
    assert spacing.size >= 1
    np.testing.assert_allclose(spacing, step, rtol=0.06)
    # noise off: a noise-free disparity, still rounded
    quiet = SimStereoCamera(SimStereoConfig(noise=False), world=world)
    assert quiet.measurement_model.disparity_sigma_px == 0.0
    assert quiet.render(looking_down(0.7)).measurement.subpixel_bits == 3


@pytest.mark.parametrize(("section", "key"), [
    ({"kind": "laser"}, "camera.kind"),
    ({"kind": "stereo", "baseline_m": 0.0}, "camera.baseline_m"),
    ({"kind": "stereo", "subpixel_bits": -1}, "camera.subpixel_bits"),
    ({"kind": "stereo", "min_disparity_px": 5.0, "max_disparity_px": 4.0}, "camera.max_disparity_px"),
    ({"kind": "stereo", "quantisation_m": 0.001}, "camera.quantisation_m"),  # a ToF key
    ({"kind": "stereo", "depth_aligned_to": "centre"}, "camera.depth_aligned_to"),
])
def test_bad_stereo_config_is_one_line_naming_the_key(section: dict[str, object], key: str) -> None:
    with pytest.raises(ConfigError) as err:
        SimCamera.from_config(section, BackendContext(section="camera", source="cell.toml"))
    assert f"key '{key}'" in str(err.value) and "\n" not in str(err.value)


def test_same_seed_same_frames_and_a_resumed_camera_continues() -> None:
    pose = looking_down(0.7, 20.0)
    scene = Scene(boxes=(Box((0.05, 0.0), (0.1, 0.1, 0.08)),))
    a, b, c = (camera(pose, scene, seed=s) for s in (4, 4, 5))
    fa, fb_, fc = a.render(pose), b.render(pose), c.render(pose)
    np.testing.assert_array_equal(fa.distance, fb_.distance)
    assert not np.array_equal(np.nan_to_num(fa.distance), np.nan_to_num(fc.distance))
    with a:
        a.capture()
        state = a.resume_state()
        want = a.capture()
    fresh = camera(pose, scene, seed=99)
    fresh.restore_resume_state(state)
    with fresh:
        got = fresh.capture()
    np.testing.assert_array_equal(got.distance, want.distance)
    assert got.sequence == want.sequence == 2


def test_sim_oak_cell_builds_the_stereo_camera_and_sees_the_table_at_the_first_pose() -> None:
    from importlib import resources

    from cellcal.core.calibration.calibrator import build_devices
    from cellcal.core.calibration.config import load_config

    path = resources.files("cellcal.configs").joinpath("sim_oak.toml")
    with resources.as_file(path) as file:
        config = load_config(file)
    camera, _arm = build_devices(config)
    assert isinstance(camera, SimStereoCamera)
    model = camera.measurement_model
    assert (model.kind, model.baseline_m, model.subpixel_bits) == ("stereo", 0.075, 3)
    assert model.focal_px == pytest.approx(320.0 / np.tan(np.radians(36.0)))
    # the paper's nearest pose: 0.46 m along the axis at 80 deg to the table
    pose = Pose(Rotation.from_euler("x", 180.0 + 10.0, degrees=True), np.zeros(3))
    pose = Pose(pose.rotation, -0.46 * pose.rotation.apply([0.0, 0.0, 1.0]))
    frame = camera.render(pose)
    assert frame.shape == (400, 640) and frame.valid.mean() > 0.98
    assert frame.measurement == model
    # the step between depth levels at 0.46 m: 0.8 mm (Z²/(f·B)/8)
    assert float(model.depth_step_m(0.46)) == pytest.approx(0.46**2 / (model.fb_px_m * 8.0))
