"""``calibrate --resume``: an interrupted plan continues from its journal without redoing poses.

The simulated camera's noise comes from one random stream per camera (and the arm's
read-back noise from one per arm), advanced by every frame / pose reading. A resumed
run restores both streams from the journal's last record, so the poses it measures
draw exactly the noise they would have drawn in one uninterrupted run: the resumed
result equals the uninterrupted one exactly (every key but wall-clock timings and
the creation time).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fault_cells import SIM_DOC, Probe, cell_document, interrupt, make_probe
from toml_files import write_toml

from cellcal.core.calibration.calibrator import run_to_file
from cellcal.core.calibration.journal import journal_path, plan_fingerprint, read_journal
from cellcal.core.cli import main
from cellcal.devices.errors import ConfigError, SafetyError
from cellcal.devices.pose import Pose

N_POSES = 3


def comparable(result: dict[str, Any]) -> dict[str, Any]:
    """The result without wall-clock timings and creation time (which differ between any two runs)."""
    out = {k: v for k, v in result.items() if k not in ("timings_s", "created_utc", "resumed_poses")}
    out["poses"] = [{k: v for k, v in p.items() if k != "timings_s"} for p in result["poses"]]
    return out


def count_captures(probe: Probe, fail_at: int | None = None) -> list[int]:
    """Count capture events on the sim camera; optionally interrupt before capture ``fail_at``."""
    seen: list[int] = []

    def hook(event: str, n: int) -> None:
        if event == "capture":
            seen.append(n)
            if fail_at is not None and len(seen) == fail_at:
                interrupt()

    probe.sim_camera.fault_hook = hook
    return seen


def interrupted(doc: dict[str, Any], out: Path, after: int) -> Probe:
    """Run ``doc`` and interrupt it (SIGINT) as the capture after ``after`` poses starts."""
    probe = make_probe(doc)
    count_captures(probe, fail_at=after + 1)
    with pytest.raises(KeyboardInterrupt):
        run_to_file(probe.calibrator, out)
    return probe


@pytest.mark.parametrize("after", [1, 2])
def test_resumed_run_equals_an_uninterrupted_one(after: int, tmp_path: Path) -> None:
    doc = cell_document(plan={"perimeters_px": [20, 40], "methods": ["law_of_cosines", "plane_fit"]})
    whole = run_to_file(make_probe(doc).calibrator, tmp_path / "whole" / "result.json")

    out = tmp_path / "resumed" / "result.json"
    first = interrupted(doc, out, after)
    assert first.sim_arm.moves_started == after + 1  # the interrupted pose had moved, not captured
    journal = journal_path(out)
    cal = first.calibrator
    assert [e.index for e in read_journal(journal, plan_fingerprint(cal.config.document, cal.poses))] == \
        list(range(after))
    assert not out.exists()

    second = make_probe(doc)
    captures = count_captures(second)
    resumed = run_to_file(second.calibrator, out, resume=True)
    # the recorded poses were not visited again: one move and one capture per remaining pose
    assert second.sim_arm.moves_started == N_POSES - after
    assert len(captures) == N_POSES - after
    assert resumed["resumed_poses"] == list(range(after))
    assert comparable(resumed) == comparable(whole)
    assert json.loads(out.read_text())["poses"] == resumed["poses"]
    assert not journal.exists()  # the result is written, the journal removed


def test_default_cell_with_every_method_resumes_exactly(tmp_path: Path) -> None:
    doc = cell_document(plan={k: SIM_DOC["plan"][k] for k in ("perimeters_px", "methods")})
    whole = run_to_file(make_probe(doc).calibrator, tmp_path / "whole.json")
    out = tmp_path / "r" / "result.json"
    interrupted(doc, out, after=1)
    resumed = run_to_file(make_probe(doc).calibrator, out, resume=True)
    assert comparable(resumed) == comparable(whole)


def test_interrupt_while_writing_resumes_without_any_device(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    doc = cell_document()
    out = tmp_path / "result.json"
    import os

    real = os.replace

    def interrupted_rename(src: Any, dst: Any) -> None:
        if Path(dst) == out:
            raise KeyboardInterrupt
        real(src, dst)

    monkeypatch.setattr(os, "replace", interrupted_rename)
    with pytest.raises(KeyboardInterrupt):
        run_to_file(make_probe(doc).calibrator, out)
    monkeypatch.undo()
    probe = make_probe(doc)
    resumed = run_to_file(probe.calibrator, out, resume=True)
    assert resumed["resumed_poses"] == [0, 1, 2]
    assert probe.sim_arm.connects == 0 and probe.sim_camera.connects == 0  # nothing left to measure
    assert len(resumed["poses"]) == N_POSES


def test_changed_config_refuses_to_resume(tmp_path: Path) -> None:
    doc = cell_document()
    out = tmp_path / "result.json"
    interrupted(doc, out, after=1)
    changed = cell_document(plan={"speed_m_s": 0.25})
    probe = make_probe(changed)
    with pytest.raises(ConfigError, match="configuration or plan changed since the interrupted run"):
        run_to_file(probe.calibrator, out, resume=True)
    assert probe.sim_arm.connects == 0  # refused before touching a device
    assert journal_path(out).exists()  # the journal of the original run is kept


def test_cli_resume_and_its_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    doc = cell_document()
    config = write_toml(tmp_path / "cell.toml", doc)
    out_dir = tmp_path / "out"
    interrupted(doc, out_dir / "result.json", after=2)  # same document as the file: same fingerprint

    changed = write_toml(tmp_path / "changed.toml", cell_document(plan={"heights_m": [0.46, 0.59, 0.62]}))
    assert main(["calibrate", "--config", str(changed), "--out", str(out_dir), "--quiet", "--resume"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "journal.jsonl" in err and "changed since the interrupted run" in err

    assert main(["calibrate", "--config", str(config), "--out", str(out_dir), "--quiet", "--resume",
                 "--no-report"]) == 0
    result = json.loads((out_dir / "result.json").read_text())
    assert result["resumed_poses"] == [0, 1] and len(result["poses"]) == N_POSES
    assert sorted(p.name for p in out_dir.iterdir()) == ["result.json"]

    capsys.readouterr()
    assert main(["calibrate", "--config", str(config), "--out", str(out_dir), "--quiet", "--resume"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no journal to resume" in err


def test_torn_last_line_is_ignored(tmp_path: Path) -> None:
    doc = cell_document()
    out = tmp_path / "result.json"
    interrupted(doc, out, after=2)
    journal = journal_path(out)
    journal.write_text(journal.read_text() + '{"kind": "pose", "index": 2, "fingerp')  # died mid-write
    probe = make_probe(doc)
    resumed = run_to_file(probe.calibrator, out, resume=True)
    assert resumed["resumed_poses"] == [0, 1] and probe.sim_arm.moves_started == 1


def test_resumed_run_checks_the_move_from_where_the_arm_is_and_names_the_plan_pose(tmp_path: Path) -> None:
    """The remaining moves are checked from the arm's current pose, numbered as in the whole plan."""
    doc = cell_document()
    out = tmp_path / "result.json"
    interrupted(doc, out, after=1)
    probe = make_probe(doc)
    # someone jogged the arm above the workspace box (z max 0.9 m) while the run was interrupted
    probe.sim_arm.world.arm.set_flange_pose(Pose.from_xyz_rpy([0.3, 0.0, 0.95], np.radians([180.0, 0.0, 0.0])))
    with pytest.raises(SafetyError, match=r"^plan pose 2 \(xyz=\(.*\) rejected: flange leaves the workspace box "
                                          r"on the path at \(0\.3000, -?0\.0000, 0\.9500\) m"):
        run_to_file(probe.calibrator, out, resume=True)
    assert probe.sim_arm.moves_started == 0
    fingerprint = plan_fingerprint(probe.calibrator.config.document, probe.calibrator.poses)
    assert [e.index for e in read_journal(journal_path(out), fingerprint)] == [0]
