"""The accuracy study: CSV, plots, reproducibility, clutter placement, artefact levels, full frame vs the paper, CLI."""

from __future__ import annotations

import csv
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from cellcal.core import study
from cellcal.core.cli import main
from cellcal.core.study import (
    ARTEFACT_LEVELS,
    BASE_ARTEFACTS,
    COLUMNS,
    FULL_FRAME,
    GRID_METHODS,
    Condition,
    StudySettings,
    headline,
    quick_settings,
    read_csv,
    run_study,
    run_trial,
    study_intrinsics,
    summary_table,
    write_csv,
)
from cellcal.devices.errors import CalibrationError, MissingDependencyError

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
TRIALS = 3


@pytest.fixture(scope="module")
def result() -> study.StudyResult:
    return run_study(quick_settings(trials=TRIALS, seed=5))


@pytest.fixture(scope="module")
def intrinsics() -> Any:
    return study_intrinsics(StudySettings())


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, float) and isinstance(b, float):
        return (math.isnan(a) and math.isnan(b)) or a == b
    return bool(a == b)


def _rows_equal(r1: list[dict[str, Any]], r2: list[dict[str, Any]]) -> bool:
    return len(r1) == len(r2) and all(_same(a[c], b[c]) for a, b in zip(r1, r2, strict=True) for c in COLUMNS)


def test_rows_cover_every_method_perimeter_and_trial(result: study.StudyResult) -> None:
    settings = result.settings
    conditions = settings.conditions()
    assert len(conditions) == 6  # 3 heights x (no clutter, 30 %)
    per_trial = len(GRID_METHODS) * len(settings.perimeters_px) + 1
    assert len(result.rows) == len(conditions) * TRIALS * per_trial
    assert result.full_frame_available
    ff = [r for r in result.rows if r["method"] == FULL_FRAME]
    assert len(ff) == len(conditions) * TRIALS
    assert all(r["perimeter_px"] is None for r in ff)
    # truth: the paper's geometry
    for r in result.rows:
        assert r["artefacts"] == BASE_ARTEFACTS  # the quick design: the base ToF artefact level only
        assert r["true_angle_deg"] == pytest.approx(80.0, abs=1e-9)
        assert r["true_tilt_deg"] == pytest.approx(10.0, abs=1e-9)
        assert r["true_height_m"] == pytest.approx(r["height_m"], abs=1e-12)
        if r["ok"]:
            assert r["abs_tilt_error_deg"] == pytest.approx(abs(r["est_tilt_deg"] - r["true_tilt_deg"]), abs=1e-12)
    # full-frame intervals bracket its estimate and are decided for every fit
    for r in ff:
        assert r["ok"], r["message"]
        assert r["ci_lo_deg"] < r["est_tilt_deg"] < r["ci_hi_deg"]
        assert r["ci_contains"] == (r["ci_lo_deg"] <= r["true_tilt_deg"] <= r["ci_hi_deg"])


def test_csv_has_the_columns_and_round_trips(result: study.StudyResult, tmp_path: Path) -> None:
    path = write_csv(tmp_path / "study.csv", result.rows)
    with path.open(newline="") as fh:
        reader = csv.reader(fh)
        header = next(reader)
        body = list(reader)
    assert tuple(header) == COLUMNS
    assert len(body) == len(result.rows)
    assert not list(tmp_path.glob(".*.tmp"))  # atomic write left nothing behind
    back = read_csv(path)
    assert _rows_equal(back, result.rows)


def test_read_csv_rejects_a_foreign_file(tmp_path: Path) -> None:
    p = tmp_path / "x.csv"
    p.write_text("a,b\n1,2\n")
    with pytest.raises(CalibrationError, match="not a study CSV"):
        read_csv(p)


def test_same_seed_same_rows_other_trial_other_noise_and_boxes(intrinsics: Any) -> None:
    settings = quick_settings(trials=1, seed=11)
    fit = study.full_frame_fitter()
    cond = Condition(0.59, 80.0, 1.0, 0.3)
    t1, rows1 = run_trial(settings, cond, 0, intrinsics, fit)
    t2, rows2 = run_trial(settings, cond, 0, intrinsics, fit)
    assert _rows_equal(rows1, rows2)
    assert np.array_equal(t1.frame.distance, t2.frame.distance, equal_nan=True)
    t3, _ = run_trial(settings, cond, 1, intrinsics, fit)
    assert t3.seed != t1.seed
    assert t3.boxes != t1.boxes
    assert not np.array_equal(t3.frame.distance, t1.frame.distance, equal_nan=True)
    # a condition's trials do not depend on the other conditions of the run
    other = StudySettings(trials=1, seed=11)
    _, rows4 = run_trial(other, cond, 0, intrinsics, fit)
    assert _rows_equal(rows1, rows4)


