"""Full-frame fit: bad input refused with one-line messages, settings checked where they are made, JSON form."""

from __future__ import annotations

import dataclasses
import json
import math
import tomllib
from typing import Any

import numpy as np
import pytest
from tof_frames import ToFSetup, make_frame

from cellcal.core.calibration.config import load_config, parse_config
from cellcal.core.methods.fullframe import FullFrameSettings, fit_full_frame, fit_plane_points
from cellcal.devices.config import parse_section
from cellcal.devices.errors import CalibrationError, CalibrationQualityError, CellcalError, ConfigError
from cellcal.devices.types import Frame


def _one_line(exc: pytest.ExceptionInfo[Any]) -> str:
    text = str(exc.value)
    assert "\n" not in text
    return text


def _with(frame: Frame, xyz: np.ndarray | None = None, valid: np.ndarray | None = None) -> Frame:
    xyz = (frame.xyz if xyz is None else xyz).astype(np.float32)
    dist = np.linalg.norm(xyz, axis=-1).astype(np.float32)
    return dataclasses.replace(frame, xyz=xyz, distance=dist, valid=frame.valid if valid is None else valid)


@pytest.fixture(scope="module")
def frame() -> Frame:
    return make_frame(ToFSetup(dropout=0.0), 0)


# ---------------------------------------------------------------------- frames and points
@pytest.mark.parametrize("bad", [None, 3.0, "frame", [], [1, 2, 3]])
def test_bad_frames_are_one_line_errors(bad: object) -> None:
    with pytest.raises(CalibrationError) as info:
        fit_full_frame(bad)  # type: ignore[arg-type]
    _one_line(info)


def test_all_invalid_lying_and_mixed_frames(frame: Frame) -> None:
    nan = np.full_like(frame.xyz, np.nan)
    with pytest.raises(CalibrationQualityError) as info:
        fit_full_frame(_with(frame, nan, np.zeros(frame.shape, bool)))
    assert info.value.gate == "valid_fraction" and "0 valid pixel" in _one_line(info)
    lying = _with(frame, frame.xyz.copy())               # NaN coordinates marked valid are skipped
    lying.xyz[:10] = np.nan
    assert math.isfinite(fit_full_frame(lying).tilt_x_rad)
    small = make_frame(ToFSetup(width=32, height=24))
    with pytest.raises(CalibrationError, match="frame 1 has shape"):
        fit_full_frame([frame, small])


def test_few_valid_pixels_say_what_the_edge_margin_left(frame: Frame) -> None:
    valid = np.zeros(frame.shape, bool)
    valid.reshape(-1)[np.random.default_rng(0).choice(valid.size, 16, replace=False)] = True
    with pytest.raises(CalibrationQualityError) as info:
        fit_full_frame(_with(frame, valid=valid))
    assert "16 valid pixels, 0 left after the edge clean-up" in _one_line(info)
    row = np.zeros(frame.shape, bool)
    row[80] = True                                       # one valid row
    with pytest.raises(CalibrationQualityError) as info:
        fit_full_frame(_with(frame, valid=row))
    assert "224 valid pixels, 0 left after the edge clean-up" in _one_line(info)
    line = frame.xyz[80].astype(np.float64)              # the same row as a raw cloud: a line, not a plane
    with pytest.raises(CalibrationError, match="lie along a line"):
        fit_plane_points(line)


def test_millimetres_are_recognised(frame: Frame) -> None:
    mm = dataclasses.replace(frame, xyz=frame.xyz * np.float32(1000), distance=frame.distance * np.float32(1000))
    for call in (lambda: fit_full_frame(mm), lambda: fit_plane_points(frame.xyz[frame.valid] * 1000.0)):
        with pytest.raises(CalibrationError) as info:
            call()
        assert "distances look like millimetres" in _one_line(info)


