"""``cellcal handeye --camera NAME`` for a fixed camera of configs/sim_multi.toml: the arm shows it the plate.

The sim's true poses of the fixed cameras ([[sim.cameras]]) differ from the configured ones by a few mm
and tenths of a degree; the run must find them within its 95 % intervals, refuse what it cannot do
before anything moves, and leave a valid result file.
"""

from __future__ import annotations

import json
import math
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from cellcal.core.cli import main
from cellcal.devices.pose import Pose

REPO = Path(__file__).resolve().parents[3]
MULTI = REPO / "configs" / "sim_multi.toml"


def truth(name: str) -> Pose:
    """The true T_base_camera of a fixed camera of configs/sim_multi.toml."""
    document = tomllib.loads(MULTI.read_text(encoding="utf-8"))
    entry = next(e for e in document["sim"]["cameras"] if e["name"] == name)
    return Pose.from_xyz_rpy(entry["translation_m"], np.radians(entry["rpy_deg"]))


def variant(tmp_path: Path, **plate: Any) -> Path:
    """configs/sim_multi.toml with ``[plate]`` keys replaced."""
    text = MULTI.read_text(encoding="utf-8")
    lines = "".join(f"{k} = {json.dumps(v)}\n" for k, v in plate.items())
    out = tmp_path / "cell.toml"
    out.write_text(text.replace("[plate]\n", "[plate]\n" + lines, 1) if "[plate]\n" in text
                   else text + "\n[plate]\n" + lines, encoding="utf-8")
    return out


@pytest.fixture(scope="module")
def above_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("fixed")
    assert main(["handeye", "--config", str(MULTI), "--camera", "above", "--out", str(out), "--quiet"]) == 0
    return out / "handeye-above.json"


@pytest.fixture(scope="module")
def above(above_path: Path) -> dict[str, Any]:
    document: dict[str, Any] = json.loads(above_path.read_text(encoding="utf-8"))
    return document


def test_the_fixed_camera_is_found_within_its_intervals(above: dict[str, Any]) -> None:
    assert above["schema"] == "cellcal.handeye-fixed/1" and above["camera"] == "above" and above["on"] == "base"
    found, true = Pose.from_dict(above["camera_base"]), truth("above")
    half = above["half_widths"]
    err_t = found.translation - true.translation
    # the truth is 3-4 mm and 0.3-0.4 deg from the configured pose; measured errors 0.7-4.6 mm against half-widths
    # of 2.4-10 mm (tz is the plate's offset's twin), the turn 0.08 deg against 0.17-0.31 deg
    for axis, e in zip("xyz", err_t, strict=True):
        assert abs(e) <= half[f"t{axis}"], f"t{axis}: {1000 * e:.2f} mm outside +-{1000 * half[f't{axis}']:.2f} mm"
    turn = (found @ true.inv()).as_xyz_rotvec()[3:]            # the error as a turn about the base axes
    for k, e in zip(("rot_x", "rot_y", "rot_z"), turn, strict=True):
        assert abs(e) <= half[k], f"{k}: {math.degrees(e):.3f} deg outside +-{math.degrees(half[k]):.3f} deg"
    assert found.distance_to(true) < 0.015 and math.degrees(found.angle_to(true)) < 0.3
    configured = Pose.from_dict(above["configured_camera_base"])
    assert found.distance_to(true) < configured.distance_to(true) + 0.005


def test_the_noise_model_holds_and_the_notes_say_what_the_intervals_rest_on(above: dict[str, Any]) -> None:
    # measured chi2/dof 1.00 over 66 dof with the systematic terms common to the views
    assert 0.5 < above["noise_model"]["chi2_per_dof"] < 2.0
    notes = " ".join(above["notes"])
    assert "common to the views" in notes and "arm's accuracy" in notes
    assert len(above["residuals"]) == len(above["commanded_flange_poses"]) >= 12


