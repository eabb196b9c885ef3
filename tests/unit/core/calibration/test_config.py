"""Cell configuration loading: the packaged default, plan geometry, and one-line errors."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from repo_paths import REPO_ROOT

from cellcal.core.calibration.config import load_config, plan_flange_poses
from cellcal.core.methods.measure import expected_geometry
from cellcal.devices import ConfigError


def test_packaged_sim_config_generates_the_papers_plan() -> None:
    config = load_config(None)
    assert config.source == "<packaged sim.toml>"
    poses = plan_flange_poses(config)
    assert len(poses) == 3
    mount = config.mount.pose()
    for flange, height in zip(poses, (0.46, 0.59, 0.61), strict=True):
        exp = expected_geometry(flange @ mount, (0, 0, 0), (0, 0, 1))
        assert math.degrees(exp.angle_rad) == pytest.approx(80.0, abs=1e-9)
        assert exp.height_m == pytest.approx(height, abs=1e-12)
        assert math.degrees(exp.tilt_x_rad) == pytest.approx(10.0, abs=1e-9)
        assert exp.tilt_y_rad == pytest.approx(0.0, abs=1e-12)
        # the optical axis hits the configured target
        cam = flange @ mount
        axis = cam.rotation.apply([0, 0, 1])
        hit = cam.translation + height * axis
        np.testing.assert_allclose(hit, [0.3, 0.0, 0.0], atol=1e-12)


BASE = """
[camera]
backend = "sim"
[arm]
backend = "sim"
[reference]
plane_point_m = [0.0, 0.0, 0.0]
plane_normal = [0.0, 0.0, 1.0]
"""


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        ("[plan]\nheights_m = 0.5\n", r"key 'plan.heights_m': expected a list of numbers, got float 0.5"),
        ("[plan]\ninclination_deg = 95.0\n", r"key 'plan.inclination_deg': must be <= 90, got 95.0"),
        ("[plan]\nmethods = ['magic']\n", r"key 'plan.methods\[0\]': expected one of 'law_of_cosines'"),
        ("[plan]\nwindow_px = 4\n", r"plan.window_px must be odd, got 4"),
        ("[plan]\nhieghts_m = [0.5]\n",
         r"key 'plan.hieghts_m': unknown key; did you mean 'heights_m'\? \(expected one of: acceleration_m_s2"),
        ("[plan]\nspeed_m_s = 5e-324\n", r"key 'plan.speed_m_s': must be >= 0.001, got 5e-324"),
        ("[plan]\nheights_m = [0.5, 1e308]\n", r"key 'plan.heights_m': must be <= 10.0, got \(0.5, 1e\+308\)"),
        ("[plan]\nmove_timeout_s = 1e308\n", r"key 'plan.move_timeout_s': must be <= 3600, got 1e\+308"),
        ("[cell]\nseed = 4294967296\n", r"key 'cell.seed': must be <= 4294967295, got 4294967296"),
        ("[mount]\ntranslation_m = [0, 0]\n", r"key 'mount.translation_m': expected a list of 3 numbers, got 2 items"),
        ("[cell]\nseed = 'x'\n", r"key 'cell.seed': expected an integer, got str 'x'"),
        ("[extras]\na = 1\n", r"key 'extras': unknown table"),
    ],
)
def test_bad_values_name_file_key_and_expectation(tmp_path: Path, extra: str, message: str) -> None:
    path = tmp_path / "cell.toml"
    path.write_text(BASE + extra)
    with pytest.raises(ConfigError, match=message) as info:
        load_config(path)
    text = str(info.value)
    assert text.startswith(str(path)) and "\n" not in text


def test_missing_file_and_bad_toml(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"nope.toml: file not found"):
        load_config(tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[camera\nbackend = 1")
    with pytest.raises(ConfigError, match=r"bad.toml: invalid TOML"):
        load_config(bad)


def test_missing_backend_and_reference(tmp_path: Path) -> None:
    path = tmp_path / "c.toml"
    path.write_text("[camera]\nbackend = 'sim'\n")
    with pytest.raises(ConfigError, match=r"key 'arm': missing table"):
        load_config(path)
    path.write_text("[camera]\nbackend = 'sim'\n[arm]\nbackend='sim'\n")
    with pytest.raises(ConfigError, match=r"generated plan poses need a \[reference\] plane"):
        load_config(path)


def test_explicit_plan_poses(tmp_path: Path) -> None:
    path = tmp_path / "c.toml"
    path.write_text(BASE + "[[plan.poses]]\nxyz_m = [0.3, 0.0, 0.5]\nrpy_deg = [180.0, 0.0, 0.0]\n")
    poses = plan_flange_poses(load_config(path))
    assert len(poses) == 1
    np.testing.assert_allclose(poses[0].translation, [0.3, 0.0, 0.5])
    np.testing.assert_allclose(poses[0].rotation.apply([0, 0, 1]), [0, 0, -1], atol=1e-12)


def test_azimuths_view_the_target_from_every_side() -> None:
    path = REPO_ROOT / "configs" / "sim_handeye.toml"
    config = load_config(path)
    poses = plan_flange_poses(config)
    assert len(poses) == 4  # two heights x two azimuths
    mount = config.mount.pose()
    headings = []
    for i, flange in enumerate(poses):
        cam = flange @ mount
        exp = expected_geometry(cam, (0, 0, 0), (0, 0, 1))
        assert math.degrees(exp.angle_rad) == pytest.approx(75.0, abs=1e-9)
        assert exp.height_m == pytest.approx((0.46, 0.55)[i // 2], abs=1e-12)
        axis = cam.rotation.apply([0, 0, 1])
        hit = cam.translation - cam.translation[2] / axis[2] * axis
        np.testing.assert_allclose(hit, (0.3, 0.0, 0.0), atol=1e-12)
        headings.append(math.degrees(math.atan2(axis[1], axis[0])))
    # the horizontal direction of the optical axis turns by the configured azimuths
    turns = [(h - headings[0]) % 360 for h in headings[:2]]
    np.testing.assert_allclose(turns, [0, 180], atol=1e-9)


def test_calibrate_with_a_wrong_mount_is_flagged_only_by_a_multi_azimuth_plan(tmp_path: Path) -> None:
    import json

    from cellcal.core.cli import main

    src = (REPO_ROOT / "configs" / "sim_handeye.toml").read_text()
    # the simulated camera really sits 1 deg (roll) off the configured mount
    wrong = src.replace("rpy_deg = [0.6, -0.5, 90.6]", "rpy_deg = [1.0, 0.0, 90.0]")
    wrong = wrong.replace("translation_m = [0.003, 0.036, 0.063]", "translation_m = [0.0, 0.04, 0.06]")
    assert wrong.count("rpy_deg = [1.0, 0.0, 90.0]") == 1  # [sim.mount] of the file
    verdicts = {}
    for name, text in (("four_sides", wrong), ("one_side", wrong.replace("[0.0, 180.0]", "[0.0]"))):
        cfg = tmp_path / f"{name}.toml"
        cfg.write_text(text)
        assert main(["calibrate", "--quiet", "--config", str(cfg), "--out", str(tmp_path / name)]) == 0
        doc = json.loads((tmp_path / name / "result.json").read_text())
        verdicts[name] = doc["summary"]["plane_consistency"]["verdict"]
    assert verdicts == {"four_sides": "inconsistent", "one_side": "blind"}


def test_commented_optional_tables_in_sim_toml_show_the_real_defaults() -> None:
    import tomllib
    from dataclasses import fields

    from cellcal.core.calibration.config import CellConfig

    text = (REPO_ROOT / "configs" / "sim.toml").read_text()
    block = text[text.index("# Optional tables"):text.index("# The simulated world")]
    shown = tomllib.loads("\n".join(line[2:] for line in block.splitlines()
                                    if line.startswith("# [") or (line.startswith("# ") and " = " in line)))
    assert set(shown) == {"full_frame", "monitor"}
    defaults = {f.name: f.default_factory() if callable(f.default_factory) else f.default  # type: ignore[misc]
                for f in fields(CellConfig) if f.name in shown}
    for table, values in shown.items():
        for key, value in values.items():
            assert getattr(defaults[table], key) == value, f"{table}.{key}"
