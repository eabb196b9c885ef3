"""A ``[camera.model]`` table in a cell's config: absurd values are one line naming the key, a valid one
replaces the backend's own model and reaches every frame of the cell built from that config."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

import pytest

from cellcal.core.calibration.calibrator import build_devices
from cellcal.core.calibration.config import load_config
from cellcal.core.cli import main
from cellcal.devices.errors import ConfigError

SIM_TOML = resources.files("cellcal.configs").joinpath("sim.toml").read_text()


def cell_with_model(tmp_path: Path, table: str) -> Path:
    """The packaged sim cell with a ``[camera.model]`` table (TOML lines) after its ``[camera]`` table."""
    assert SIM_TOML.count("\n[arm]") == 1
    path = tmp_path / "cell.toml"
    path.write_text(SIM_TOML.replace("\n[arm]", f"\n[camera.model]\n{table}\n\n[arm]"))
    return path


@pytest.mark.parametrize(("table", "key", "expected"), [
    ('kind = "stereo"\nbaseline_m = 0\nfocal_px = 440.0', "camera.model.baseline_m", "must be > 0.0, got 0.0"),
    ('kind = "stereo"\nbaseline_m = 0.075\nfocal_px = 440.0\nsubpixel_bits = -1', "camera.model.subpixel_bits",
     "must be >= 0, got -1"),
    ('kind = "stereo"\nbaseline_m = 0.075\nfocal_px = 440.0\nbaseline_mm = 75', "camera.model.baseline_mm",
     "unknown key"),
    ('kind = "stereo"\nfocal_px = 440.0', "camera.model.baseline_m", "a stereo model needs baseline_m"),
])
def test_an_absurd_model_is_one_line_naming_the_key(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                     table: str, key: str, expected: str) -> None:
    path = cell_with_model(tmp_path, table)
    assert main(["calibrate", "--check", "--config", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert err.startswith(f"cellcal: error: {path}: key '{key}': ") and expected in err
    with pytest.raises(ConfigError) as exc:                          # the same error from the library
        build_devices(load_config(path))
    # the same message; a long one (an unknown key's list of the known ones) shortened in its middle
    assert exc.value.key == key and str(exc.value)[:150] in err and str(exc.value)[-60:] in err


def test_a_valid_model_reaches_the_frames_of_a_cell_built_from_the_config(tmp_path: Path) -> None:
    path = cell_with_model(tmp_path, 'kind = "stereo"\nbaseline_m = 0.075\nfocal_px = 440.0\nsubpixel_bits = 3\n'
                                     'disparity_sigma_px = 0.1')
    camera, arm = build_devices(load_config(path))
    own = type(camera)._measurement_model(camera)                    # what the sim states of itself
    with arm, camera:
        frames = [camera.capture(5.0) for _ in range(2)]
    stated = camera.measurement_model
    assert stated.kind == "stereo" and stated.source == "config" and stated != own
    assert stated.fb_px_m == pytest.approx(33.0) and stated.depth_step_m(0.7) == pytest.approx(0.49 / 33.0 / 8.0)
    assert stated.disparity_noise_px == pytest.approx((0.1 ** 2 + 0.125 ** 2 / 12) ** 0.5)
    assert all(f.measurement == stated for f in frames)
