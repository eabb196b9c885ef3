"""``[sim.systematic]``: the sims' systematic depth errors (ADR 0054), drawn before noise, stated as an allowance."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cellcal.devices.base import BackendContext
from cellcal.devices.errors import ConfigError
from cellcal.devices.measurement import DEFAULT_ALLOWANCES
from cellcal.devices.pose import Pose
from cellcal.devices.systematic import SystematicError, normalised_pixels
from cellcal.devices.types import Frame
from cellcal.sims.camera import SimCamera, SimCameraConfig
from cellcal.sims.scene import Scene
from cellcal.sims.stereo import SimStereoCamera, SimStereoConfig
from cellcal.sims.systematic import WIGGLE_PERIOD_60MHZ_M, SystematicConfig, radial_bow_coeffs
from cellcal.sims.tof import SPEED_OF_LIGHT_M_S, ArtefactsConfig
from cellcal.sims.world import SimWorld, world_from_context

DOWN = Rotation.from_euler("x", 180.0, degrees=True)  # camera z along world -z
#: Every term zero: what each test switches on one at a time.
NONE = SystematicConfig(fb_error=0.0, disparity_offset_px=0.0, disparity_bow_px=0.0, range_offset_m=0.0,
                        range_scale_error=0.0, wiggle_amplitude_m=0.0, range_bow_m=0.0)
SMALL_STEREO = {"width": 320, "height": 200, "speckle_fraction": 0.0}
EXACT_TOF = {"noise": False, "quantisation_m": 0.0, "distortion": False}


def looking_down(height_m: float, tilt_deg: float = 0.0) -> Pose:
    return Pose(DOWN * Rotation.from_euler("x", tilt_deg, degrees=True), np.array([0.0, 0.0, height_m]))


def stereo(systematic: SystematicConfig, pose: Pose, seed: int = 4, **cfg: object) -> SimStereoCamera:
    world = SimWorld(Scene(), Pose.identity(), flange_pose=pose, seed=seed, systematic=systematic)
    return SimStereoCamera(SimStereoConfig(**{**SMALL_STEREO, **cfg}), world=world)  # type: ignore[arg-type]


def tof(systematic: SystematicConfig, pose: Pose, seed: int = 4, **cfg: object) -> SimCamera:
    world = SimWorld(Scene(), Pose.identity(), flange_pose=pose, seed=seed, artefacts=ArtefactsConfig.off(),
                     systematic=systematic)
    return SimCamera(SimCameraConfig(**cfg), world=world)  # type: ignore[arg-type]


def disparity(cam: SimStereoCamera, frame: Frame) -> np.ndarray:
    """The frame's disparity ``f·B / Z``, px (NaN where invalid)."""
    return cam.config.fb_px_m / frame.xyz[..., 2].astype(np.float64)


def test_a_radial_bow_is_exactly_two_monomials_scaled_by_the_aspect() -> None:
    width, height, cx, cy = 640, 400, 331.7, 190.2
    err = SystematicError("stereo", field_order=2, field_coeffs=radial_bow_coeffs(0.5, width, height))
    u, v = normalised_pixels(width, height, cx, cy)
    cols, rows = np.meshgrid(np.arange(width) - cx, np.arange(height) - cy)
    # bow * r^2 / r_corner^2, r in pixels from the principal point, r_corner half the diagonal
    expected = 0.5 * (cols**2 + rows**2) / ((width / 2) ** 2 + (height / 2) ** 2)
    np.testing.assert_allclose(err.field_at(u, v), expected, rtol=0, atol=1e-12)
    assert err.field_at(np.array([1.0, -1.0, 0.0]), np.array([1.0, 1.0, 0.0])) == pytest.approx([0.5, 0.5, 0.0])


