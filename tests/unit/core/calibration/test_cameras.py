"""``[[cameras]]``: several cameras in one configuration, each on the flange or fixed, and the one a command runs."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from cellcal.core.calibration.cameras import MAX_CAMERAS, parse_cameras
from cellcal.core.calibration.config import parse_config
from cellcal.core.cli import main
from cellcal.devices.errors import ConfigError
from tests.support.toml_files import write_toml


def arm_camera(name: str = "arm", **extra: Any) -> dict[str, Any]:
    return {"name": name, "on": "flange", "backend": "sim",
            "mount": {"translation_m": [0.0, 0.01, 0.05], "rpy_deg": [0.0, 0.0, 90.0]}, **extra}


def fixed_camera(name: str = "above", **extra: Any) -> dict[str, Any]:
    return {"name": name, "on": "base", "backend": "sim",
            "pose": {"translation_m": [0.4, 0.0, 1.2], "rpy_deg": [180.0, 0.0, 45.0]}, **extra}


REFERENCE = {"plane_point_m": [0.3, 0.0, 0.0], "plane_normal": [0.0, 0.0, 1.0]}


def document(cameras: list[dict[str, Any]], **extra: Any) -> dict[str, Any]:
    return {"cameras": cameras, "arm": {"backend": "sim"}, "reference": REFERENCE, **extra}


def test_one_camera_table_is_one_camera_named_camera_on_the_flange() -> None:
    config = parse_config({"camera": {"backend": "sim"}, "arm": {"backend": "sim"}, "reference": REFERENCE,
                           "mount": {"translation_m": [0.0, 0.0, 0.07]}}, "<x>")
    assert [(c.name, c.on) for c in config.cameras] == [("camera", "flange")]
    assert config.camera_name == "camera"
    assert config.mount.translation_m == (0.0, 0.0, 0.07)


def test_several_cameras_each_with_its_place_and_the_first_on_the_flange_runs() -> None:
    config = parse_config(document([fixed_camera(), arm_camera(), arm_camera("wrist2", width=320)]), "<x>")
    assert [(c.name, c.on) for c in config.cameras] == [("above", "base"), ("arm", "flange"), ("wrist2", "flange")]
    assert config.camera_name == "arm"
    assert config.camera_section == {"backend": "sim"}          # cellcal's keys are not the backend's
    assert config.mount.translation_m == (0.0, 0.01, 0.05) and config.mount.rpy_deg == (0.0, 0.0, 90.0)
    fixed = config.cameras[0].pose_base
    assert fixed is not None
    assert np.allclose(fixed.translation, [0.4, 0.0, 1.2], atol=1e-12)
    # looking straight down: the camera's z axis along the base's -z
    assert math.degrees(math.acos(-fixed.rotation_matrix[2, 2])) == pytest.approx(0.0, abs=1e-5)
    other = parse_config(document([fixed_camera(), arm_camera(), arm_camera("wrist2", width=320)]), "<x>",
                         camera="wrist2")
    assert other.camera_name == "wrist2" and other.camera_section == {"backend": "sim", "width": 320}


@pytest.mark.parametrize(("cameras", "extra", "key", "words"), [
    ([{"on": "flange", "backend": "sim"}], {}, "cameras[0].name", "missing required value"),
    ([arm_camera("a b")], {}, "cameras[0].name", "needs a name"),
    ([arm_camera(on=None)], {}, "cameras[0].on", "expected one of 'flange', 'base'"),
    ([arm_camera(on="ceiling")], {}, "cameras[0].on", "'flange'"),
    ([arm_camera(), arm_camera()], {}, "cameras[1].name", "two cameras are named 'arm'"),
    ([arm_camera(), fixed_camera(pose=None)], {}, "cameras[1].pose", "needs its [cameras.pose]"),
    ([arm_camera(pose={"translation_m": [0, 0, 1], "rpy_deg": [0, 0, 0]})], {}, "cameras[0].pose", "has a"),
    ([arm_camera(), fixed_camera(mount={"translation_m": [0, 0, 0]})], {}, "cameras[1].mount", "not a mount"),
    ([arm_camera(backend=None)], {}, "cameras[0].backend", "backend"),
    ([arm_camera()], {"camera": {"backend": "sim"}}, "cameras", "not both"),
    ([arm_camera()], {"mount": {"translation_m": [0, 0, 0.05]}}, "mount", "its own [cameras.mount]"),
    ([], {}, "cameras", "one or more"),
    ([arm_camera(f"c{i}") for i in range(MAX_CAMERAS + 1)], {}, "cameras", f"at most {MAX_CAMERAS}"),
    ([fixed_camera()], {}, "cameras", "no camera on the flange"),
    ([arm_camera(), fixed_camera(pose={"translation_m": [0, 0, 99], "rpy_deg": [0, 0, 0]})], {},
     "cameras[1].pose.translation_m", "20"),
])
def test_bad_cameras_are_one_line_naming_the_key(cameras: list[dict[str, Any]], extra: dict[str, Any], key: str,
                                                 words: str) -> None:
    with pytest.raises(ConfigError) as err:
        parse_config(document(cameras, **extra), "<cell.toml>")
    message = str(err.value)
    assert "\n" not in message
    assert f"'{key}'" in message and words in message


@pytest.mark.parametrize(("name", "words"), [("nope", "no camera named 'nope'; the cell has: arm, above"),
                                             ("above", "camera 'above' is fixed")])
def test_a_camera_the_command_cannot_run_is_one_line(name: str, words: str) -> None:
    with pytest.raises(ConfigError, match=words):
        parse_config(document([arm_camera(), fixed_camera()]), "<x>", camera=name)
    with pytest.raises(ConfigError, match="the cell has one, 'camera'"):
        parse_config({"camera": {"backend": "sim"}, "arm": {"backend": "sim"}, "reference": REFERENCE}, "<x>",
                     camera="arm")


def test_parse_cameras_keeps_the_backend_table_apart_from_the_place() -> None:
    entries = parse_cameras(document([arm_camera(width=320), fixed_camera(height=200)]), "<x>")
    assert entries[0].table == {"backend": "sim", "width": 320} and entries[0].pose_base is None
    assert entries[1].table == {"backend": "sim", "height": 200} and entries[1].mount is None


def test_calibrate_dry_run_on_a_cell_of_several_cameras_runs_the_first_on_the_flange(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = tmp_path / "cell.toml"
    config.write_text("""
