"""Full-frame plane fit: accuracy against the sim's truth, robustness, honest intervals, gates."""

from __future__ import annotations

import dataclasses
import json
import math
import tomllib

import numpy as np
import pytest
from scipy.ndimage import binary_dilation

from cellcal.core.calibration.config import load_config, parse_config
from cellcal.core.geometry.planes import Plane
from cellcal.core.methods.fullframe import (
    FullFrameSettings,
    check_gates,
    fit_full_frame,
    fit_plane_points,
)
from cellcal.devices.errors import CalibrationError, CalibrationQualityError, CellcalError, ConfigError
from cellcal.devices.pose import Pose
from cellcal.devices.types import Frame
from cellcal.sims.camera import SimCamera, SimCameraConfig, noise_sigma_m
from cellcal.sims.scene import Box, Scene
from cellcal.sims.world import SimWorld

HEIGHT_M = 0.6
INCLINATION_DEG = 80.0


def _pose() -> Pose:
    from cellcal.core.calibration.config import look_at_pose
    return look_at_pose(np.array([0.3, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]), HEIGHT_M,
                        math.radians(INCLINATION_DEG), "x")


def _camera(boxes: tuple[Box, ...] = (), seed: int = 0, **cfg: object) -> tuple[SimCamera, Pose, Plane]:
    scene = Scene(np.zeros(3), np.array([0.0, 0.0, 1.0]), boxes)
    cam = SimCamera(SimCameraConfig(seed=seed, **cfg), world=SimWorld(scene, Pose.identity(), seed=seed))
    pose = _pose()
    truth = Plane.from_point_normal(np.zeros(3), [0.0, 0.0, 1.0]).transformed(pose.inv()).oriented_toward_origin()
    return cam, pose, truth


def _clutter_boxes() -> tuple[Box, ...]:
    """Eight boxes hiding about a third of the table (footprint x -0.08..0.68 m, y -0.24..0.28 m)."""
    return (Box((0.30, -0.12), (0.12, 0.14, 0.08), 0.3), Box((0.27, 0.10), (0.14, 0.12, 0.12), -0.4),
            Box((0.37, 0.00), (0.10, 0.12, 0.05), 0.9), Box((0.20, -0.02), (0.09, 0.10, 0.10), 0.0),
            Box((0.40, -0.20), (0.10, 0.10, 0.06), 0.2), Box((0.40, 0.20), (0.10, 0.11, 0.07), 0.5),
            Box((0.18, 0.18), (0.08, 0.08, 0.04), 0.1), Box((0.18, -0.20), (0.08, 0.08, 0.04), 0.7))


def _off_plane(frame: Frame, pose: Pose, tol_m: float = 0.005) -> np.ndarray:
    """(H, W) True where the (valid) pixel is not on the table."""
    world = pose.apply(np.nan_to_num(frame.xyz.reshape(-1, 3).astype(np.float64)))
    return (frame.valid.reshape(-1) & (np.abs(world[:, 2]) > tol_m)).reshape(frame.shape)


def _deg(x: float) -> float:
    return math.degrees(x)


def _replace(frame: Frame, xyz: np.ndarray, valid: np.ndarray | None = None) -> Frame:
    xyz = xyz.astype(np.float32)
    dist = np.linalg.norm(xyz, axis=-1).astype(np.float32)
    v = np.isfinite(dist) if valid is None else valid
    return dataclasses.replace(frame, xyz=xyz, distance=dist, valid=v)


# ---------------------------------------------------------------------- accuracy
def test_noise_free_plane_is_recovered_exactly() -> None:
    cam, pose, truth = _camera(noise=False, quantisation_m=0.0)
    res = fit_full_frame(cam.render(pose))
    assert abs(_deg(res.tilt_x_rad - truth.tilt_about_x_rad())) < 1e-4
    assert abs(_deg(res.tilt_y_rad - truth.tilt_about_y_rad())) < 1e-4
    assert abs(_deg(res.angle_rad) - INCLINATION_DEG) < 1e-4
    assert res.height_m == pytest.approx(HEIGHT_M, abs=1e-6)
    assert res.plane.offset_m > 0 and res.plane.normal[2] < 0      # facing the camera
    assert res.inlier_fraction > 0.999 and res.passed


