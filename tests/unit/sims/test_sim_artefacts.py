"""The simulated ToF camera's artefacts: mixed pixels, multipath, amplitude noise, drift, [sim.artefacts]."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy.ndimage import binary_dilation
from scipy.spatial.transform import Rotation

from cellcal.devices.base import BackendContext
from cellcal.devices.errors import ConfigError
from cellcal.devices.pose import Pose
from cellcal.devices.registry import default_registry
from cellcal.devices.types import Frame
from cellcal.sims.camera import CONF_INVALID, CONF_LOW_AMPLITUDE, CONF_SATURATED, SimCamera, SimCameraConfig
from cellcal.sims.scene import Box, Scene
from cellcal.sims.systematic import SystematicConfig
from cellcal.sims.tof import ArtefactsConfig, amplitude_sigma_m, drift_offset_m, relative_amplitude
from cellcal.sims.world import SimWorld, world_from_context

DOWN = Rotation.from_euler("x", 180.0, degrees=True)  # camera z along world -z
OFF = ArtefactsConfig.off()
IDEAL = SystematicConfig.off()  # the artefacts alone, no systematic depth error (ADR 0054)
EXACT = {"noise": False, "quantisation_m": 0.0}


def only(**on: object) -> ArtefactsConfig:
    """Every artefact off except the ones named (with their settings)."""
    return dataclasses.replace(OFF, **on)  # type: ignore[arg-type]


def pose_at(height_m: float, tilt_deg: float = 0.0, x_m: float = 0.0) -> Pose:
    return Pose(DOWN * Rotation.from_euler("x", tilt_deg, degrees=True), np.array([x_m, 0.0, height_m]))


def render(pose: Pose, scene: Scene, artefacts: ArtefactsConfig, seed: int = 7, **cfg: object) -> Frame:
    world = SimWorld(scene, Pose.identity(), flange_pose=pose, seed=seed, artefacts=artefacts, systematic=IDEAL)
    return SimCamera(SimCameraConfig(**cfg), world=world).render(pose)  # type: ignore[arg-type]


def world_z(frame: Frame, pose: Pose) -> np.ndarray:
    """Height above the plane z = 0 of each pixel's point, (H, W) (NaN where invalid)."""
    return pose.apply(frame.xyz.reshape(-1, 3).astype(np.float64))[:, 2].reshape(frame.shape)


def test_artefacts_table_is_read_from_sim_and_checked() -> None:
    doc = {"sim": {"plane_reflectivity": 0.3, "artefacts": {"multipath": False, "drift_m": 0.002},
                   "boxes": [{"center_xy_m": [0.3, 0.0], "size_m": [0.1, 0.1, 0.1], "reflectivity": 0.9}]}}
    world = world_from_context(BackendContext(source="cell.toml", document=doc))
    assert world.artefacts == ArtefactsConfig(multipath=False, drift_m=0.002)
    assert world.artefacts.mixed_pixels and world.artefacts.amplitude_noise  # the others stay on
    assert world.scene.plane_reflectivity == 0.3 and world.scene.boxes[0].reflectivity == 0.9
    assert world_from_context(BackendContext(document={})).artefacts == ArtefactsConfig()  # on by default
    with pytest.raises(ConfigError, match=r"cell\.toml.*sim\.artefacts\.multipth"):
        world_from_context(BackendContext(source="cell.toml", document={"sim": {"artefacts": {"multipth": False}}}))
    with pytest.raises(ConfigError, match=r"sim\.artefacts\.saturation_amplitude.*exceed min_amplitude"):
        ArtefactsConfig(min_amplitude=2.0, saturation_amplitude=1.0)


def test_a_lone_plane_shows_no_mixed_pixels_or_multipath() -> None:
    pose = pose_at(0.6, 20.0)
    plain = render(pose, Scene(), OFF, **EXACT)
    realistic = render(pose, Scene(), ArtefactsConfig(amplitude_noise=False), **EXACT)
    np.testing.assert_allclose(realistic.distance, plain.distance, atol=1e-7)  # a warm camera: drift < 0.1 um


