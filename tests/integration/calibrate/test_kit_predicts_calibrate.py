"""Issue #37: what `cellcal calibrate` refuses, the conformance kit and `calibrate --check` refuse first, in its words.

The user's case: a 64 x 48 camera passed the kit's 15 rules and `--check` said "config OK"; the run
then stopped on "perimeter 30 px puts points outside the 64x48 image". Here that camera is the
simulated one with a 64 x 48 image and the packaged sim.toml's plan (perimeters 20-50 px).
"""

from __future__ import annotations

import tomllib
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from toml_files import write_toml

from cellcal.core.calibration.calibrator import Calibrator, build_devices
from cellcal.core.calibration.config import parse_config
from cellcal.core.cli import main
from cellcal.devices import BackendContext, Camera3D, default_registry
from cellcal.devices.errors import ConfigError
from cellcal.testing import CAMERA_RULES, CameraOptions, ScenePlane, check_camera

SIM_TOML = resources.files("cellcal.configs").joinpath("sim.toml").read_text()
SIM_DOC: dict[str, Any] = tomllib.loads(SIM_TOML)
#: The sim camera with no plan sees the table straight below it, 0.44 m away.
OPTIONS = CameraOptions(distance_range_m=(0.1, 4.0), scene_plane=ScenePlane((0.0, 0.0, 1.0), 0.44))
#: Why calibrate refuses the 64 x 48 camera with the default plan: the grid's reach from the principal point
#: (31.5, 23.5) px is 23.5 px to the top and bottom edges, less one pixel of the 3 px sampling window.
TOO_SMALL = ("perimeters 30, 40, 50 px put the P1-P9 grid with its 3 px sampling windows outside the 64x48 image "
             "(at most 22.5 px from the principal point (31.5, 23.5) px); use perimeters_px of at most 22 px")


def small_document(**camera: Any) -> dict[str, Any]:
    """sim.toml with a 64 x 48 px camera (the field of view of the default one) and ``camera`` keys."""
    return {**SIM_DOC, "camera": {**SIM_DOC["camera"], "width": 64, "height": 48, **camera}}


def camera_factory(doc: dict[str, Any]) -> Any:
    def make() -> Camera3D:
        context = BackendContext(source="<small.toml>", section="camera", document=doc, shared={}, seed=3)
        return default_registry().create_camera(doc["camera"], context)

    return make


def test_the_kit_fails_the_small_camera_by_calibrates_own_words() -> None:
    report = check_camera(camera_factory(small_document()), OPTIONS, raise_on_failure=False, quiet=True)
    (failure,) = report.failures
    assert failure.rule == "camera.calibrate-image"
    assert failure.detail == ("`cellcal calibrate` with [plan] perimeters_px = [20, 30, 40, 50], window_px = 3 "
                              f"refuses this camera before the arm moves: {TOO_SMALL}")
    # every rule the kit had before issue #37 passes: the 15/15 the user saw
    passed = [r.rule for r in report.results if r.passed]
    assert passed == [r for r in CAMERA_RULES if r != "camera.calibrate-image"] and len(passed) == 16


def test_check_and_calibrate_refuse_it_in_one_line_before_the_arm_moves(tmp_path: Path,
                                                                       capsys: pytest.CaptureFixture[str]) -> None:
    path = write_toml(tmp_path / "small.toml", small_document())
    why = f"cellcal: error: {path}: key 'plan.perimeters_px': {TOO_SMALL}\n"
    assert main(["calibrate", "--check", "--config", str(path)]) == 2
    captured = capsys.readouterr()
    assert captured.err == why and "config OK" not in captured.out
    assert main(["calibrate", "--config", str(path), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    assert capsys.readouterr().err.startswith(why)
    assert not (tmp_path / "out" / "result.json").exists()
    # the perimeters the message names as fitting: --check says so and shows the image it judged
    fits = write_toml(tmp_path / "fits.toml", {**small_document(), "plan": {**SIM_DOC["plan"], "perimeters_px": [22]}})
    assert main(["calibrate", "--check", "--config", str(fits)]) == 0
    out = capsys.readouterr().out
    assert "image:   64x48 px (from the configuration) holds the grid at perimeters 22 px with 3 px windows (up " \
           "to 22.5 px)\nconfig OK (no device was touched)\n" in out


def test_the_run_refuses_before_the_first_move() -> None:
    config = parse_config(small_document(), "<small.toml>")
    camera, arm = build_devices(config)
    start = arm.inner.true_flange_pose()                                  # type: ignore[attr-defined]
    with pytest.raises(ConfigError) as info:
        Calibrator(config, camera, arm).run()
    assert str(info.value) == f"<small.toml>: key 'plan.perimeters_px': {TOO_SMALL}"
    after = arm.inner.true_flange_pose()                                  # type: ignore[attr-defined]
    assert np.array_equal(after.translation, start.translation)           # not a step: no move was made
    assert np.array_equal(after.rotation_matrix, start.rotation_matrix)


def test_a_camera_stating_more_noise_than_it_has_fails_the_kit_and_calibrate_on_the_same_gate(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A noise-free sim whose [camera.model] states 10 mm at 1 m: its frames are 'too good' for that model."""
    camera = '[camera]\nbackend = "sim"\n'
    assert SIM_TOML.count(camera) == 1
    loud = tmp_path / "loud.toml"
    loud.write_text(SIM_TOML.replace(camera, camera + 'noise = false\n\n[camera.model]\nkind = "tof"\n'
                                                      'sigma_at_1m_m = 0.01\nrange_step_m = 0.001\n'))
    doc = tomllib.loads(loud.read_text())
    report = check_camera(camera_factory(doc), OPTIONS, raise_on_failure=False, quiet=True)
    (failure,) = report.failures
    assert failure.rule == "camera.calibrate-frames"
    kit = failure.detail.removeprefix("`cellcal calibrate` with the default [full_frame] gates refuses frame #0 of "
                                      "the test scene: ")
    assert kit.startswith("quality gate 'residual_floor' failed: ")
    assert main(["calibrate", "--config", str(loud), "--out", str(tmp_path / "out"), "--quiet"]) == 1
    run = capsys.readouterr().err
    assert run.startswith("cellcal: error: quality gate 'residual_floor' failed: ") and "plan pose 1: " in run
    # the same explanation, in the same words (the numbers are the kit scene's, 0.44 m straight down, and the first
    # pose's, 0.46 m at 80 deg: 0.085 and 0.079 x the stated noise, over a floor of 0.268 and 0.264 mm)
    for words in (" mm the sensor can deliver for these pixels (quantisation floor 0.26",
                  " mm), below the minimum of 0.25 x: too good to be a measurement of this sensor (a fit on one "
                  "quantisation level, or the wrong model)"):
        assert words in kit and words in run