@pytest.mark.parametrize("fraction", [0.1, 0.25, 0.4])
def test_clutter_hits_the_requested_fraction(fraction: float, intrinsics: Any) -> None:
    settings = StudySettings(trials=1, seed=3)
    for index in range(3):
        trial, _ = run_trial(settings, Condition(0.46, 80.0, 1.0, fraction), index, intrinsics, None)
        assert 1 <= len(trial.boxes) <= settings.max_boxes
        assert abs(trial.clutter_achieved - fraction) < 0.02
        # the frame rendered by the sim shows (nearly) the same pixels hidden: the
        # placement's occlusion model agrees with the simulator's ray casting
        assert abs(trial.clutter_observed - trial.clutter_achieved) < 0.02
        assert trial.clutter_observed > 0.5 * fraction


def test_the_design_sweeps_clutter_at_every_artefact_level() -> None:
    settings = StudySettings(trials=2, heights_m=(0.46,), clutter_fractions=(0.0, 0.3))
    conds = settings.conditions()
    sweep = {(c.clutter, c.artefacts) for c in conds if c.inclination_deg == 80.0 and c.noise_scale == 1.0}
    assert sweep == {(c, a) for c in (0.0, 0.3) for a in ARTEFACT_LEVELS}
    # the inclination and noise sweeps run at the base level only, and nothing is run twice
    assert {c.artefacts for c in conds if c.inclination_deg != 80.0 or c.noise_scale != 1.0} == {BASE_ARTEFACTS}
    assert len({c.ident() for c in conds}) == len(conds)
    assert settings.trials_for(Condition(0.46, 80.0, 1.0, 0.3, BASE_ARTEFACTS)) == 2 * settings.headline_factor
    assert settings.trials_for(Condition(0.46, 80.0, 1.0, 0.3, "all")) == 2
    with pytest.raises(CalibrationError, match="artefact levels must be some of off, all-but-multipath, all"):
        StudySettings(artefact_levels=("none",))


def test_artefact_levels_see_the_same_scene_and_noise(intrinsics: Any) -> None:
    settings = StudySettings(trials=1, seed=2)
    trials = {a: run_trial(settings, Condition(0.46, 80.0, 1.0, 0.3, a), 0, intrinsics, None)[0]
              for a in ARTEFACT_LEVELS}
    off, base, full = trials["off"], trials[BASE_ARTEFACTS], trials["all"]
    assert off.seed == base.seed == full.seed and off.boxes == base.boxes == full.boxes  # paired trials
    valid = off.frame.valid & base.frame.valid & full.frame.valid
    d_base = (base.frame.distance - off.frame.distance)[valid]
    d_mp = (full.frame.distance - base.frame.distance)[valid]
    # flying pixels (cm) and the amplitude noise law (mm) change the frame; multipath adds a bias
    assert np.max(np.abs(d_base)) > 0.01 and np.median(np.abs(d_base)) < 0.002
    assert np.mean(d_mp) > 0 and np.percentile(d_mp, 1) > -1e-3
    row = run_trial(settings, Condition(0.46, 80.0, 1.0, 0.3, "all"), 0, intrinsics, None)[1][0]
    assert row["artefacts"] == "all"


def test_headline_and_summary_per_artefact_level() -> None:
    rows = []
    for level, err in (("off", 0.001), (BASE_ARTEFACTS, 0.004), ("all", 0.03)):
        for clutter in (0.0, 0.3):
            for trial in range(4):
                rows.append({"height_m": 0.46, "inclination_deg": 80.0, "noise_scale": 1.0, "clutter_target": clutter,
                             "artefacts": level, "trial": trial, "method": FULL_FRAME, "ok": True,
                             "abs_tilt_error_deg": err, "height_error_m": -err / 10, "ci_contains": trial > 0,
                             "height_ci_contains": trial != 1 or level == "off", "gates_passed": True,
                             "clutter_achieved": clutter})
    h = headline(rows)
    assert h.artefacts == BASE_ARTEFACTS and h.full_frame_error_deg == pytest.approx(0.004)
    assert h.coverage_by_clutter == ((0.0, 0.75, 0.75), (0.3, 0.75, 0.75))
    assert h.meets_coverage_clutter is False
    assert headline(rows, "off").full_frame_error_deg == pytest.approx(0.001)
    assert headline([r for r in rows if r["artefacts"] == "all"]).artefacts == "all"
    table = summary_table(rows)
    assert [(r["artefacts"], r["clutter"]) for r in table] == [(a, c) for a in ARTEFACT_LEVELS for c in (0.0, 0.3)]
    by = {(r["artefacts"], r["clutter"]): r for r in table}
    assert by[("all", 0.3)]["mean_deg"] == pytest.approx(0.03)
    assert by[("off", 0.0)]["height_coverage"] == 1.0 and by[("all", 0.0)]["height_coverage"] == 0.75
    assert by[("all", 0.0)]["mean_height_error_m"] == pytest.approx(0.003)


def test_no_clutter_places_no_box(intrinsics: Any) -> None:
    trial, _ = run_trial(StudySettings(trials=1), Condition(0.61, 70.0, 2.0, 0.0), 0, intrinsics, None)
    assert trial.boxes == []
    assert trial.clutter_achieved == 0.0
    assert trial.truth.angle_rad == pytest.approx(math.radians(70.0), abs=1e-9)