def test_mixed_pixels_lie_between_the_box_and_the_table() -> None:
    pose = pose_at(0.5)
    scene = Scene(boxes=(Box((0.0, 0.0), (0.12, 0.1, 0.06)),))  # top at z = 0.06, 0.44 m from the camera
    plain = render(pose, scene, OFF, **EXACT)
    mixed = render(pose, scene, only(mixed_pixels=True), **EXACT)
    z0, z = world_z(plain, pose), world_z(mixed, pose)
    assert set(np.round(z0[plain.valid], 4)) <= {0.0, 0.06}  # without: every pixel on the table or the top
    flying = mixed.valid & (np.abs(z) > 1e-5) & (np.abs(z - 0.06) > 1e-5)  # (float32 points: 1e-5 m)
    # Straight down, the sides are not seen: the flying pixels lie between top and table, at the outline.
    assert np.all((z[flying] > 0.0) & (z[flying] < 0.06))
    top = np.abs(z0 - 0.06) < 1e-5
    outline = np.zeros_like(top)
    for shift, axis in ((1, 0), (-1, 0), (1, 1), (-1, 1)):
        outline |= top ^ np.roll(top, shift, axis)
    # Strongly mixed (over 10 % of the step from both surfaces): on the outline, about one per
    # outline pixel pair; weakly mixed ones (the lens blur's tail, up to 2 px out) are more.
    strong = flying & (z > 0.006) & (z < 0.054)
    weak = flying & ~strong
    assert np.all(outline[strong])
    assert 0.6 < strong.sum() / (outline.sum() / 2) < 1.5
    assert weak.sum() > strong.sum()
    assert np.mean(binary_dilation(outline, np.ones((3, 3)))[flying]) > 0.99
    far = ~binary_dilation(outline, np.ones((5, 5)))  # beyond the footprint's reach: unchanged
    np.testing.assert_allclose(mixed.distance[far], plain.distance[far], atol=1e-7, rtol=0)


def test_mixed_pixels_lean_toward_the_brighter_surface() -> None:
    pose = pose_at(0.5)
    means = []
    for rho in (0.25, 2.0):
        scene = Scene(boxes=(Box((0.0, 0.0), (0.12, 0.1, 0.06), reflectivity=rho),))
        f = render(pose, scene, only(mixed_pixels=True), **EXACT)
        z = world_z(f, pose)
        flying = f.valid & (z > 1e-5) & (z < 0.06 - 1e-5)
        means.append(float(np.mean(z[flying])))
    # Phasor blend weighted by amplitude: a white top pulls its edge pixels up, a dark one lets the table win.
    assert means[1] > means[0] + 0.01


def _corner_scene(reflectivity: float = 0.5) -> Scene:
    return Scene(boxes=(Box((0.0, 0.0), (0.2, 0.3, 0.15), reflectivity=reflectivity),))


def _multipath_bias(reflectivity: float = 0.5, **on: object) -> tuple[np.ndarray, Frame, Pose]:
    # Looking 35 deg off vertical from x = -0.45 m: the box's -x side faces the camera, lit.
    pose = Pose(DOWN * Rotation.from_euler("y", 35.0, degrees=True), np.array([-0.45, 0.0, 0.55]))
    scene = _corner_scene(reflectivity)
    plain = render(pose, scene, OFF, **EXACT)
    mp = render(pose, scene, only(multipath=True, **on), **EXACT)
    return (mp.distance - plain.distance).astype(np.float64), plain, pose


def test_multipath_reads_long_near_the_foot_of_a_box_and_fades() -> None:
    bias, frame, pose = _multipath_bias()
    pts = pose.apply(frame.xyz.reshape(-1, 3).astype(np.float64)).reshape(*frame.shape, 3)
    table = frame.valid & (np.abs(pts[..., 2]) < 1e-5)
    top = frame.valid & (np.abs(pts[..., 2] - 0.15) < 1e-5)
    side = frame.valid & ~table & ~top
    assert side.sum() > 200  # the lit -x face is in view
    assert np.all(bias[frame.valid] >= -1e-7)  # a bias, never shorter
    assert np.all(np.abs(bias[top]) < 1e-7)  # the top sees nothing above it

    def table_bias(gap_lo: float, gap_hi: float) -> float:
        gap = -0.1 - pts[..., 0]  # distance in front of the -x face (x = -0.1), on the table
        return float(np.mean(bias[table & (gap > gap_lo) & (gap < gap_hi) & (np.abs(pts[..., 1]) < 0.1)]))

    # In the concave corner the table reads long: little at the foot (no extra path), most a box
    # height away (3.7 mm here), fading beyond as the face subtends less; the face itself reads longer.
    peak = table_bias(0.05, 0.12)
    assert 2e-3 < peak < 6e-3
    assert table_bias(0.0, 0.01) < 0.3 * peak
    assert table_bias(0.3, 0.35) < 0.5 * peak
    assert np.mean(bias[table & (pts[..., 1] > 0.2)]) < 0.1 * peak  # beside the box, out of the face's sight
    assert np.median(bias[side]) > 3 * peak
    # Stronger reflector, stronger multipath (about in proportion while the phase stays small).
    white, _, _ = _multipath_bias(1.0)
    near = table & (np.abs(pts[..., 1]) < 0.1) & (pts[..., 0] < -0.15) & (pts[..., 0] > -0.22)
    assert 1.6 < np.mean(white[near]) / np.mean(bias[near]) < 2.1
    off = render(pose, _corner_scene(), OFF, **EXACT)
    np.testing.assert_array_equal(off.distance, frame.distance)