def test_derived_values_follow_the_plane_methods() -> None:
    cam, pose, _ = _camera(seed=3)
    res = fit_full_frame(cam.render(pose))
    pl = res.plane
    assert res.angle_rad == pytest.approx(pl.angle_to_optical_axis_rad(), abs=1e-12)
    assert res.tilt_x_rad == pytest.approx(pl.tilt_about_x_rad(), abs=1e-12)
    assert res.tilt_y_rad == pytest.approx(pl.tilt_about_y_rad(), abs=1e-12)
    assert res.height_m == pytest.approx(pl.distance_along_optical_axis_m(), abs=1e-12)
    lo, hi = res.tilt_x_ci_rad
    assert lo < res.tilt_x_rad < hi
    assert (hi - lo) / 2 == pytest.approx(1.959964 * res.tilt_x_sigma_rad, rel=1e-5)
    # the normal covariance is tangent to the sphere
    assert abs(res.plane.normal @ res.normal_covariance @ res.plane.normal) < 1e-6 * np.trace(res.normal_covariance)


def test_clutter_of_boxes_is_rejected() -> None:
    cam, pose, truth = _camera(_clutter_boxes(), seed=1)
    frame = cam.render(pose)
    off = _off_plane(frame, pose)
    clutter = off.sum() / frame.valid.sum()
    assert 0.30 <= clutter <= 0.45, clutter
    res = fit_full_frame(frame)
    check_gates(res)
    err_x = res.tilt_x_rad - truth.tilt_about_x_rad()
    err_y = res.tilt_y_rad - truth.tilt_about_y_rad()
    assert abs(_deg(err_x)) < 0.02 and abs(err_x) < 4 * res.tilt_x_sigma_rad
    assert abs(_deg(err_y)) < 0.02 and abs(err_y) < 4 * res.tilt_y_sigma_rad
    assert abs(res.height_m - HEIGHT_M) < 2e-4
    # boxes (more than 2 cm above the table) are outliers; the table is mostly inliers
    tall = _off_plane(frame, pose, 0.02)
    assert np.count_nonzero(res.inlier_mask & tall) == 0
    # the table is inlier except a thin rim around the boxes (edge_margin_deg: 1 px here)
    table = frame.valid & ~off
    assert np.count_nonzero(res.inlier_mask & table) / table.sum() > 0.93
    far = table & ~binary_dilation(off | ~frame.valid, iterations=3)
    assert np.count_nonzero(res.inlier_mask & far) / far.sum() > 0.99
    # the noise scale found matches the sim's model: 3.2 mm at 1 m (+ 1 mm quantisation)
    assert 0.0030 < res.noise_scale_m < 0.0036