[[cameras]]
name = "arm"
on = "flange"
backend = "sim"
[cameras.mount]
translation_m = [0.0, 0.0, 0.05]

[[cameras]]
name = "above"
on = "base"
backend = "sim"
[cameras.pose]
translation_m = [0.4, 0.0, 1.2]
rpy_deg = [180.0, 0.0, 0.0]

[arm]
backend = "sim"

[reference]
plane_point_m = [0.3, 0.0, 0.0]
plane_normal = [0.0, 0.0, 1.0]
""")
    assert main(["calibrate", "--config", str(config), "--dry-run"]) == 0
    out = capsys.readouterr()
    assert "dry run OK" in out.out
    assert main(["calibrate", "--config", str(config), "--camera", "above", "--dry-run"]) == 2   # configuration error
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "camera 'above' is fixed" in err[0]


THREE_CAMERAS = """
[arm]
backend = "sim"
[reference]
plane_point_m = [0.3, 0.0, 0.0]
plane_normal = [0.0, 0.0, 1.0]
[[cameras]]
name = "wrist"
on = "flange"
backend = "sim"
mount = { translation_m = [0.0, 0.01, 0.05], rpy_deg = [0.0, 0.0, 90.0] }
[[cameras]]
name = "above"
on = "base"
backend = "sim"
pose = { translation_m = [0.4, 0.0, 1.2], rpy_deg = [180.0, 0.0, 45.0] }
[[cameras]]
name = "side"
on = "base"
backend = "sim"
pose = { translation_m = [0.4, 0.6, 0.8], rpy_deg = [135.0, 0.0, 0.0] }
"""


def test_load_every_camera_reads_the_file_once_and_gives_each_camera_its_configuration(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from cellcal.core.calibration import config as config_module

    path = tmp_path / "cell.toml"
    path.write_text(THREE_CAMERAS)
    reads: list[object] = []
    real_read = config_module.read_config_text

    def counted(p: Any) -> tuple[str, str]:
        reads.append(p)
        return real_read(p)

    monkeypatch.setattr(config_module, "read_config_text", counted)
    configs = config_module.load_every_camera(path)
    assert len(reads) == 1
    assert [(c.camera_name, c.camera_key, c.camera_entry.on) for c in configs] == [
        ("wrist", "cameras[0]", "flange"), ("above", "cameras[1]", "base"), ("side", "cameras[2]", "base")]
    assert configs[0].mount.translation_m == (0.0, 0.01, 0.05)  # the flange camera's own [cameras.mount]


def test_load_every_camera_of_one_camera_table_is_that_camera(tmp_path: Path) -> None:
    from cellcal.core.calibration.config import load_every_camera

    path = write_toml(tmp_path / "cell.toml", {"camera": {"backend": "sim"}, "arm": {"backend": "sim"},
                                               "reference": REFERENCE})
    assert [c.camera_name for c in load_every_camera(path)] == ["camera"]