def test_points_behind_the_camera_are_refused(frame: Frame) -> None:
    flipped = frame.xyz.copy()
    flipped[..., 2] *= -1                                # z flipped: every point behind the camera
    for call in (lambda: fit_full_frame(_with(frame, flipped)), lambda: fit_plane_points(flipped[frame.valid])):
        with pytest.raises(CalibrationError) as info:
            call()
        assert "behind the camera (z <= 0)" in _one_line(info)
    some = frame.xyz.copy()
    some[:5, :, 2] *= -1                                 # a few corrupt pixels are dropped, not fitted
    res = fit_full_frame(_with(frame, some))
    assert res.n_points == int(frame.valid.sum()) - 5 * frame.shape[1] and res.passed


def test_a_plane_missing_the_optical_axis_has_no_height() -> None:
    # a wall parallel to the optical axis, 0.3 m to the right: the axis never meets it
    yy, zz = np.meshgrid(np.linspace(-0.3, 0.3, 60), np.linspace(0.5, 2.0, 60))
    pts = np.column_stack([np.full(yy.size, 0.3), yy.ravel(), zz.ravel()])
    pts += np.random.default_rng(0).normal(0.0, 1e-4, pts.shape)
    with pytest.raises(CalibrationError) as info:
        fit_plane_points(pts)
    assert "does not cross the optical axis in front of the camera" in _one_line(info)


@pytest.mark.parametrize("points", [np.zeros((10, 2)), np.zeros(3), [["a", "b", "c"]], np.full((50, 3), np.nan)])
def test_bad_points_are_one_line_errors(points: object) -> None:
    with pytest.raises(CellcalError) as info:
        fit_plane_points(points)  # type: ignore[arg-type]
    _one_line(info)


def test_degenerate_points() -> None:
    line = np.column_stack([np.linspace(-0.1, 0.1, 100), np.zeros(100), np.full(100, 0.5)])
    with pytest.raises(CalibrationError, match=r"collinear|along a line"):
        fit_plane_points(line)
    with pytest.raises(CalibrationError, match="sigma_m must have shape"):
        fit_plane_points(np.random.default_rng(0).random((30, 3)) + 1.0, sigma_m=np.ones(3))


# ---------------------------------------------------------------------- settings
@pytest.mark.parametrize(("kwargs", "key"), [
    ({"confidence": 1.5}, "full_frame.confidence"),
    ({"confidence": math.nan}, "full_frame.confidence"),
    ({"inlier_threshold_sigma": 0}, "full_frame.inlier_threshold_sigma"),
    ({"hypotheses": 0}, "full_frame.hypotheses"),
    ({"hypotheses": 96.0}, "full_frame.hypotheses"),
    ({"weighted": 1}, "full_frame.weighted"),
    ({"coverage_grid": (0, 4)}, "full_frame.coverage_grid"),
    ({"expected_noise_m": 0.0}, "full_frame.expected_noise_m"),
    ({"seed": -1}, "full_frame.seed"),
    ({"min_inlier_threshold_m": 0.05, "max_inlier_threshold_m": 0.01}, "full_frame"),
])
def test_settings_are_checked_when_made(kwargs: dict[str, Any], key: str) -> None:
    with pytest.raises(ConfigError) as info:
        FullFrameSettings(**kwargs)
    assert info.value.key == key
    _one_line(info)


def test_settings_ranges_live_in_one_place() -> None:
    """Every bounded field: the constructor and the config file reject the same values with the same words."""
    for f in dataclasses.fields(FullFrameSettings):
        for op, bound in f.metadata.items():
            bad = {"gt": bound, "ge": bound - 1, "lt": bound, "le": bound + 1}[op]
            if str(f.type).startswith("tuple"):
                bad = (bad, bad)
            elif "int" in str(f.type) and "float" not in str(f.type):
                bad = int(bad)
            with pytest.raises(ConfigError) as made:
                FullFrameSettings(**{f.name: bad})
            with pytest.raises(ConfigError) as read:
                parse_section(FullFrameSettings, {f.name: bad}, where="full_frame", source="cell.toml")
            assert made.value.key == read.value.key == f"full_frame.{f.name}"
            assert made.value.reason == read.value.reason, f.name