def test_flying_pixels_and_gross_outliers_are_rejected() -> None:
    cam, pose, truth = _camera(seed=2)
    frame = cam.render(pose)
    rng = np.random.default_rng(5)
    xyz = frame.xyz.astype(np.float64).copy()
    flat = xyz.reshape(-1, 3)
    n = flat.shape[0]
    fly = rng.choice(n, n // 10, replace=False)           # 10 % flying pixels: range off by 2-30 %
    flat[fly] *= rng.choice([-1.0, 1.0], fly.size)[:, None] * rng.uniform(0.02, 0.3, fly.size)[:, None] + 1.0
    gross = rng.choice(n, n // 20, replace=False)        # 5 % anywhere in a 2 m cube
    flat[gross] = rng.uniform([-1.0, -1.0, 0.1], [1.0, 1.0, 2.0], (gross.size, 3))
    multipath = rng.choice(n, n // 20, replace=False)    # 5 %: +1..3 cm range bias
    flat[multipath] *= 1.0 + rng.uniform(0.01, 0.03, multipath.size)[:, None] / np.linalg.norm(
        flat[multipath], axis=1, keepdims=True)
    res = fit_full_frame(_replace(frame, xyz))
    clean = fit_full_frame(frame)
    assert 0.75 < res.inlier_fraction < 0.85
    for got, ref, sig in ((res.tilt_x_rad, truth.tilt_about_x_rad(), res.tilt_x_sigma_rad),
                          (res.tilt_y_rad, truth.tilt_about_y_rad(), res.tilt_y_sigma_rad)):
        assert abs(got - ref) < 4 * sig and abs(_deg(got - ref)) < 0.02
    assert abs(res.height_m - HEIGHT_M) < 4 * res.height_sigma_m
    assert res.tilt_x_sigma_rad < 1.3 * clean.tilt_x_sigma_rad


def test_pooled_frames_shrink_the_interval() -> None:
    cam, pose, truth = _camera(seed=4)
    frames = [cam.render(pose) for _ in range(4)]
    one = fit_full_frame(frames[0])
    four = fit_full_frame(frames)
    assert four.n_frames == 4 and four.n_points == 4 * one.n_points
    assert 1.7 < one.tilt_x_sigma_rad / four.tilt_x_sigma_rad < 2.3
    assert abs(four.tilt_x_rad - truth.tilt_about_x_rad()) < 4 * four.tilt_x_sigma_rad
    assert four.inlier_mask.shape == frames[0].shape


def test_interval_coverage_monte_carlo() -> None:
    """The 95 % intervals contain the truth in 92-98 % of 200 seeded noisy frames.

    The scene (table + 3 boxes) is ray-cast once; each trial draws the sim camera's
    range noise (its own ``noise_sigma_m`` model along each ray) and 1 mm quantisation.
    """
    cam, pose, truth = _camera(_clutter_boxes()[:3], seed=11, noise=False, quantisation_m=0.0)
    base = cam.render(pose)
    rays = (base.xyz / base.distance[..., None]).reshape(-1, 3).astype(np.float64)
    ok = base.valid.reshape(-1)
    dirs = pose.apply_vector(np.where(ok[:, None], rays, [0.0, 0.0, 1.0]))
    t_true, normals, _ = cam.world.scene.raycast(pose.translation, dirs)
    cos_inc = np.where(ok, -np.einsum("ij,ij->i", normals, dirs), 1.0)
    sigma = noise_sigma_m(np.where(ok, t_true, 1.0), cos_inc)
    rng = np.random.default_rng(2024)
    true = {"tilt_x": truth.tilt_about_x_rad(), "tilt_y": truth.tilt_about_y_rad(),
            "angle": truth.angle_to_optical_axis_rad(), "height": truth.distance_along_optical_axis_m()}
    hits = dict.fromkeys(true, 0)
    z = []
    trials = 200
    for _ in range(trials):
        d = np.round((t_true + sigma * rng.standard_normal(t_true.size)) / 0.001) * 0.001
        xyz = np.where(ok[:, None], rays * d[:, None], np.nan).reshape(base.xyz.shape)
        r = fit_full_frame(_replace(base, xyz, base.valid))
        got = {"tilt_x": r.tilt_x_ci_rad, "tilt_y": r.tilt_y_ci_rad, "angle": r.angle_ci_rad, "height": r.height_ci_m}
        for k, (lo, hi) in got.items():
            hits[k] += lo <= true[k] <= hi
        z.append((r.tilt_x_rad - true["tilt_x"]) / r.tilt_x_sigma_rad)
    for k, h in hits.items():
        assert 0.92 <= h / trials <= 0.98, (k, h / trials)
    assert 0.85 < float(np.std(z)) < 1.15
    assert abs(float(np.mean(z))) < 0.3


def test_unweighted_and_given_sigma_agree_with_the_truth() -> None:
    cam, pose, truth = _camera(seed=6)
    frame = cam.render(pose)
    pts = frame.xyz[frame.valid].astype(np.float64)
    unweighted = fit_plane_points(pts, settings=FullFrameSettings(weighted=False))
    # the sim's own per-pixel sigma (true range and incidence)
    rng_true = -truth.offset_m / (pts / np.linalg.norm(pts, axis=1, keepdims=True) @ truth.normal)
    cos_inc = np.abs(pts @ truth.normal) / np.linalg.norm(pts, axis=1)
    given = fit_plane_points(pts, sigma_m=noise_sigma_m(rng_true, cos_inc))
    for r in (unweighted, given):
        assert abs(r.tilt_x_rad - truth.tilt_about_x_rad()) < 4 * r.tilt_x_sigma_rad
        assert math.isnan(r.coverage) and "coverage" not in r.gates
        assert r.inlier_mask.shape == (pts.shape[0],)
    assert 0.8 < given.noise_scale_m < 1.3           # sigma given exactly: unit scale


# ---------------------------------------------------------------------- gates
def test_gate_mostly_invalid_frame() -> None:
    cam, pose, _ = _camera(seed=7)
    frame = cam.render(pose)
    valid = frame.valid.copy()
    valid[:, 60:] = False                                # 27 % of the image stays valid
    xyz = frame.xyz.copy()
    xyz[~valid] = np.nan
    res = fit_full_frame(_replace(frame, xyz, valid))
    assert res.gates["valid_fraction"][2] is False
    with pytest.raises(CalibrationQualityError) as info:
        check_gates(res)
    assert info.value.gate == "valid_fraction"
    assert info.value.value == pytest.approx(60 / 224, abs=0.01)
    msg = str(info.value)
    assert "\n" not in msg and "valid pixels" in msg and "below the minimum of 50 %" in msg


def test_gate_plane_seen_in_one_corner_fails_coverage() -> None:
    """Data only in the left 60 % of the image, and its top 45 % a surface 20 cm nearer:
    valid and inlier fractions pass, but the table is seen in one corner of the image."""
    cam, pose, _ = _camera(seed=8)
    frame = cam.render(pose)
    h, w = frame.shape
    valid = frame.valid.copy()
    valid[:, int(0.6 * w):] = False
    xyz = frame.xyz.copy()
    xyz[~valid] = np.nan
    xyz[: int(0.45 * h)] *= 0.8                          # a nearer surface along the same rays
    res = fit_full_frame(_replace(frame, xyz, valid))
    assert res.gates["valid_fraction"][2] is True
    assert res.gates["inlier_fraction"][2] is True
    with pytest.raises(CalibrationQualityError) as info:
        check_gates(res)
    assert info.value.gate == "coverage"
    assert info.value.value == pytest.approx(15 / 36)        # 15 of the 6x6 cells hold table inliers
    assert "image cells holding plane inliers" in str(info.value)


def test_gates_accept_scattered_clutter_hiding_40_percent() -> None:
    """Boxes hiding 40 % of the table in several places: the fit is sound, the gates pass."""
    boxes = (Box((0.22, -0.15), (0.2, 0.2, 0.08), 0.3), Box((0.42, 0.12), (0.22, 0.2, 0.1), -0.4),
             Box((0.10, 0.14), (0.14, 0.16, 0.05), 0.9), Box((0.5, -0.18), (0.14, 0.14, 0.06), 0.2))
    cam, pose, truth = _camera(boxes, seed=3)
    frame = cam.render(pose)
    hidden = float(np.mean(_off_plane(frame, pose)))
    assert 0.3 < hidden < 0.5, hidden
    res = fit_full_frame(frame)
    check_gates(res)
    assert abs(_deg(res.tilt_x_rad - truth.tilt_about_x_rad())) < 0.05


def test_gate_inlier_fraction_and_residual_rms() -> None:
    cam, pose, _ = _camera(seed=9)
    frame = cam.render(pose)
    rng = np.random.default_rng(1)
    xyz = frame.xyz.copy()
    flat = xyz.reshape(-1, 3)
    bad = rng.random(flat.shape[0]) < 0.6                # 60 % gross outliers
    flat[bad] = rng.uniform([-1.0, -1.0, 0.2], [1.0, 1.0, 2.0], (int(bad.sum()), 3))
    with pytest.raises(CalibrationQualityError) as info:
        check_gates(fit_full_frame(_replace(frame, xyz)))
    assert info.value.gate == "inlier_fraction"
    noisy, pose2, _ = _camera(seed=9, noise_scale=12.0)  # ~18 mm range noise at 0.6 m
    with pytest.raises(CalibrationQualityError) as info:
        check_gates(fit_full_frame(noisy.render(pose2)))
    assert info.value.gate == "residual_rms_m" and "mm" in str(info.value)


def test_check_gates_with_other_thresholds() -> None:
    cam, pose, _ = _camera(_clutter_boxes(), seed=1)
    res = fit_full_frame(cam.render(pose))
    check_gates(res)                                     # defaults: passes
    strict = FullFrameSettings(min_inlier_fraction=0.9)
    with pytest.raises(CalibrationQualityError) as info:
        check_gates(res, strict)
    assert info.value.gate == "inlier_fraction" and info.value.threshold == 0.9


# ---------------------------------------------------------------------- bad input
@pytest.mark.parametrize("bad", [None, 3.0, "frame", [], [1, 2, 3]])
def test_bad_frames_are_one_line_errors(bad: object) -> None:
    with pytest.raises(CalibrationError) as info:
        fit_full_frame(bad)  # type: ignore[arg-type]
    assert "\n" not in str(info.value)


def test_all_invalid_and_mixed_frames() -> None:
    cam, pose, _ = _camera(seed=10)
    frame = cam.render(pose)
    nan = np.full_like(frame.xyz, np.nan)
    with pytest.raises(CalibrationQualityError) as info:
        fit_full_frame(_replace(frame, nan, np.zeros(frame.shape, bool)))
    assert info.value.gate == "valid_fraction" and "0 valid pixel" in str(info.value)
    # valid flags that lie (NaN coordinates marked valid) are skipped, not propagated
    lying = _replace(frame, frame.xyz.copy(), frame.valid.copy())
    lying.xyz[:10] = np.nan
    assert math.isfinite(fit_full_frame(lying).tilt_x_rad)
    small = SimCamera(SimCameraConfig(width=32, height=24), world=SimWorld(Scene(), Pose.identity())).render(pose)
    with pytest.raises(CalibrationError, match="frame 1 has shape"):
        fit_full_frame([frame, small])


@pytest.mark.parametrize("points", [np.zeros((10, 2)), np.zeros(3), [["a", "b", "c"]], np.full((50, 3), np.nan)])
def test_bad_points_are_one_line_errors(points: object) -> None:
    with pytest.raises(CellcalError) as info:
        fit_plane_points(points)  # type: ignore[arg-type]
    assert "\n" not in str(info.value)


def test_degenerate_points() -> None:
    line = np.column_stack([np.linspace(-0.1, 0.1, 100), np.zeros(100), np.full(100, 0.5)])
    with pytest.raises(CalibrationError):
        fit_plane_points(line)
    with pytest.raises(CalibrationError, match="sigma_m must have shape"):
        fit_plane_points(np.random.default_rng(0).random((30, 3)) + 1.0, sigma_m=np.ones(3))


# ---------------------------------------------------------------------- config and JSON
def _doc(extra: str) -> dict:
    doc = tomllib.loads(_SIM_TOML)
    doc.update(tomllib.loads(extra))
    return doc


_SIM_TOML = """
[camera]
backend = "sim"
[arm]
backend = "sim"
[plan]
poses = [{xyz_m = [0.3, 0.0, 0.5]}]
"""


def test_config_table_defaults_and_values() -> None:
    assert load_config().full_frame == FullFrameSettings()
    cfg = parse_config(_doc("[full_frame]\nconfidence = 0.99\nmin_coverage = 0.5\ncoverage_grid = [8, 6]\n"
                            "weighted = false\n"), "cell.toml")
    assert cfg.full_frame.confidence == 0.99 and cfg.full_frame.coverage_grid == (8, 6)
    assert cfg.full_frame.weighted is False


@pytest.mark.parametrize(("table", "key"), [
    ("confidence = 1.0", "full_frame.confidence"),
    ("min_valid_fraction = -0.1", "full_frame.min_valid_fraction"),
    ("weighted = 1", "full_frame.weighted"),
    ("coverage_grid = [0, 4]", "full_frame.coverage_grid"),
    ("inlier_threshold_m = 0.01", "full_frame.inlier_threshold_m"),
    ("max_residual_rms_m = \"1 cm\"", "full_frame.max_residual_rms_m"),
    ("min_inlier_threshold_m = 0.05\nmax_inlier_threshold_m = 0.01", "full_frame"),
])
def test_config_table_rejects_bad_values(table: str, key: str) -> None:
    with pytest.raises(ConfigError) as info:
        parse_config(_doc("[full_frame]\n" + table), "cell.toml")
    assert info.value.key == key and str(info.value).startswith("cell.toml: key ")
    assert "\n" not in str(info.value)


def test_to_dict_is_json_in_degrees() -> None:
    cam, pose, _ = _camera(seed=12)
    res = fit_full_frame(cam.render(pose))
    d = json.loads(json.dumps(res.to_dict()))
    assert d["method"] == "full_frame"
    assert d["angle_deg"] == pytest.approx(INCLINATION_DEG, abs=0.05)
    assert d["tilt_x_ci_deg"][0] < d["tilt_x_deg"] < d["tilt_x_ci_deg"][1]
    assert set(d["gates"]) == {"valid_fraction", "inlier_fraction", "residual_rms_m", "coverage"}
    assert d["passed"] is True and d["gates"]["coverage"]["passed"] is True


def test_edge_margin_drops_rims_of_patches_not_of_isolated_outliers() -> None:
    from cellcal.core.methods.fullframe.fit import _edge_keep
    h, w = 20, 30
    valid = np.ones((h, w), bool)
    inl = np.ones((h, w), bool)
    inl[5:10, 5:10] = False                              # a 5x5 box: a patch
    inl[15, 20] = False                                  # one noisy pixel: isolated
    keep = _edge_keep(inl.reshape(-1), [valid.reshape(-1)], (h, w), 2).reshape(h, w)
    assert not keep[3:12, 3:12].any()                    # patch grown by 2 px
    assert keep[2, 5] and keep[5, 12] and keep[12, 12]
    assert keep[14:17, 19:22].all()                      # the isolated outlier leaves its neighbours
    assert np.count_nonzero(~keep) == 81
