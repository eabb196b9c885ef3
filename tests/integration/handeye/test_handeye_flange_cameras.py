"""``cellcal handeye`` of several cameras on the flange in one run (issue #40, ADR 0061).

configs/sim_two_wrist.toml: "wrist" (driven) and "wrist2" (6 cm beside it, 10 deg off the tool's
axis) on the flange, their true mounts a few mm and tenths of a degree off the configured ones.
One run of the automatic plan (8 poses) estimates both: each camera's 95 % interval must hold its
truth (the run's margins: |error| / half-width <= 0.4 on every value at seed 7).
"""

from __future__ import annotations

import json
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fuzz_targets import dump_toml

from cellcal.core.cli import main

CONFIGS = Path(__file__).resolve().parents[3] / "configs"
TWO = CONFIGS / "sim_two_wrist.toml"


def _truth(document: dict[str, Any], name: str) -> tuple[np.ndarray, np.ndarray]:
    """The true mount of ``name``: translation (m), roll-pitch-yaw (deg), from ``[[sim.cameras]]``."""
    entry = next(t for t in document["sim"]["cameras"] if t["name"] == name)
    return np.asarray(entry["translation_m"]), np.asarray(entry["rpy_deg"])


def _holds(mount: dict[str, Any], truth: tuple[np.ndarray, np.ndarray]) -> None:
    """The 95 % intervals of ``mount`` hold the truth (translation, m; rpy, deg)."""
    for key, true in (("translation_ci_m", truth[0]), ("rpy_ci_deg", truth[1])):
        ci = np.asarray(mount[key])
        assert np.all(ci[:, 0] <= true) and np.all(true <= ci[:, 1]), (key, ci.tolist(), true.tolist())


def test_two_flange_cameras_are_found_in_one_run_and_related(tmp_path: Path,
                                                               capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["handeye", "--config", str(TWO), "--no-report", "--quiet", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    document = tomllib.loads(TWO.read_text(encoding="utf-8"))
    driven = json.loads((tmp_path / "handeye.json").read_text(encoding="utf-8"))
    other = json.loads((tmp_path / "handeye-wrist2.json").read_text(encoding="utf-8"))
    assert driven["camera"] == "wrist" and other["camera"] == "wrist2" and other["schema"] == driven["schema"]
    assert other["driven_camera"] == "wrist" and other["plan_poses_used"] == list(range(8))
    assert other["capture"]["together"] == ["wrist", "wrist2"]
    _holds(driven["mount"], _truth(document, "wrist"))
    _holds(other["mount"], _truth(document, "wrist2"))
    assert "camera 'wrist2' (on the flange): mount xyz" in out and "from 8 of 8 poses" in out
    # the files relate: the two cameras on the flange, one plane
    assert main(["cameras", str(tmp_path / "handeye.json"), str(tmp_path / "handeye-wrist2.json")]) == 0
    related = capsys.readouterr().out
    assert "wrist -> wrist2 (both on the flange)" in related or "wrist2 -> wrist (both on the flange)" in related
    assert "planes agree" in related


def test_fixed_cameras_are_said_and_a_camera_that_cannot_see_the_plane_has_no_mount(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    document = tomllib.loads((CONFIGS / "sim_multi.toml").read_text(encoding="utf-8"))
    # a second camera on the flange looking up, away from the plane: no plane at any pose
    document["cameras"].append({"name": "up", "on": "flange", "backend": "sim",
                                "mount": {"translation_m": [0.0, -0.04, 0.06], "rpy_deg": [180.0, 0.0, 0.0]}})
    config = tmp_path / "cell.toml"
    config.write_text(dump_toml(document), encoding="utf-8")
    status = main(["handeye", "--config", str(config), "--no-report", "--quiet", "--out", str(tmp_path / "out")])
    out = capsys.readouterr().out
    assert status == 1  # a camera of the run has no mount; the driven camera's is written
    assert (tmp_path / "out" / "handeye.json").exists() and not (tmp_path / "out" / "handeye-up.json").exists()
    assert "fixed camera(s) above, side45: not part of a hand-eye run" in out
    line = next(x for x in out.splitlines() if x.startswith("camera 'up'"))
    assert "no mount: a plane at 0 of 8 poses, at least 3 needed" in line
