"""``cellcal export --ros2`` on crafted files: one line and exit 2, never a traceback (issue #31)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from cellcal.core.cli import main


@pytest.mark.parametrize(("mount", "says"), [
    ({"translation_m": [1e308, 0.0, 0.0], "quaternion_xyzw": [0.0, 0.0, 0.0, 1.0]},
     "key 'mount.translation_m': has a component beyond +-10 (got [1e+308, 0.0, 0.0]): not a camera mount"),
    ({"translation_m": [0.0, 0.0, 0.1], "rpy_deg": [0.0, 1e300, 0.0]},
     "key 'mount.rpy_deg': has a component beyond +-360 (got [0.0, 1e+300, 0.0]): not a camera mount"),
])
def test_a_mount_no_camera_has_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                           mount: dict[str, list[float]], says: str) -> None:
    path = tmp_path / "m.json"
    path.write_text(json.dumps({"mount": mount}))
    assert main(["export", "--ros2", str(path)]) == 2
    assert capsys.readouterr() == ("", f"cellcal: error: {path}: {says}\n")


def test_a_value_nested_100000_deep_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "deep.json"
    path.write_text('{"mount": ' + "[" * 100_000 + "]" * 100_000 + "}")
    assert main(["export", "--ros2", str(path)]) == 2
    assert capsys.readouterr() == ("", f"cellcal: error: {path}: not a readable JSON file: nested 100001 levels "
                                       "deep, more than the 64 accepted\n")
