"""An interrupted or failed journaled run says how many poses are saved and how to resume."""

from __future__ import annotations

import argparse
from pathlib import Path
from types import SimpleNamespace

import pytest

from cellcal.core.cli.exits import EXIT_INTERRUPTED
from cellcal.core.cli.resumable import resume_command, run_resumable
from cellcal.devices.errors import DeviceTimeoutError


def _calibrator(saved: int) -> SimpleNamespace:
    """What poses_saved reads: the run's journal writer and its count."""
    return SimpleNamespace(journal_writer=SimpleNamespace(saved=saved))


ARGS = argparse.Namespace(config="my cell.toml", out="out dir")
RESUME = resume_command("handeye", ARGS, "--plan auto")


def test_resume_command_quotes_what_the_shell_would_split() -> None:
    assert RESUME == "cellcal handeye --config 'my cell.toml' --plan auto --out 'out dir' --resume"
    assert resume_command("calibrate", argparse.Namespace(config=None, out="o")) == "cellcal calibrate --out o --resume"


def test_interrupt_is_exit_130_with_the_hint(capsys: pytest.CaptureFixture[str]) -> None:
    def run() -> dict[str, int]:
        raise KeyboardInterrupt

    code = run_resumable(run, _calibrator(2), 8, Path("out dir/handeye.json"), RESUME)
    assert code == EXIT_INTERRUPTED
    assert capsys.readouterr().err == (
        "cellcal: interrupted; 2 of 8 poses are saved in out dir/handeye.json.journal.jsonl; "
        f"'{RESUME}' continues the run\n")


def test_interrupt_before_any_pose_says_nothing_of_resuming(capsys: pytest.CaptureFixture[str]) -> None:
    def run() -> dict[str, int]:
        raise KeyboardInterrupt

    assert run_resumable(run, _calibrator(0), 8, Path("r.json"), RESUME) == EXIT_INTERRUPTED
    assert capsys.readouterr().err == "cellcal: interrupted\n"


def test_a_failure_keeps_its_type_and_gains_the_hint() -> None:
    def run() -> dict[str, int]:
        raise DeviceTimeoutError("sim: no frame within 1 s")

    with pytest.raises(DeviceTimeoutError) as err:
        run_resumable(run, _calibrator(3), 8, Path("o/result.json"), "cellcal calibrate --out o --resume")
    assert str(err.value) == ("sim: no frame within 1 s; 3 of 8 poses are saved in o/result.json.journal.jsonl; "
                              "'cellcal calibrate --out o --resume' continues the run")


def test_a_finished_run_returns_its_document() -> None:
    assert run_resumable(lambda: {"ok": 1}, _calibrator(8), 8, Path("r.json"), RESUME) == {"ok": 1}