def test_multipath_patch_grid_agrees_with_every_pixel_a_patch() -> None:
    pose = Pose(DOWN * Rotation.from_euler("y", 35.0, degrees=True), np.array([-0.45, 0.0, 0.55]))
    small = {**EXACT, "width": 64, "height": 48}
    plain = render(pose, _corner_scene(), OFF, **small)
    coarse = render(pose, _corner_scene(), only(multipath=True, multipath_patches=16), **small)
    exact = render(pose, _corner_scene(), only(multipath=True, multipath_patches=64), **small)
    b_c = (coarse.distance - plain.distance).astype(np.float64)
    b_e = (exact.distance - plain.distance).astype(np.float64)
    z = world_z(plain, pose)
    table = plain.valid & (np.abs(z) < 1e-5)
    side = plain.valid & ~table & (np.abs(z - 0.15) > 1e-5)
    # 4 x 4-pixel patches against every pixel a patch (measured: table rms 0.17 mm of a 1.1 mm
    # mean, the face's mean within 7 % of 15.6 mm); the finer the image, the closer (224 px: 0.02 mm).
    d = b_c[table] - b_e[table]
    assert np.mean(b_e[table]) > 0.5e-3
    assert np.sqrt(np.mean(d**2)) < 0.25 * np.mean(b_e[table])
    assert abs(np.mean(d)) < 0.05 * np.mean(b_e[table])
    assert abs(np.mean(b_c[side]) - np.mean(b_e[side])) < 0.1 * np.mean(b_e[side])


@pytest.mark.parametrize("reflectivity", [0.1, 1.0])
def test_amplitude_noise_grows_as_the_return_weakens(reflectivity: float) -> None:
    pose = pose_at(1.0)
    window = (slice(80, 92), slice(106, 118))  # near the axis: cos(incidence) > 0.999
    world = SimWorld(Scene(plane_reflectivity=reflectivity), Pose.identity(), flange_pose=pose, seed=3)
    cam = SimCamera(SimCameraConfig(quantisation_m=0.0), world=world)
    stack = np.array([cam.render(pose).distance[window] for _ in range(40)], dtype=np.float64)
    measured = float(np.sqrt(np.mean(stack.std(axis=0, ddof=1) ** 2)))
    a = float(relative_amplitude(1.0, 1.0, reflectivity))
    assert a == pytest.approx(reflectivity / 0.5)
    assert measured == pytest.approx(float(amplitude_sigma_m(a)), rel=0.06)
    # a tenth of the amplitude: the amplitude term alone grows 10 sqrt(1.1 / 2.9) = 6.2 x (between shot-noise
    # sqrt(10) and floor-limited 10), but the default per-pixel 2.7 mm (measured on the real O3R) does not grow:
    # sqrt(2.7**2 + 8.52**2) / sqrt(2.7**2 + 1.38**2) mm = 2.95 x (4.47 x with the earlier F = 0, n = 0.25)
    shot = 2.24e-3 * math.sqrt(1.1 / 1.9) / 0.2, 2.24e-3 * math.sqrt(2.9 / 1.9) / 2.0
    ratio = math.hypot(0.0027, shot[0]) / math.hypot(0.0027, shot[1])
    assert float(amplitude_sigma_m(0.2) / amplitude_sigma_m(2.0)) == pytest.approx(ratio, rel=1e-9)
    assert ratio == pytest.approx(2.95, abs=0.005)


def test_low_amplitude_and_saturated_pixels_are_invalid() -> None:
    far = pose_at(3.5)
    dark = Scene(plane_reflectivity=0.05)  # amplitude 0.1 / 3.5^2 = 0.008 < 0.05
    frame = render(far, dark, ArtefactsConfig(), max_range_m=10.0, **EXACT)
    assert not frame.valid.any()
    assert frame.confidence is not None
    assert np.all(frame.confidence & (CONF_LOW_AMPLITUDE | CONF_INVALID) == CONF_LOW_AMPLITUDE | CONF_INVALID)
    assert render(far, dark, OFF, max_range_m=10.0, **EXACT).valid.all()  # the data-sheet camera has no limit
    # A retro-reflective box 0.3 m under the camera saturates (amplitude 200 / 0.09 > 100); the table does not.
    near = pose_at(0.5)
    retro = Scene(boxes=(Box((0.0, 0.0), (0.1, 0.1, 0.2), reflectivity=100.0),))
    sat = render(near, retro, ArtefactsConfig(), **EXACT)
    assert sat.confidence is not None
    centre = sat.confidence[80:92, 106:118]
    assert np.all(centre & (CONF_SATURATED | CONF_INVALID) == CONF_SATURATED | CONF_INVALID)
    assert sat.valid[5, 5] and not sat.valid[85, 111]
    assert sat.amplitude[85, 111] == pytest.approx(100.0 * 1000.0)  # clipped at the saturation level


