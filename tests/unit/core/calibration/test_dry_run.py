"""``cellcal calibrate --dry-run``: every move with its checks; nothing connected, nothing moved."""

from __future__ import annotations

import itertools
import math
import re
from importlib import resources
from pathlib import Path

import numpy as np
import pytest
from fault_cells import cell_document
from toml_files import write_toml

from cellcal.core.calibration.config import parse_config, plan_flange_poses
from cellcal.core.calibration.dryrun import check_moves, dry_run
from cellcal.core.cli import main

MOVE = re.compile(r"^move (\d+)/(\d+): xyz=\(([-\d.]+), ([-\d.]+), ([-\d.]+)\) m "
                  r"rpy=\(([-\d.]+), ([-\d.]+), ([-\d.]+)\) deg; path (\S+)")


def test_dry_run_prints_every_move_with_its_checks(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["calibrate", "--dry-run"]) == 0
    lines = capsys.readouterr().out.splitlines()
    moves = [MOVE.match(line) for line in lines if line.startswith("move ")]
    config = parse_config(cell_document(plan={"perimeters_px": [20]}), "<x>")
    poses = plan_flange_poses(config)
    assert len(moves) == len(poses) == 3
    for i, (m, pose) in enumerate(zip(moves, poses, strict=True)):
        assert m is not None and int(m.group(1)) == i + 1 and int(m.group(2)) == 3
        xyz = [float(m.group(k)) for k in (3, 4, 5)]
        rpy = [float(m.group(k)) for k in (6, 7, 8)]
        assert np.allclose(xyz, pose.translation, atol=5e-5)
        assert np.allclose(rpy, np.degrees(pose.rotation.as_euler("xyz")), atol=5e-3)
        if i == 0:
            assert m.group(9) == "n/a"  # no arm connected: the start pose is unknown
        else:
            assert float(m.group(9)) == pytest.approx(np.linalg.norm(pose.translation - poses[i - 1].translation),
                                                      abs=5e-5)
    for line in lines[1:4]:
        assert "workspace ok" in line and "standoff ok" in line and "speed ok (0.3 <= 0.5 m/s)" in line
        assert "acceleration ok (1.5 <= 2 m/s^2)" in line
    assert lines[-1] == "dry run OK: all 3 moves inside the safety envelope"


@pytest.mark.parametrize("name", ["ur_o3r.toml", "ur_oak.toml"])
def test_dry_run_touches_no_device(name: str, capsys: pytest.CaptureFixture[str]) -> None:
    # real-device cells with nothing at their addresses: a dry run still lists every move
    path = resources.files("cellcal.configs").joinpath(name)
    assert main(["calibrate", "--dry-run", "--config", str(path)]) == 0
    out = capsys.readouterr().out
    assert "no device is connected, nothing moves" in out and out.rstrip().endswith("inside the safety envelope")


def test_standoff_figure_is_the_closest_camera_approach() -> None:
    config = parse_config(cell_document(), "<x>")
    poses = plan_flange_poses(config)
    limits = config.safety_limits()
    checks = check_moves(limits, poses, 0.3, 1.5)
    assert all(c.ok for c in checks)
    for c in checks[:1]:
        camera = c.target @ limits.mount
        assert c.min_standoff_m == pytest.approx(camera.translation[2], abs=1e-12)  # plane z = 0, normal +z
    for prev, c in itertools.pairwise(checks):
        ends = min((p.target @ limits.mount).translation[2] for p in (prev, c))
        assert c.min_standoff_m is not None and c.min_standoff_m <= ends + 1e-12


def test_violating_plan_names_the_pose_and_exits_1(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # pose 2 puts the camera 0.1 m above the plane, under the 0.2 m standoff
    down = [180.0, 0.0, 0.0]
    doc = cell_document(plan={"poses": [{"xyz_m": [0.3, 0.0, 0.6], "rpy_deg": down},
                                        {"xyz_m": [0.3, 0.0, 0.16], "rpy_deg": down},
                                        {"xyz_m": [0.3, 0.1, 0.6], "rpy_deg": down}]})
    config = write_toml(tmp_path / "bad.toml", doc)
    assert main(["calibrate", "--dry-run", "--config", str(config)]) == 1
    captured = capsys.readouterr()
    lines = captured.out.splitlines()
    assert lines[1].startswith("move 1/3") and "checks:" in lines[1]
    assert lines[2].startswith("move 2/3") and "REJECTED" in lines[2] and "min standoff 0.2000 m" in lines[2]
    assert not any(line.startswith("move 3/3") for line in lines)  # stops at the offending pose
    assert captured.err.count("\n") == 1 and "plan pose 2 (xyz=(0.3000, 0.0000, 0.1600) m" in captured.err


def test_dry_run_function_returns_the_checks() -> None:
    out: list[str] = []
    checks = dry_run(parse_config(cell_document(), "<x>"), emit=out.append)
    assert [c.index for c in checks] == [0, 1, 2] and checks[0].path_length_m is None
    assert all(c.path_length_m is not None and c.path_length_m > 0 for c in checks[1:])
    assert len(out) == 5 and math.isfinite(checks[1].min_standoff_m or math.nan)
