"""``cellcal depthcal`` end to end on the simulated cells: the plan, its checks, the run, resume, record/replay."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from repo_paths import REPO_ROOT

# imported before any test patches calibrator.build_devices: replay binds the function at its import, and a
# first import inside a patched test (the CLI's resume path imports it) kept the patch for later tests
import cellcal.core.calibration.replay  # noqa: F401
from cellcal.core.calibration.config import load_config
from cellcal.core.calibration.journal import journal_path, read_journal
from cellcal.core.cli import main
from cellcal.core.depthcal.plan import depthcal_heights, depthcal_plan, plan_coverage
from cellcal.core.depthcal.run import DEPTHCAL_FILENAME, FRAMES_DIRNAME

#: A small plan (6 poses, 2 held out, few points) for speed.
SMALL = """
[depthcal]
heights_m = [0.45, 0.6]
inclinations_deg = [90.0, 75.0]
rolls_deg = [0.0, 90.0]
max_points_per_view = 600
field_max_order = 1
holdout_every = 3
"""


def small_config(tmp_path: Path, name: str = "sim.toml", extra: str = "") -> Path:
    cfg = tmp_path / f"small-{name}"
    cfg.write_text((REPO_ROOT / "configs" / name).read_text() + SMALL + extra)
    return cfg


def no_devices(monkeypatch: pytest.MonkeyPatch) -> None:
    """Any attempt to build the devices fails the test."""
    def refuse(*_: Any, **__: Any) -> Any:
        raise AssertionError("a device was built")

    monkeypatch.setattr("cellcal.core.calibration.calibrator.build_devices", refuse)


@pytest.mark.parametrize("name", ["sim.toml", "sim_oak.toml"])
def test_the_command_writes_the_correction_and_the_report(tmp_path: Path, name: str,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    assert main(["depthcal", "--config", str(small_config(tmp_path, name)), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    doc = json.loads((out / DEPTHCAL_FILENAME).read_text())
    kind = "tof" if name == "sim.toml" else "stereo"
    assert doc["schema"] == "cellcal.depthcal/1" and doc["kind"] == kind
    assert len(doc["plan"]) == 6 and len(doc["views"]) == 6
    assert sum(v["held_out"] for v in doc["views"]) == 2
    assert doc["holdout"]["rms_after"] <= doc["holdout"]["rms_before"] * 1.05
    assert f"depth calibration of a {kind} camera from 6 views (2 held out)" in text
    assert "held-out residual RMS" in text and "what the fit sees" in text and "the plan: 2 heights" in text
    assert '[camera.correction] file = "' in text
    assert (out / "depthcal-report.html").exists()
    for png in ("field", "residuals", "views", "orders"):
        assert (out / f"depthcal-{png}.png").read_bytes()[:4] == b"\x89PNG"
    assert not (out / FRAMES_DIRNAME).exists() and not journal_path(out / DEPTHCAL_FILENAME).exists()


def test_the_default_plan_spans_heights_inclinations_and_image_directions() -> None:
    config = load_config(REPO_ROOT / "configs" / "sim.toml")
    views = depthcal_plan(config)
    assert depthcal_heights(config) == (0.385, 0.535, 0.685)  # [plan] 0.46-0.61 m widened to 0.3 m
    assert len(views) == 15
    seen = plan_coverage(config, views)
    assert seen.inclinations_deg == (90.0, 80.0, 70.0) and len(seen.slope_directions) == 4 and not seen.notes


def test_a_plan_with_one_height_and_no_tilt_says_what_it_cannot_see(tmp_path: Path) -> None:
    cfg = tmp_path / "flat.toml"
    cfg.write_text((REPO_ROOT / "configs" / "sim.toml").read_text()
                   + "\n[depthcal]\nheights_m = [0.5]\ninclinations_deg = [90.0]\n")
    config = load_config(cfg)
    notes = plan_coverage(config, depthcal_plan(config)).notes
    assert any("one height" in n for n in notes) and any("no tilted view" in n for n in notes)


@pytest.mark.parametrize(("extra", "named"), [
    ("heights_m = [0.5]\n", ["one height"]),
    ("inclinations_deg = [90.0]\n", ["no tilted view"]),
    ("heights_m = [0.5]\ninclinations_deg = [90.0]\n", ["one height", "no tilted view"]),
    ("inclinations_deg = [90.0]\nfield_max_order = 0\n", []),   # no field fitted: nothing to see across
])
def test_a_plan_that_cannot_see_a_term_is_refused_before_anything_connects(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], extra: str,
        named: list[str]) -> None:
    no_devices(monkeypatch)
    cfg = tmp_path / "cell.toml"
    cfg.write_text((REPO_ROOT / "configs" / "sim.toml").read_text() + "\n[depthcal]\n" + extra)
    for mode in ("--dry-run", "--check", "--out"):
        args = ["depthcal", "--config", str(cfg), mode] + ([str(tmp_path / "o")] if mode == "--out" else [])
        if not named:
            if mode == "--dry-run":
                assert main(args) == 0 and "dry run OK" in capsys.readouterr().out
            continue
        assert main(args) == 1, mode
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "quality gate 'observability' failed" in err and "Traceback" not in err
        assert all(n in err for n in named) and f"{len(named)} vs threshold 0" in err
    assert not (tmp_path / "o").exists()


def test_dry_run_draws_the_plan_and_moves_nothing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    no_devices(monkeypatch)
    assert main(["depthcal", "--config", str(REPO_ROOT / "configs" / "sim_oak.toml"), "--dry-run",
                 "--out", str(tmp_path / "o")]) == 0
    out = capsys.readouterr().out
    assert out.count("move ") == 15 and "[h 0.685 m, 70 deg, roll 270]" in out
    assert "coverage: 3 heights (385-685 mm)" in out and "dry run OK" in out
    assert not (tmp_path / "o").exists()


def test_check_names_the_devices_and_the_plan(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["depthcal", "--config", str(small_config(tmp_path)), "--check"]) == 0
    out = capsys.readouterr().out
    assert "plan:    6 poses x 1 frames (heights 0.450, 0.600 m" in out and "config OK" in out


def test_a_pose_outside_the_envelope_is_refused_before_anything_moves(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                                      capsys: pytest.CaptureFixture[str]) -> None:
    no_devices(monkeypatch)
    cfg = small_config(tmp_path, extra="")
    cfg.write_text(cfg.read_text().replace("heights_m = [0.45, 0.6]", "heights_m = [0.45, 0.95]"))
    assert main(["depthcal", "--config", str(cfg), "--out", str(tmp_path / "o")]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "plan pose 4" in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()


def test_a_bad_depthcal_key_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg = small_config(tmp_path, extra="holdout_evry = 3\n")
    assert main(["depthcal", "--config", str(cfg), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "depthcal.holdout_evry" in err and "unknown key" in err


def test_ctrl_c_gives_130_a_valid_journal_and_resume_continues(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                               capsys: pytest.CaptureFixture[str]) -> None:
    import cellcal.core.calibration.calibrator as calibrator_module

    build = calibrator_module.build_devices
    cfg, out = small_config(tmp_path), tmp_path / "out"

    def interrupted(config: Any) -> Any:
        camera, arm = build(config)

        def stop(event: str, n: int) -> None:
            if event == "move" and n == 4:
                raise KeyboardInterrupt

        arm.inner.fault_hook = stop
        return camera, arm

    monkeypatch.setattr(calibrator_module, "build_devices", interrupted)
    assert main(["depthcal", "--config", str(cfg), "--out", str(out)]) == 130
    err = capsys.readouterr().err
    assert "3 of 6 poses are saved" in err and "--resume" in err
    config = load_config(cfg)
    from cellcal.core.calibration.journal import plan_fingerprint

    entries = read_journal(journal_path(out / DEPTHCAL_FILENAME),
                           plan_fingerprint(config.document, [v.pose for v in depthcal_plan(config)]))
    assert [e.index for e in entries] == [0, 1, 2]
    assert sorted(p.name for p in (out / FRAMES_DIRNAME).iterdir()) == ["pose-001.npz", "pose-002.npz",
                                                                        "pose-003.npz"]
    assert not (out / DEPTHCAL_FILENAME).exists()

    monkeypatch.setattr(calibrator_module, "build_devices", build)
    assert main(["depthcal", "--config", str(cfg), "--out", str(out), "--resume", "--no-report"]) == 0
    doc = json.loads((out / DEPTHCAL_FILENAME).read_text())
    assert doc["resumed_poses"] == [0, 1, 2] and len(doc["views"]) == 6
    assert not (out / FRAMES_DIRNAME).exists()


def test_record_then_replay_gives_the_same_correction(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rec = tmp_path / "session.mcap"
    assert main(["depthcal", "--config", str(small_config(tmp_path)), "--out", str(tmp_path / "a"), "--record",
                 str(rec), "--no-report", "--quiet"]) == 0
    assert main(["depthcal", "--replay", str(rec), "--out", str(tmp_path / "b"), "--no-report", "--quiet"]) == 0
    assert "replay: identical to the recorded result (6 poses" in capsys.readouterr().out
    a, b = (json.loads((tmp_path / d / DEPTHCAL_FILENAME).read_text()) for d in "ab")
    assert a["correction"] == b["correction"] and a["holdout"] == b["holdout"]


def test_the_plan_views_are_the_hand_eye_plan_s_without_scipy() -> None:
    import math

    import numpy as np

    from cellcal.core.handeye.plan import view_pose

    config = load_config(REPO_ROOT / "configs" / "sim.toml")
    mount = config.mount.pose()
    for v in depthcal_plan(config):
        want = view_pose(np.array(v.target_m), v.height_m, math.radians(v.inclination_deg), math.radians(v.roll_deg),
                         mount)
        assert np.allclose(want.rotation_matrix, v.pose.rotation_matrix, atol=1e-12)
        assert np.allclose(want.translation, v.pose.translation, atol=1e-12)


def test_a_configured_correction_is_not_applied_to_the_frames_depthcal_fits(tmp_path: Path,
                                                                            capsys: pytest.CaptureFixture[str]) -> None:
    first = tmp_path / "first"
    cfg = small_config(tmp_path)
    assert main(["depthcal", "--config", str(cfg), "--out", str(first), "--no-report", "--quiet"]) == 0
    plain = json.loads((first / DEPTHCAL_FILENAME).read_text())
    corrected = tmp_path / "corrected.toml"
    corrected.write_text(cfg.read_text().replace('[camera]\nbackend = "sim"\n', '[camera]\nbackend = "sim"\n\n'
                                                 f'[camera.correction]\nfile = "{first / DEPTHCAL_FILENAME}"\n', 1))
    assert "[camera.correction]" in corrected.read_text()
    capsys.readouterr()
    assert main(["depthcal", "--config", str(corrected), "--check"]) == 0
    assert "its [camera.correction] is not applied: depthcal fits the raw frames" in capsys.readouterr().out
    again = tmp_path / "again"
    assert main(["depthcal", "--config", str(corrected), "--out", str(again), "--no-report"]) == 0
    assert "the configured [camera.correction] was not applied" in capsys.readouterr().out
    # the same raw frames (same seed): the same correction, not a correction of the corrected frames
    assert json.loads((again / DEPTHCAL_FILENAME).read_text())["correction"] == plain["correction"]


def test_a_failed_fit_keeps_every_pose_and_resume_fits_again_without_moving(tmp_path: Path,
                                                                            monkeypatch: pytest.MonkeyPatch,
                                                                            capsys: pytest.CaptureFixture[str]) -> None:
    import cellcal.core.calibration.calibrator as calibrator_module
    import cellcal.core.depthcal.run as run_module
    from cellcal.devices.errors import CalibrationQualityError

    cfg, out = small_config(tmp_path), tmp_path / "out"
    fit = run_module.fit_plan

    def refused(*_: Any) -> Any:
        raise CalibrationQualityError("noise_model", 12.0, 10.0, "residuals far beyond the stated noise")

    monkeypatch.setattr(run_module, "fit_plan", refused)
    assert main(["depthcal", "--config", str(cfg), "--out", str(out), "--no-report"]) == 1
    err = [line for line in capsys.readouterr().err.splitlines() if not line.startswith(("pose", "6 poses"))]
    assert len(err) == 1 and "noise_model" in err[0] and "6 of 6 poses are saved" in err[0] and "--resume" in err[0]
    assert len(list((out / FRAMES_DIRNAME).iterdir())) == 6 and not (out / DEPTHCAL_FILENAME).exists()

    build = calibrator_module.build_devices
    moves: list[int] = []

    def counting(config: Any) -> Any:
        camera, arm = build(config)
        arm.inner.fault_hook = lambda event, n: moves.append(n) if event == "move" else None
        return camera, arm

    monkeypatch.setattr(run_module, "fit_plan", fit)
    monkeypatch.setattr(calibrator_module, "build_devices", counting)
    assert main(["depthcal", "--config", str(cfg), "--out", str(out), "--resume", "--no-report"]) == 0
    assert moves == []  # every pose came from the journal and its frames
    doc = json.loads((out / DEPTHCAL_FILENAME).read_text())
    assert doc["resumed_poses"] == list(range(6)) and len(doc["views"]) == 6
