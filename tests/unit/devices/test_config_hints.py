"""An unknown configuration key names the near one ("did you mean") and still lists every key."""

from __future__ import annotations

from pathlib import Path

import pytest

from cellcal.devices import BackendContext, ConfigError
from cellcal.devices.config import parse_section
from cellcal.devices.registry import Registry
from cellcal.sims.camera import SimCameraConfig
from cellcal.sims.world import SimConfig


def _message(exc: pytest.ExceptionInfo[ConfigError]) -> str:
    return str(exc.value)


def test_a_typo_in_a_camera_section_names_the_near_key() -> None:
    with pytest.raises(ConfigError) as info:
        Registry().create("camera", {"backend": "sim", "frame_rat": 30.0},
                          BackendContext(source="cell.toml", section="camera"))
    message = _message(info)
    assert message.startswith("cell.toml: key 'camera.frame_rat': unknown key; did you mean 'frame_rate_hz'? "
                              "(expected one of: amplitude_at_1m, distortion, ")
    assert message.endswith(", width)") and "\n" not in message
    # every key is still listed, once, in order
    listed = message.split("(expected one of: ")[1].rstrip(")").split(", ")
    assert listed == sorted(SimCameraConfig.__dataclass_fields__)


def test_a_typo_in_a_nested_table_names_the_near_key_of_that_table() -> None:
    with pytest.raises(ConfigError) as info:
        parse_section(SimConfig, {"charuco": {"square_size_m": 0.03}}, where="sim", source="cell.toml")
    assert _message(info) == (
        "cell.toml: key 'sim.charuco.square_size_m': unknown key; did you mean 'square_m'? (expected one of: "
        "center_m, dark_reflectivity, dictionary, light_reflectivity, marker_ratio, on, square_m, squares, "
        "supersample, texture_px_per_square, yaw_deg)")


def test_upper_case_is_a_near_key_too() -> None:
    with pytest.raises(ConfigError, match=r"key 'camera.Frame_Rate_Hz': unknown key; did you mean 'frame_rate_hz'\?"):
        parse_section(SimCameraConfig, {"Frame_Rate_Hz": 30.0}, where="camera", source="cell.toml")


def test_a_key_near_nothing_gets_the_list_without_a_guess() -> None:
    with pytest.raises(ConfigError) as info:
        parse_section(SimConfig, {"charuco": {"zzz": 1}}, where="sim", source="cell.toml")
    assert _message(info) == (
        "cell.toml: key 'sim.charuco.zzz': unknown key; expected one of: center_m, dark_reflectivity, dictionary, "
        "light_reflectivity, marker_ratio, on, square_m, squares, supersample, texture_px_per_square, yaw_deg")


def test_the_cli_prints_the_guess_as_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from cellcal.core.cli import main

    config = tmp_path / "cell.toml"
    packaged = Path(__file__).parents[3] / "configs" / "sim.toml"
    config.write_text(packaged.read_text(encoding="utf-8").replace('[camera]\nbackend = "sim"\n',
                                                                    '[camera]\nbackend = "sim"\nframe_rat = 30\n', 1),
                      encoding="utf-8")
    assert "frame_rat = 30" in config.read_text(encoding="utf-8")
    status = main(["calibrate", "--config", str(config), "--out", str(tmp_path / "out")])
    out, err = capsys.readouterr()
    assert status == 2 and out == ""
    (line,) = err.splitlines()
    assert line.startswith(f"cellcal: error: {config}: key 'camera.frame_rat': unknown key; "
                           "did you mean 'frame_rate_hz'? (expected one of: ")