def test_full_frame_beats_the_papers_nine_point_fit(result: study.StudyResult) -> None:
    h = headline(result.rows)
    assert h.n_trials == 3 * TRIALS and h.n_trials_clutter == 3 * TRIALS
    assert h.full_frame_error_deg is not None and h.nominal_error_deg is not None
    # measured: full frame ~0.002 deg, nominal nine-point ~0.36 deg (no clutter)
    assert h.full_frame_error_deg < h.nominal_error_deg / 10
    assert h.full_frame_error_deg <= study.TARGET_ERROR_DEG
    assert h.full_frame_error_clutter_deg is not None and h.nominal_error_clutter_deg is not None
    assert h.full_frame_error_clutter_deg <= study.TARGET_ERROR_CLUTTER_DEG
    assert h.full_frame_error_clutter_deg < h.nominal_error_clutter_deg / 10
    assert h.clutter_achieved_mean == pytest.approx(0.3, abs=0.01)


def test_headline_without_paper_rows_is_empty() -> None:
    h = headline([])
    assert h.n_trials == 0 and h.full_frame_error_deg is None and h.meets_coverage is None


def test_settings_reject_nonsense() -> None:
    with pytest.raises(CalibrationError, match="trials"):
        StudySettings(trials=0)
    with pytest.raises(CalibrationError, match="clutter"):
        StudySettings(clutter_fractions=(0.95,))


def test_plots_are_png_files(result: study.StudyResult, tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    from cellcal.core.study.plots import PLOT_FILES, write_plots

    paths = write_plots(result, tmp_path)
    assert set(paths) == {"perimeter", "clutter", "plane"}  # one noise level / inclination: no 4th plot
    for name, p in paths.items():
        assert p.name == PLOT_FILES[name]
        data = p.read_bytes()
        assert len(data) > 5000
        assert data[:8] == PNG_SIGNATURE
    assert not list(tmp_path.glob(".*.tmp"))


def test_plots_need_matplotlib(monkeypatch: pytest.MonkeyPatch, result: study.StudyResult, tmp_path: Path) -> None:
    from cellcal.core.study import plots as study_plots

    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib -> ImportError
    with pytest.raises(MissingDependencyError, match=r"cellcal\[plots\]"):
        study_plots.plot_error_vs_perimeter(result.rows, tmp_path / "x.png")
    assert not (tmp_path / "x.png").exists()


def test_cli_writes_to_out_and_exits_0(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "study-out"
    code = main(["study", "--quick", "--trials", "1", "--seed", "2", "--out", str(out), "--no-plots"])
    assert code == 0
    text = capsys.readouterr().out
    assert "full frame, mean |tilt error|" in text and "nine-point, nominal FOV" in text
    rows = read_csv(out / "study.csv")
    assert len(rows) == 6 * (len(GRID_METHODS) * 4 + 1)
    assert (out / "headline.json").stat().st_size > 0


def test_cli_artefact_levels_and_resolution(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "study-out"
    code = main(["study", "--quick", "--trials", "1", "--seed", "2", "--out", str(out), "--no-plots",
                 "--artefacts", "off,all", "--resolution", "160x120"])
    assert code == 0
    text = capsys.readouterr().out
    assert "ToF artefacts off" in text  # without the base level, the headline reports the first level
    rows = read_csv(out / "study.csv")
    assert {r["artefacts"] for r in rows} == {"off", "all"}
    assert len(rows) == 2 * 6 * (len(GRID_METHODS) * 4 + 1)
    head = json.loads((out / "headline.json").read_text())
    assert head["resolution_px"] == [160, 120] and head["artefact_levels"] == ["off", "all"]


@pytest.mark.parametrize(("option", "value"), [("--artefacts", "off,most"), ("--artefacts", ","),
                                               ("--resolution", "160"), ("--resolution", "1x800"),
                                               ("--resolution", "axb")])
def test_cli_bad_artefacts_or_resolution_is_a_usage_error(option: str, value: str, tmp_path: Path,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["study", option, value, "--out", str(tmp_path)])
    assert exc.value.code == 2
    assert option in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


def test_cli_bad_trials_is_a_usage_error(tmp_path: Path) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["study", "--trials", "0", "--out", str(tmp_path)])
    assert exc.value.code == 2
    assert not any(tmp_path.iterdir())


def test_artefact_plot_is_a_png(tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    from cellcal.core.study.plots import PLOT_FILES, plot_artefacts

    rows = [{"height_m": 0.46, "inclination_deg": 80.0, "noise_scale": 1.0, "clutter_target": c, "artefacts": a,
             "trial": i, "method": FULL_FRAME, "ok": True, "abs_tilt_error_deg": 0.001 * (1 + i), "ci_contains": i > 0,
             "height_ci_contains": True} for a in ARTEFACT_LEVELS for c in (0.0, 0.2, 0.4) for i in range(3)]
    path = plot_artefacts(rows, tmp_path / PLOT_FILES["artefacts"])
    data = path.read_bytes()
    assert data[:8] == PNG_SIGNATURE and len(data) > 5000
