"""A real ``cellcal calibrate`` with the ACME camera on cellcal's simulated arm.

The ``acme-z1-emulated`` camera asks cellcal's public scene view what it sees from the
arm's pose, so the plane measured from four sides agrees in the base frame; a camera
that ignores the arm (``follow_arm = false``) is named as one at the second pose.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from cellcal.core.cli import main

HERE = Path(__file__).resolve().parent
CELL = HERE.parent / "acme_cell.toml"


def _calibrate(tmp_path: Path, config: Path, *extra: str) -> tuple[int, dict[str, object]]:
    out = tmp_path / "out"
    code = main(["calibrate", "--config", str(config), "--out", str(out), "--quiet", *extra])
    return code, json.loads((out / "result.json").read_text())


def test_the_check_shows_what_connects_to_what(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["calibrate", "--check", "--config", str(CELL)]) == 0
    out = capsys.readouterr().out
    assert "camera:  backend 'acme-z1-emulated' (acme_cellcal.emulated.AcmeZ1EmulatedCamera)" in out
    assert "plan:    8 poses" in out
    assert "image:   160x120 px (from the configuration) holds the grid at perimeters 30 px with 3 px windows" in out


def test_the_check_refuses_an_image_too_small_for_the_plan(tmp_path: Path,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    """The emulated Z1 knows its image from its config: --check says at once what the run would refuse."""
    small = tmp_path / "small.toml"
    small.write_text(CELL.read_text().replace("noise_m = 0.001", "noise_m = 0.001\nwidth = 64\nheight = 48"))
    assert main(["calibrate", "--check", "--config", str(small)]) == 2
    why = (f"{small}: key 'plan.perimeters_px': perimeter 30 px puts the P1-P9 grid with its 3 px sampling windows "
           "outside the 64x48 image (at most 22.5 px from the principal point (31.5, 23.5) px); use perimeters_px "
           "of at most 22 px")
    assert capsys.readouterr().err == f"cellcal: error: {why}\n"
    assert main(["calibrate", "--config", str(small), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    assert capsys.readouterr().err.startswith(f"cellcal: error: {why}")   # before the arm moved


def test_calibrate_with_the_camera_following_the_arm_is_consistent(tmp_path: Path) -> None:
    code, doc = _calibrate(tmp_path, CELL, "--strict")
    assert code == 0
    cons = doc["summary"]["plane_consistency"]                        # type: ignore[index]
    assert cons["verdict"] == "consistent" and cons["n_poses"] == 8
    assert cons["orientation_span_deg"] == pytest.approx(180.0, abs=1.0)  # four sides: a real check on the mount
    assert cons["normal_spread_deg"] < cons["normal_tolerance_deg"]
    # the consensus holds [reference] within its 95 % interval: the sim arm's kinematic errors (about
    # 0.05 deg, [sim.arm_errors]) tilt it by hundredths of a degree, and the interval says so
    interval = cons["consensus_interval"]
    assert cons["reference"]["angle_deg"] < interval["normal_halfwidth_deg"] < 0.2
    assert abs(cons["reference"]["height_m"]) < interval["height_halfwidth_m"]


def test_a_camera_that_ignores_the_arm_is_named(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    static = tmp_path / "static.toml"
    static.write_text(CELL.read_text().replace("noise_m = 0.001", "noise_m = 0.001\nfollow_arm = false\n"
                                                                  "plane_distance_m = 0.5"))
    # the fit looks for the plane where [reference] and [mount] put it: a camera that ignores the arm
    # shows it elsewhere, and the first pose stops the run naming the gate (there is no second view yet)
    assert main(["calibrate", "--config", str(static), "--out", str(tmp_path / "first"), "--quiet"]) == 1
    assert "expected_plane" in capsys.readouterr().err
    # without that search the second pose stops it: the arm moved and turned, the view stayed (ADR 0045)
    blind = tmp_path / "blind.toml"
    blind.write_text(static.read_text().replace("[reference]", "[reference]\nsearch = false", 1))
    assert main(["calibrate", "--config", str(blind), "--out", str(tmp_path / "out"), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("cellcal: error: quality gate 'view_follows_arm' failed: ")
    assert "the camera's view did not change while the arm moved 0.199 m and turned 90.0 deg between poses 1 and 2" \
        in err and "the camera is not on the arm that moves" in err
    assert not (tmp_path / "out" / "result.json").exists()
