"""``[camera.correction]`` applied to every frame of a run (ADR 0058): the stereo sim of configs/sim_oak.toml."""

from __future__ import annotations

import json
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from cellcal.core.calibration.calibrator import Calibrator, build_devices
from cellcal.core.calibration.config import load_config
from cellcal.core.cli import main
from cellcal.devices.correction import CorrectedCamera, correct_frame, leftover_allowance
from cellcal.devices.systematic import SystematicError

SIM_OAK = resources.files("cellcal.configs").joinpath("sim_oak.toml").read_text()
SIM_TOF = resources.files("cellcal.configs").joinpath("sim.toml").read_text()


def write_cell(tmp_path: Path, correction: SystematicError | None, *, ideal: bool = False,
               file: str = "depthcal.json", base: str = SIM_OAK) -> Path:
    """configs/sim_oak.toml (or ``base``) in ``tmp_path`` with ``[camera.correction] file`` beside it."""
    text = base
    if ideal:   # an ideal camera: no systematic error drawn
        text = text.replace("\n[sim]\n", "\n[sim.systematic]\nenabled = false\n\n[sim]\n")
    if correction is not None:
        text += f'\n[camera.correction]\nfile = "{file}"\n'
        (tmp_path / "depthcal.json").write_text(json.dumps({"schema": "cellcal.depthcal/1",
                                                             "correction": correction.to_dict()}))
    path = tmp_path / "cell.toml"
    path.write_text(text)
    return path


def run(path: Path) -> dict[str, Any]:
    config = load_config(path)
    camera, arm = build_devices(config)
    return Calibrator(config, camera, arm).run()


def height_errors_mm(result: dict[str, Any]) -> np.ndarray:
    return np.array([(p["full_frame"]["height_m"] - p["expected"]["height_m"]) * 1e3 for p in result["poses"]])


def sim_truth(path: Path) -> SystematicError | None:
    """The stereo sim's own systematic error, from a raw frame's metadata (None: the sims draw none yet)."""
    config = load_config(path)
    camera, _ = build_devices(config, apply_correction=False)
    with camera:
        meta = camera.capture().metadata.get("sim_systematic")
    return None if meta is None else SystematicError.from_dict(meta)


def test_a_zero_correction_with_a_covariance_states_its_allowance_in_every_frame(tmp_path: Path) -> None:
    cov = np.diag([1e-6, 0.01 ** 2, 0.02 ** 2, 0.02 ** 2])
    correction = SystematicError("stereo", field_order=1, covariance=cov)
    cell = write_cell(tmp_path, correction)
    config = load_config(cell)
    camera, _ = build_devices(config)
    assert isinstance(camera, CorrectedCamera)
    want = leftover_allowance(correction)
    assert want == pytest.approx((1e-3, 0.01, 0.02 * 2 ** 0.5))   # field: b = (±1, ±1) at the corners
    with camera:
        frame = camera.capture()
        raw = camera.raw_capture()
    assert frame.measurement.allowance == pytest.approx(want)
    assert camera.measurement_model.allowance == pytest.approx(want)
    assert frame.metadata["depth_correction"]["applied"] and "depth_correction" not in raw.metadata
    # a zero correction moves no point (to float32 precision)
    again = correct_frame(raw, correction)
    assert np.array_equal(again.valid, raw.valid) and again.valid.mean() > 0.9
    assert np.allclose(again.xyz[raw.valid], raw.xyz[raw.valid], rtol=1e-6, atol=0)


@pytest.mark.parametrize("base", [SIM_OAK, SIM_TOF], ids=["stereo", "tof"])
def test_the_true_correction_brings_the_heights_to_the_ideal_cameras(tmp_path: Path, base: str) -> None:
    """With the sim's own systematic error removed, calibrate's heights are the ideal camera's (same seed)."""
    raw_cell = write_cell(tmp_path, None, base=base)
    truth = sim_truth(raw_cell)
    if truth is None or truth.is_zero:
        pytest.skip("the sim draws no systematic error ([sim.systematic], engineer A)")
    k = len(truth.names)
    exact = SystematicError.from_vector(truth.kind, truth.vector, field_order=truth.field_order,
                                        wiggle_period_m=truth.wiggle_period_m, covariance=np.zeros((k, k)))
    (tmp_path / "ideal").mkdir()
    (tmp_path / "fixed").mkdir()
    uncorrected = height_errors_mm(run(raw_cell))
    ideal = height_errors_mm(run(write_cell(tmp_path / "ideal", None, ideal=True, base=base)))
    corrected = height_errors_mm(run(write_cell(tmp_path / "fixed", exact, base=base)))
    # measured (seed 7): stereo uncorrected -3.8, -5.4, -5.6 mm, corrected and ideal -0.18, -0.17, -0.11 mm
    # (equal to 2 um: the rounding of corrected disparities is not the ideal camera's); ToF uncorrected
    # +3.6, +4.3, +4.4 mm, corrected and ideal -0.18, -0.19, -0.11 mm (equal to 3 um)
    assert np.abs(uncorrected - ideal).min() > 2.0
    assert np.abs(corrected - ideal).max() < 0.02


def test_check_names_the_correction_and_refuses_a_bad_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]
                                                           ) -> None:
    cell = write_cell(tmp_path, SystematicError("stereo"))
    assert main(["calibrate", "--check", "--config", str(cell)]) == 0
    out = capsys.readouterr().out
    assert f"correction: {tmp_path / 'depthcal.json'}: stereo, field order 0" in out
    assert "camera:  backend 'sim'" in out and "SimStereoCamera" in out
    (tmp_path / "depthcal.json").write_text('{"schema": "cellcal.depthcal/1", "correction": {"kind": "stereo", '
                                            '"fb_error": 0.9}}')
    assert main(["calibrate", "--check", "--config", str(cell)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "key 'camera.correction.file'" in err and "correction.fb_error" in err
    (tmp_path / "depthcal.json").unlink()
    assert main(["calibrate", "--check", "--config", str(cell)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "key 'camera.correction.file'" in err and "file not found" in err