def test_dry_run_lists_every_move_and_what_the_plan_sees(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["handeye", "--config", str(MULTI), "--camera", "above", "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "fixed camera 'above'" in out and "nothing moves" in out
    assert out.count("\nmove ") >= 12
    assert "observability: all 9 parameters observable" in out and "dry run OK" in out


@pytest.mark.parametrize(("args", "plate", "words"), [
    (["--method", "charuco", "--resume"], {}, "work with --method plane only"),
    (["--plan", "config"], {}, "camera 'above' is fixed"),
    ([], {"size_m": [0.01, 0.01]}, "outside camera 'above''s view at every pose"),
    ([], {"distance_m": 4.0}, "breaks the envelope"),
])
def test_what_the_fixed_run_cannot_do_is_one_line_before_anything_moves(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], plate: dict[str, Any],
        words: str) -> None:
    config = variant(tmp_path, **plate) if plate else MULTI
    code = main(["handeye", "--config", str(config), "--camera", "above", "--out", str(tmp_path / "out"), *args])
    assert code in (1, 2)
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and words in err[0]
    assert not (tmp_path / "out" / "handeye-above.json").exists()


def test_export_writes_every_camera_under_its_parent(above_path: Path, tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "wrist"
    assert main(["calibrate", "--config", str(MULTI), "--no-report", "--out", str(out)]) == 0
    capsys.readouterr()
    assert main(["export", "--ros2", str(out / "result.json"), str(above_path)]) == 0
    text = capsys.readouterr().out
    assert text.count('executable="static_transform_publisher"') == 2
    assert 'name="cellcal_camera"' in text and 'name="cellcal_above"' in text
    assert '"--frame-id", "flange", "--child-frame-id", "camera"' in text
    assert '"--frame-id", "base_link", "--child-frame-id", "above"' in text
    compile(text.split("<!-- URDF")[0], "launch.py", "exec")          # one launch file, valid Python
    found = Pose.from_dict(json.loads(above_path.read_text(encoding="utf-8"))["camera_base"])
    joint = text.split("<!-- URDF fixed joint: base_link -> above -->")[1]
    xyz = [float(v) for v in joint.split('xyz="')[1].split('"')[0].split()]
    assert np.allclose(xyz, found.translation, atol=1e-12)


def test_export_refuses_two_files_for_one_camera_frame(above_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["export", "--ros2", str(above_path), str(above_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "two files give camera frame 'above'" in err[0]


@pytest.fixture(scope="module")
def cell_results(above_path: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The hand-eye results of the three cameras of configs/sim_multi.toml (the wrist's, above's, side45's)."""
    out = above_path.parent
    assert main(["handeye", "--config", str(MULTI), "--out", str(out), "--quiet", "--no-report"]) == 0
    assert main(["handeye", "--config", str(MULTI), "--camera", "side45", "--out", str(out), "--quiet"]) == 0
    return {"wrist": out / "handeye.json", "above": above_path, "side45": out / "handeye-side45.json"}


def test_cameras_relates_the_fixed_pair_within_its_intervals_and_the_planes_agree(
        cell_results: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    capsys.readouterr()
    out = tmp_path / "cameras.json"
    assert main(["cameras", *map(str, cell_results.values()), "--json", str(out)]) == 0
    document = json.loads(out.read_text(encoding="utf-8"))
    assert [c["name"] for c in document["cameras"]] == ["wrist", "above", "side45"]
    (pair,) = document["pairs"]                     # the two fixed cameras; the wrist's changes with the arm
    assert (pair["from"], pair["to"], pair["parent"]) == ("above", "side45", "base")
    true = truth("above").inv() @ truth("side45")
    # measured: the pair 0.3-2.6 mm and 0.1 deg from the truth, half-widths 3.8-14 mm and 0.4-0.5 deg
    err = np.asarray(pair["translation_m"]) - true.translation
    assert np.all(np.abs(err) <= np.asarray(pair["translation_half_width_m"]))
    agreement = document["plane_agreement"]
    assert agreement["agree"] and agreement["cameras"] == ["above", "side45", "wrist"]
    assert agreement["p_value"] > 0.05                  # measured 0.94
    assert "agree" in capsys.readouterr().out


def test_cameras_names_the_camera_whose_plane_disagrees(cell_results: dict[str, Path], tmp_path: Path,
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    moved = json.loads(cell_results["side45"].read_text(encoding="utf-8"))
    moved["measuring_plane"]["plane_base"]["offset_m"] -= 0.08   # its table 80 mm off: 10 of its sigmas
    path = tmp_path / "handeye-side45.json"
    path.write_text(json.dumps(moved), encoding="utf-8")
    capsys.readouterr()
    assert main(["cameras", str(cell_results["wrist"]), str(cell_results["above"]), str(path)]) == 1
    assert "camera 'side45' disagrees" in capsys.readouterr().out
    assert main(["cameras", str(cell_results["above"]), str(cell_results["above"])]) == 2
    assert "two results for camera 'above'" in capsys.readouterr().err