def test_temperature_drift_follows_the_simulated_clock() -> None:
    cold = ArtefactsConfig(warm_up_s=0.0, amplitude_noise=False)
    pose = pose_at(0.6)
    world = SimWorld(Scene(), Pose.identity(), flange_pose=pose, seed=1, artefacts=cold, systematic=IDEAL)
    cam = SimCamera(SimCameraConfig(**EXACT), world=world)  # type: ignore[arg-type]
    truth = render(pose, Scene(), OFF, **EXACT).distance.astype(np.float64)
    offsets = []
    for t in (0.0, 300.0, 1800.0):
        world.clock.advance_to(t)
        offsets.append(float(np.mean(cam.render(pose).distance - truth)))
    np.testing.assert_allclose(offsets, [0.004, 0.004 / math.e, 0.004 * math.exp(-6.0)], atol=2e-7)
    assert drift_offset_m(ArtefactsConfig(), 0.0) < 1e-7  # default: the camera has warmed up for an hour
    assert drift_offset_m(dataclasses.replace(cold, temperature_drift=False), 0.0) == 0.0


def test_cluttered_frames_repeat_with_the_seed_and_resume_where_they_left_off() -> None:
    pose = pose_at(0.55, 12.0, 0.1)
    scene = Scene(boxes=(Box((0.05, 0.02), (0.12, 0.1, 0.07), 0.4),
                         Box((0.2, -0.1), (0.08, 0.1, 0.05), reflectivity=0.9)))
    cold = ArtefactsConfig(warm_up_s=0.0)

    def camera() -> SimCamera:
        world = SimWorld(scene, Pose.identity(), flange_pose=pose, seed=5, artefacts=cold)
        return SimCamera(SimCameraConfig(frame_rate_hz=0.01), world=world)  # 100 s per frame: the drift moves

    a, b = camera(), camera()
    with a, b:
        fa = [a.capture(1.0) for _ in range(3)]
        state = a.resume_state()
        later = a.capture(1.0)
        fb = [b.capture(1.0) for _ in range(3)]
        resumed = camera()
        resumed.restore_resume_state(state)
        with resumed:
            again = resumed.capture(1.0)
    for x, y in zip(fa, fb, strict=True):
        np.testing.assert_array_equal(x.distance, y.distance)
    assert not np.array_equal(fa[0].distance, fa[1].distance, equal_nan=True)
    np.testing.assert_array_equal(again.distance, later.distance)
    assert resumed.world.clock.elapsed_s == a.world.clock.elapsed_s == pytest.approx(300.0)


def test_the_o3r_emulator_serves_the_same_artefacts() -> None:
    doc = {"cell": {"seed": 9}, "mount": {"translation_m": [0.0, 0.0, 0.0], "rpy_deg": [0.0, 0.0, 0.0]},
           "sim": {"boxes": [{"center_xy_m": [0.3, 0.05], "size_m": [0.15, 0.12, 0.08], "yaw_deg": 20.0}],
                   "initial_flange_translation_m": [0.2, 0.0, 0.5], "initial_flange_rpy_deg": [180.0, -15.0, 0.0]}}
    frames = {}
    for backend in ("sim", "o3r-emulated"):
        section = {"backend": backend}
        cam = default_registry().create_camera(section, BackendContext(section="camera", document=doc, seed=9))
        with cam.connect(5.0):
            frames[backend] = cam.capture(5.0)
    sim, emu = frames["sim"], frames["o3r-emulated"]
    np.testing.assert_array_equal(emu.valid, sim.valid)
    diff = np.abs(emu.distance[sim.valid].astype(np.float64) - sim.distance[sim.valid])
    assert diff.max() <= (10 / 65535) / 2 + 1e-6  # the wire's distance resolution (a VPU's 10/65535 m, the default)
    # the frame has flying pixels: valid points between the box top (z = 0.08) and the table
    world = Pose.from_xyz_rpy(np.array([0.2, 0.0, 0.5]), np.radians([180.0, -15.0, 0.0]))
    z = world.apply(emu.xyz[emu.valid].astype(np.float64))[:, 2]
    assert np.count_nonzero((z > 0.015) & (z < 0.065)) > 20


def test_commented_artefacts_table_in_sim_toml_shows_the_real_defaults() -> None:
    import tomllib
    from importlib import resources

    text = resources.files("cellcal.configs").joinpath("sim.toml").read_text(encoding="utf-8")
    block = text[text.index("# [sim.artefacts]"):].split("\n#\n")[0]  # up to the next commented table
    shown = tomllib.loads("\n".join(line[2:] for line in block.splitlines() if line.startswith("# ") and " = " in line))
    assert len(shown) >= 10
    defaults = ArtefactsConfig()
    for key, value in shown.items():
        assert getattr(defaults, key) == value, key