def test_the_stereo_bow_reads_at_the_corners_and_not_at_the_centre() -> None:
    h_m = 0.7
    pose = looking_down(h_m)
    cam = stereo(dataclasses.replace(NONE, disparity_bow_px=0.5), pose)
    d_true = cam.config.fb_px_m / h_m  # 23.6 px at 320 px wide
    residual = np.mean([disparity(cam, cam.render(pose)) - d_true for _ in range(8)], axis=0)
    # the bow each corner patch should read (its pixels lie a little inside the corner)
    intr = cam.config.intrinsics()
    u, v = normalised_pixels(intr.width, intr.height, intr.cx, intr.cy)
    bow = cam.systematic_error()[0].field_at(u, v)
    k = 6
    for rows, cols in ((slice(0, k), slice(0, k)), (slice(0, k), slice(-k, None)),
                       (slice(-k, None), slice(0, k)), (slice(-k, None), slice(-k, None))):
        # 8 frames x 36 px of 0.25 px noise and 1/8 px rounding: 0.005 px; the patch's bow 0.47-0.50 px
        assert float(np.mean(residual[rows, cols])) == pytest.approx(float(np.mean(bow[rows, cols])), abs=0.05)
        assert float(np.mean(bow[rows, cols])) == pytest.approx(0.5, abs=0.035)
    centre = residual[100 - k // 2:100 + k // 2, 160 - k // 2:160 + k // 2]
    assert float(np.mean(centre)) == pytest.approx(0.0, abs=0.05)


def test_fb_error_scales_the_mean_disparity() -> None:
    pose = looking_down(0.6)
    cam = stereo(dataclasses.replace(NONE, fb_error=0.01), pose)
    ideal = stereo(SystematicConfig.off(), pose)
    d_true = cam.config.fb_px_m / 0.6
    ratio = float(np.nanmean(disparity(cam, cam.render(pose)))) / d_true
    ratio_ideal = float(np.nanmean(disparity(ideal, ideal.render(pose)))) / d_true
    # 64,000 pixels of 0.25 px noise on 27.5 px: the mean's ratio to +-3e-5; rounding's bias below 1e-4
    assert ratio == pytest.approx(1.01, abs=2e-4)
    assert ratio_ideal == pytest.approx(1.0, abs=2e-4)


def test_a_tof_offset_shifts_the_mean_range() -> None:
    pose = looking_down(0.55, 12.0)
    shifted = tof(dataclasses.replace(NONE, range_offset_m=0.003), pose).render(pose)
    ideal = tof(SystematicConfig.off(), pose).render(pose)  # the same seed: the same noise
    diff = (shifted.distance - ideal.distance)[shifted.valid & ideal.valid].astype(np.float64)
    # the 1 mm quantisation dithered by ~3 mm noise: the mean of 38,000 px to 0.01 mm
    assert float(np.mean(diff)) == pytest.approx(0.003, abs=5e-5)


def test_the_tof_wiggle_follows_the_range() -> None:
    amp, period = 0.002, WIGGLE_PERIOD_60MHZ_M
    wiggly = dataclasses.replace(NONE, wiggle_amplitude_m=amp, wiggle_phase_deg=30.0)
    seen = []
    for height in (0.4, 0.4 + period / 4, 0.4 + period / 2, 0.4 + 3 * period / 4):
        pose = looking_down(height, 25.0)
        on = tof(wiggly, pose, **EXACT_TOF).render(pose)
        off = tof(SystematicConfig.off(), pose, **EXACT_TOF).render(pose)
        r = off.distance.astype(np.float64)
        diff = on.distance.astype(np.float64) - r
        expected = amp * np.cos(2 * np.pi * r / period - np.radians(30.0))
        ok = on.valid & off.valid
        np.testing.assert_allclose(diff[ok], expected[ok], atol=2e-6)  # float32 distances
        seen.append(diff[ok])
    every = np.concatenate(seen)
    assert every.max() > 0.95 * amp and every.min() < -0.95 * amp  # the whole wiggle over the ranges seen


def test_off_renders_exactly_what_a_camera_without_systematic_error_does() -> None:
    pose = looking_down(0.5, 10.0)
    for make in (stereo, tof):
        off = make(SystematicConfig.off(), pose).render(pose)  # type: ignore[operator]
        zero = make(NONE, pose).render(pose)  # type: ignore[operator]
        for name in ("distance", "xyz", "valid", "amplitude", "confidence"):
            assert np.array_equal(getattr(off, name), getattr(zero, name), equal_nan=name != "valid"), name
        assert "sim_systematic" not in off.metadata
        assert SystematicError.from_dict(zero.metadata["sim_systematic"]).is_zero


def test_the_defaults_lie_within_the_stated_allowance_and_the_frames_carry_the_truth() -> None:
    pose = looking_down(0.6)
    default = SystematicConfig()
    assert default.enabled
    s_scale, s_offset, s_field = DEFAULT_ALLOWANCES["stereo"]
    assert abs(default.fb_error) <= s_scale and abs(default.disparity_offset_px) <= s_offset
    assert abs(default.disparity_bow_px) <= s_field
    t_scale, t_offset, t_field = DEFAULT_ALLOWANCES["tof"]
    assert abs(default.range_scale_error) <= t_scale and abs(default.range_offset_m) <= t_offset
    assert abs(default.range_bow_m) <= t_field and default.wiggle_amplitude_m <= t_offset
    modulation_hz = ArtefactsConfig().modulation_frequency_hz
    assert default.wiggle_period_m == pytest.approx(SPEED_OF_LIGHT_M_S / (8 * modulation_hz))  # 0.6246 m
    for make, kind in ((stereo, "stereo"), (tof, "tof")):
        cam = make(default, pose)  # type: ignore[operator]
        frame = cam.render(pose)
        model = frame.measurement
        # a sim states what a vendor would (the kind's default), not its own truth
        assert (model.scale_allowance, model.offset_allowance, model.field_allowance) == (None, None, None)
        assert model.allowance == DEFAULT_ALLOWANCES[kind]
        truth = SystematicError.from_dict(frame.metadata["sim_systematic"])
        assert truth == cam.systematic_error()[0] and truth.kind == kind and not truth.is_zero
        ideal = make(SystematicConfig.off(), pose).render(pose)  # type: ignore[operator]
        assert ideal.measurement.allowance == (0.0, 0.0, 0.0)  # an ideal camera knows it is ideal


def test_a_linear_tof_field_tilts_the_range_across_the_image() -> None:
    """``range_field_m``: the coefficients of u, v, u^2, uv, v^2 (m), on top of the bow (here none)."""
    pose = looking_down(0.6)
    field = dataclasses.replace(NONE, range_field_m=(0.002, -0.001, 0.0, 0.0005, 0.0))
    on = tof(field, pose, **EXACT_TOF).render(pose)
    off = tof(SystematicConfig.off(), pose, **EXACT_TOF).render(pose)
    cam = tof(field, pose, **EXACT_TOF)
    intr = cam.config.intrinsics()
    u, v = normalised_pixels(intr.width, intr.height, intr.cx, intr.cy)
    ok = on.valid & off.valid
    diff = (on.distance.astype(np.float64) - off.distance.astype(np.float64))[ok]
    expected = (0.002 * u - 0.001 * v + 0.0005 * u * v)[ok]
    np.testing.assert_allclose(diff, expected, atol=2e-6)  # float32 distances, no noise or rounding
    assert diff.max() - diff.min() > 0.005  # +-2 mm in u, +-1 mm in v and the cross term: a tilt seen


def test_a_stereo_field_adds_to_the_bow() -> None:
    cfg = dataclasses.replace(NONE, disparity_bow_px=0.5, disparity_field_px=(0.1, 0.0, 0.2, 0.0, -0.1))
    bow = radial_bow_coeffs(0.5, 640, 400)
    assert cfg.stereo(640, 400).field_coeffs == pytest.approx(
        (bow[0] + 0.1, bow[1], bow[2] + 0.2, bow[3], bow[4] - 0.1), abs=1e-15)


def test_the_table_is_read_from_the_document() -> None:
    doc = {"sim": {"systematic": {"fb_error": 0.01, "range_offset_m": -0.002, "wiggle_phase_deg": 90.0}}}
    world = world_from_context(BackendContext(source="cell.toml", document=doc))
    assert world.systematic == SystematicConfig(fb_error=0.01, range_offset_m=-0.002, wiggle_phase_deg=90.0)
    err = world.systematic.tof(224, 172)
    assert err.wiggle_cos_m == pytest.approx(0.0, abs=1e-12) and err.wiggle_sin_m == pytest.approx(0.001)
    assert world_from_context(BackendContext(document={})).systematic == SystematicConfig()  # on by default
    off = world_from_context(BackendContext(document={"sim": {"systematic": {"enabled": False}}})).systematic
    assert off == SystematicConfig.off() and off.stereo(640, 400).is_zero and off.tof(224, 172).is_zero


@pytest.mark.parametrize(("table", "key"), [
    ({"fb_eror": 0.01}, "fb_eror"),
    ({"fb_error": 0.5}, "fb_error"),
    ({"enabled": "yes"}, "enabled"),
    ({"disparity_bow_px": "big"}, "disparity_bow_px"),
    ({"wiggle_amplitude_m": -0.001}, "wiggle_amplitude_m"),
    ({"wiggle_amplitude_m": 0.02, "wiggle_period_m": 0.2}, "wiggle_amplitude_m"),  # 2 pi A / P above 0.5
    ({"range_scale_error": float("nan")}, "range_scale_error"),
    ({"range_field_m": [0.001, 0.0, 0.0]}, "range_field_m"),
    ({"range_field_m": [0.06, 0.0, 0.0, 0.0, 0.0]}, "range_field_m"),
    ({"disparity_field_px": [0.0, float("inf"), 0.0, 0.0, 0.0]}, "disparity_field_px"),
])
def test_a_bad_key_or_value_is_one_line_naming_it(table: dict[str, object], key: str) -> None:
    with pytest.raises(ConfigError) as info:
        world_from_context(BackendContext(source="cell.toml", document={"sim": {"systematic": table}}))
    text = str(info.value)
    assert f"sim.systematic.{key}" in text and "\n" not in text and "cell.toml" in text


@pytest.mark.parametrize("name", ["sim.toml", "sim_oak.toml"])
def test_the_commented_table_in_the_shipped_configs_shows_the_real_defaults(name: str) -> None:
    import tomllib
    from importlib import resources

    text = resources.files("cellcal.configs").joinpath(name).read_text(encoding="utf-8")
    block = text[text.index("# [sim.systematic]"):].split("\n#\n")[0]
    shown = tomllib.loads("\n".join(line[2:] for line in block.splitlines() if line.startswith("# ") and " = " in line))
    assert len(shown) >= 4 and shown["enabled"] is True
    defaults = SystematicConfig()
    for key, value in shown.items():
        assert getattr(defaults, key) == pytest.approx(value, rel=1e-4), key


def test_the_tof_sims_cached_path_is_the_models_distort() -> None:
    table = SystematicConfig(range_scale_error=0.003, range_offset_m=-0.004, wiggle_amplitude_m=0.002,
                             wiggle_phase_deg=-70.0, range_bow_m=0.0015)
    cam = tof(table, looking_down(0.5))
    err, u, v = cam.systematic_error()
    r = np.random.default_rng(1).uniform(0.1, 3.0, u.size)
    np.testing.assert_allclose(cam._distort_range(r), err.distort(r, u, v), rtol=0, atol=1e-12)