def test_settings_store_what_the_config_file_would() -> None:
    """One checker for both paths (``check_value``): a direct construction converts like a file does."""
    made = FullFrameSettings(confidence=0.9, flatness_sigma=5, coverage_grid=[8, 6])   # type: ignore[arg-type]
    read = parse_section(FullFrameSettings, {"confidence": 0.9, "flatness_sigma": 5, "coverage_grid": [8, 6]},
                         where="full_frame")
    assert made == read
    assert type(made.flatness_sigma) is float and made.coverage_grid == (8, 6)


def _doc(extra: str) -> dict[str, Any]:
    doc = tomllib.loads('[camera]\nbackend = "sim"\n[arm]\nbackend = "sim"\n'
                        '[plan]\nposes = [{xyz_m = [0.3, 0.0, 0.5]}]\n')
    doc.update(tomllib.loads(extra))
    return doc


def test_config_table_defaults_and_values() -> None:
    assert load_config().full_frame == FullFrameSettings()
    cfg = parse_config(_doc("[full_frame]\nconfidence = 0.99\nmin_coverage = 0.5\ncoverage_grid = [8, 6]\n"
                            "weighted = false\nexpected_noise_m = 0.01\nflatness_tolerance_m = 0.002\n"), "cell.toml")
    ff = cfg.full_frame
    assert ff.confidence == 0.99 and ff.coverage_grid == (8, 6) and ff.weighted is False
    assert ff.expected_noise_m == 0.01 and ff.flatness_tolerance_m == 0.002


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
    assert info.value.key == key and _one_line(info).startswith("cell.toml: key ")


# ---------------------------------------------------------------------- JSON
def test_to_dict_is_json_in_degrees_and_only_adds_keys(frame: Frame) -> None:
    d = json.loads(json.dumps(fit_full_frame(frame).to_dict()))
    old_keys = {"method", "angle_deg", "angle_sigma_deg", "angle_ci_deg", "tilt_x_deg", "tilt_x_sigma_deg",
                "tilt_x_ci_deg", "tilt_y_deg", "tilt_y_sigma_deg", "tilt_y_ci_deg", "height_m", "height_sigma_m",
                "height_ci_m", "confidence", "plane_cam", "normal_covariance", "valid_fraction", "inlier_fraction",
                "residual_rms_m", "coverage", "noise_scale_m", "n_points", "n_inliers", "n_frames", "gates", "passed"}
    new_keys = {"noise_ratio", "flatness_m", "flatness_where", "multipath_border_m", "multipath_border_sigma_m",
                "multipath_border_ci_m", "multipath_shift", "mixed_margin_px", "n_mixed"}
    honest_keys = {"measurement", "native_space", "residual_expected_m", "residual_floor_m", "multipath_allowance_m",
                   "lock_on", "expected_departure", "interval_factors", "interval_notes"}   # issue 27
    budget_keys = {"error_budget"}                                                    # issue 39, ADR 0059
    split_keys = {"noise_normal_covariance", "noise_offset_sigma_m", "noise_normal_offset_covariance",
                  "systematic_shifts"}                                                # ADR 0059 "Amended"
    assert set(d) == old_keys | new_keys | honest_keys | budget_keys | split_keys
    assert d["method"] == "full_frame" and d["angle_deg"] == pytest.approx(80.0, abs=0.05)
    assert d["tilt_x_ci_deg"][0] < d["tilt_x_deg"] < d["tilt_x_ci_deg"][1]
    assert set(d["gates"]) == {"valid_fraction", "inlier_fraction", "residual_rms_m", "coverage", "flatness",
                               "residual_floor"}
    assert d["passed"] is True and all(g["passed"] for g in d["gates"].values())
    assert set(d["multipath_shift"]) == {"angle_deg", "tilt_x_deg", "tilt_y_deg", "height_m"}
