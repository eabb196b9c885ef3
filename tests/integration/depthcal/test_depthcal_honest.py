"""depthcal on the shipped ToF sim: the truth inside the intervals, with the arm's accuracy and the unfitted field.

The sim's truth (``[sim.systematic]`` defaults, ADR 0054): range scale +0.1 %, offset +3 mm, a 1 mm
wiggle at 0.6246 m, a 1 mm radial bow; the sim arm errs by 0.48 mm / 0.049 deg RMS (ADR 0055).
"""

from __future__ import annotations

from typing import Any

import pytest
from repo_paths import REPO_ROOT

from cellcal.core.calibration.calibrator import build_devices
from cellcal.core.calibration.config import load_config
from cellcal.core.depthcal.fit import fit_depthcal
from cellcal.core.depthcal.plan import depthcal_plan
from cellcal.core.depthcal.run import DepthcalCalibrator, raw_camera, run_depthcal
from cellcal.sims.systematic import SystematicConfig

Z95 = 1.959963984540054


@pytest.fixture(scope="module")
def measured(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict[str, Any], list[Any], Any]:
    """One depthcal run of configs/sim.toml: its document, its views and the config."""
    out = tmp_path_factory.mktemp("depthcal")
    config = load_config(REPO_ROOT / "configs" / "sim.toml")
    camera, arm = build_devices(config)
    calibrator = DepthcalCalibrator(config, raw_camera(camera), arm, depthcal_plan(config), out / "frames")
    document, _, views = run_depthcal(calibrator, out)
    return document, views, config


def test_the_truth_is_inside_the_intervals_and_the_notes_say_why(measured: tuple[dict[str, Any], list[Any], Any]
                                                                 ) -> None:
    document, _, _ = measured
    truth = SystematicConfig()
    corr, sigma = document["correction"], document["correction_sigma"]
    assert corr["wiggle_period_m"] == pytest.approx(truth.wiggle_period_m, rel=1e-9)  # fitted by default
    # scale +0.22 +- 0.24 % (truth 0.1), offset +0.6 +- 5.7 mm (truth 3): about half a half-width off each
    assert abs(corr["scale_error"] - truth.range_scale_error) < 0.7 * Z95 * sigma["scale_error"]
    assert abs(corr["offset_m"] - truth.range_offset_m) < 0.7 * Z95 * sigma["offset_m"]
    notes = " ".join(document["notes"])
    assert "the arm's stated accuracy (0.477 mm" in notes and "field allowance is in the intervals" in notes


def test_without_the_arm_and_the_field_the_same_views_were_confidently_wrong(
        measured: tuple[dict[str, Any], list[Any], Any]) -> None:
    document, views, config = measured
    dc = config.depthcal
    bare = fit_depthcal(views, mount=config.mount.pose(), model=views[0].frame.measurement,
                        field_orders=(2,), holdout_every=dc.holdout_every,   # the field fitted: none left over
                        max_points_per_view=dc.max_points_per_view, wiggle_period_m=SystematicConfig().wiggle_period_m,
                        seed=config.cell.seed).to_dict()
    truth = SystematicConfig()
    # the reported flanges as exact: the scale's interval shrinks several-fold and misses the truth
    assert bare["correction_sigma"]["scale_error"] < document["correction_sigma"]["scale_error"] / 3
    assert abs(bare["correction"]["scale_error"] - truth.range_scale_error) > 2 * Z95 * bare["correction_sigma"][
        "scale_error"]
