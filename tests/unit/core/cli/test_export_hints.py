"""``cellcal export --ros2`` says when the mount it exports is the configured one, not an estimate."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from defusedxml import ElementTree

from cellcal.core.cli import main
from cellcal.devices.pose import Pose

CONFIGURED = Pose.from_xyz_rpy([0.0, 0.04, 0.06], np.radians([0.0, 0.0, 90.0]))
ESTIMATED = Pose.from_xyz_rpy([0.0012, 0.0391, 0.0604], np.radians([0.21, -0.13, 90.07]))
NOTE = ("this mount is the configured [mount] of configs/sim.toml, exported unchanged: nothing estimated it "
        "(estimate it with 'cellcal handeye', set [mount] from_handeye to its handeye.json, calibrate again)")


def _result(mount_table: dict[str, Any], mount: Pose) -> dict[str, Any]:
    """A ``cellcal calibrate`` result.json as the calibrator writes it (schema, configuration, mount)."""
    return {"schema": "cellcal.calibration/2", "config_source": "configs/sim.toml",
            "config": {"cell": {"name": "paper-sim"}, "mount": mount_table}, "mount": mount.to_dict(), "poses": []}


def _export(tmp_path: Path, document: dict[str, Any], capsys: pytest.CaptureFixture[str]) -> tuple[str, str]:
    path = tmp_path / "result.json"
    path.write_text(json.dumps(document), encoding="utf-8")
    assert main(["export", "--ros2", str(path)]) == 0
    captured = capsys.readouterr()
    return captured.out, captured.err


def test_a_configured_mount_is_said_on_stderr_and_in_both_texts(tmp_path: Path,
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    table = {"translation_m": [0.0, 0.04, 0.06], "rpy_deg": [0.0, 0.0, 90.0]}
    out, err = _export(tmp_path, _result(table, CONFIGURED), capsys)
    assert err == f"cellcal export: note: {NOTE}\n"
    launch, urdf = out[:out.index("<!-- URDF")], out[out.index("<!-- URDF"):]
    assert f"\n# NOTE: {NOTE}\n" in launch
    compile(launch, "launch.py", "exec")                    # still a valid launch file
    assert f"<!-- NOTE: {NOTE} -->\n<joint " in urdf
    origin = ElementTree.fromstring(urdf[urdf.index("<joint"):]).find("origin")
    assert np.allclose([float(v) for v in origin.get("xyz").split()], [0.0, 0.04, 0.06], atol=1e-15)
    assert np.allclose([float(v) for v in origin.get("rpy").split()], [0.0, 0.0, np.pi / 2], atol=1e-12)


def test_a_mount_from_a_hand_eye_estimate_has_no_note(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out, err = _export(tmp_path, _result({"from_handeye": "out/handeye.json"}, ESTIMATED), capsys)
    assert err == "" and "NOTE" not in out
    assert '"--x", "0.0012"' in out


def test_a_hand_eye_file_is_an_estimate(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    document = {"schema": "cellcal.handeye/1", "method": "plane",
                "mount": {"translation_m": [0.0012, 0.0391, 0.0604], "rpy_deg": [0.21, -0.13, 90.07]}}
    out, err = _export(tmp_path, document, capsys)
    assert err == "" and "NOTE" not in out


def test_a_configuration_path_cannot_break_the_comments(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    document = _result({"translation_m": [0.0, 0.04, 0.06], "rpy_deg": [0.0, 0.0, 90.0]}, CONFIGURED)
    document["config_source"] = "cells/a--b\n-->.toml"
    out, err = _export(tmp_path, document, capsys)
    assert len(err.splitlines()) == 1
    urdf = out[out.index("<!-- URDF"):]
    assert "<!-- NOTE: this mount is the configured [mount] of cells/a- -b?- ->.toml, exported unchanged" in urdf
    ElementTree.fromstring(f"<robot>{urdf}</robot>")       # the comments stay well-formed XML
    compile(out[:out.index("<!-- URDF")], "launch.py", "exec")
