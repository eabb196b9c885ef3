"""Real ``cellcal`` processes: interrupted recordings, one run per output, a full disk, saved-pose counts.

Each test starts the console script on the fast sim cell slowed down by a settle time
at every pose, and acts on it at a known point of its run (a whole progress line on stderr
says which pose it is at): Ctrl-C, a second run on the same output, a file size limit.
The settle times leave a second or more between that line and the end of the run, for a
loaded machine's delay in seeing the line and sending the signal.
"""

from __future__ import annotations

import json
import os
import resource
import signal
import time
from pathlib import Path

import pytest
from fault_cells import CellcalProcess, slow_cell_document
from toml_files import write_toml

from cellcal.core.calibration.journal import journal_path, read_journal
from cellcal.core.calibration.outlock import LOCK_NAME
from cellcal.core.calibration.report import RESULT_SCHEMA
from cellcal.core.cli.progress import PLAIN_LINE
from cellcal.devices.recording import read_recording

N_POSES = 3
#: The whole progress line that says the run is at a pose (stderr is a pipe: plain lines).
AT_POSE = {f"{n}/{N_POSES}": f"pose {n}/{N_POSES} done" for n in range(1, N_POSES + 1)}
AT_POSE[f"0/{N_POSES}"] = f"{N_POSES} poses to go (0/{N_POSES})"


def _names(directory: Path) -> list[str]:
    return sorted(p.name for p in directory.iterdir())


def _one_line(err: str) -> str:
    """The one line a failing command prints (after the progress lines: stderr is a pipe here), on a line of its own."""
    assert "Traceback" not in err, err
    lines = [line for line in err.replace("\r", "\n").splitlines()
             if line.strip() and "|" not in line and not PLAIN_LINE.fullmatch(line)]
    assert len(lines) == 1, err
    assert lines[0].startswith("cellcal: "), err  # no progress text run into it
    return lines[0]


# ---------------------------------------------------------------------- cellcal record, interrupted


@pytest.mark.parametrize(("after_poses", "keep_failed"), [(1, False), (2, False), (2, True)],
                         ids=["after-pose-1", "at-the-last-pose", "at-the-last-pose-keep-failed"])
def test_interrupted_recording_is_finished_with_what_was_recorded(tmp_path: Path, after_poses: int,
                                                                  keep_failed: bool) -> None:
    config = write_toml(tmp_path / "slow.toml", slow_cell_document(settle_s=1.0))  # 1 s after the last pose's line
    out = tmp_path / "rec" / "s.mcap"
    run = CellcalProcess(["record", "--config", str(config), "--out", str(out),
                          *(["--keep-failed"] if keep_failed else [])])
    assert run.wait_for_line(AT_POSE[f"{after_poses}/{N_POSES}"]), run.stderr_so_far()
    run.interrupt()  # during the next pose's settle time: its frame is not taken yet
    code, out_text, err = run.finish()
    assert code == 130, err
    line = _one_line(err)
    assert line == (f"cellcal: interrupted; the recording of the run so far ({after_poses} captures, "
                    f"{line.split(', ')[1].split(' ')[0]} arm calls, no result) is in {out}")
    assert out_text == ""
    rec = read_recording(out)  # a valid, indexed MCAP file: summary, chunk indexes and CRCs are checked
    assert rec.result == {"ok": False, "result": None,
                          "error": {"type": "KeyboardInterrupt", "message": "interrupted (Ctrl-C)", "attrs": {}}}
    assert len(rec.captures) == after_poses and all(c["error"] is None for c in rec.captures)
    moves = [c for c in rec.arm_calls if c["method"] == "move_linear"]
    assert len(moves) in (after_poses, after_poses + 1)  # the move to the next pose: not yet, made or cut short
    assert all(m["error"] is None for m in moves[:after_poses])
    if len(moves) > after_poses:  # a move the Ctrl-C cut short was still sent: it is in the file, with why
        assert moves[-1]["error"] in (None, {"type": "KeyboardInterrupt", "message": "interrupted (Ctrl-C)",
                                             "attrs": {}})
    assert rec.arm_calls[-1]["method"] == "stop"  # the arm was told to stop, and the file shows it
    assert rec.message_counts["/arm/call"] == int(line.split(", ")[1].split(" ")[0])
    assert _names(out.parent) == ["s.mcap"]  # no temporary file, no lock file


#: (what to wait for, seconds after it): main's call (the imports; the recorder may not
#: exist yet), and every pose of the run (the devices are connected: the file must be kept).
#: The run settles 1.5 s at each pose: 2/3 + 0.45 s still leaves a second before it ends.
MOMENTS = [("main", 0.0), ("main", 0.02), ("main", 0.3), ("0/3", 0.0), ("0/3", 0.3), ("1/3", 0.0),
           ("1/3", 0.25), ("2/3", 0.1), ("2/3", 0.45)]


@pytest.mark.parametrize(("moment", "delay"), MOMENTS, ids=[f"{m}+{d}s" for m, d in MOMENTS])
def test_ctrl_c_at_any_moment_of_a_recording_leaves_no_file_or_a_valid_one(tmp_path: Path, moment: str,
                                                                           delay: float) -> None:
    config = write_toml(tmp_path / "slow.toml", slow_cell_document(settle_s=1.5))
    out = tmp_path / "rec" / "s.mcap"
    run = CellcalProcess(["record", "--config", str(config), "--out", str(out)], announce=True)
    if moment == "main":
        run.wait_ready()
    else:
        assert run.wait_for_line(AT_POSE[moment]), run.stderr_so_far()
    time.sleep(delay)  # the moment of the Ctrl-C; either outcome below is checked
    run.interrupt()
    code, _out, err = run.finish()
    assert code == 130, err
    line = _one_line(err)
    if out.parent.exists() and _names(out.parent):
        assert _names(out.parent) == ["s.mcap"]  # no temporary file, no lock file
        assert not read_recording(out).result["ok"]
        assert line.endswith(f"no result) is in {out}"), line
    else:  # before the recorder opened the file: nothing written, nothing left
        assert moment == "main" and line == "cellcal: interrupted", line


# ---------------------------------------------------------------------- one run per output


def test_a_second_run_on_the_same_output_is_refused_while_the_first_goes_on(tmp_path: Path) -> None:
    # the first run is stopped (SIGSTOP) at its second pose while the second one starts, however long that
    # takes on a loaded machine, and continued afterwards; 1 s per pose leaves 2 s to stop it in, and timeouts
    # of a minute let a move or capture go on after the stop (the fast cell's end one at a second's pause)
    config = write_toml(tmp_path / "slow.toml", slow_cell_document(settle_s=1.0, plan={"move_timeout_s": 60.0,
                                                                                      "capture_timeout_s": 60.0}))
    out = tmp_path / "out"
    first = CellcalProcess(["calibrate", "--config", str(config), "--out", str(out), "--no-report"])
    assert first.wait_for_line(AT_POSE[f"1/{N_POSES}"]), first.stderr_so_far()  # running, one pose in its journal
    first.proc.send_signal(signal.SIGSTOP)
    try:
        assert first.proc.poll() is None, "the first run ended before it was held"
        assert (out / LOCK_NAME).read_text() == f"{first.pid}\n"
        code, text, err = CellcalProcess(["calibrate", "--quiet", "--config", str(config), "--out", str(out)]).finish()
    finally:
        first.proc.send_signal(signal.SIGCONT)
    assert code == 1 and text == ""
    assert err == (f"cellcal: error: {out} is in use by another cellcal run (pid {first.pid}); wait for it to end "
                   f"or write elsewhere (lock file {out / LOCK_NAME})\n")
    code, text, err = first.finish()
    assert code == 0, err
    assert json.loads((out / "result.json").read_text())["schema"] == RESULT_SCHEMA
    assert len(json.loads((out / "result.json").read_text())["poses"]) == N_POSES
    assert _names(out) == ["result.json"]  # the journal is gone, and so is the lock file
    # a recording is locked the same way
    rec = tmp_path / "s.mcap"
    first = CellcalProcess(["record", "--config", str(config), "--out", str(rec)])
    assert first.wait_for_line(AT_POSE[f"1/{N_POSES}"]), first.stderr_so_far()
    first.proc.send_signal(signal.SIGSTOP)
    try:
        assert first.proc.poll() is None, "the first recording ended before it was held"
        code, _text, err = CellcalProcess(["record", "--config", str(config), "--out", str(rec)]).finish()
    finally:
        first.proc.send_signal(signal.SIGCONT)
    assert code == 1 and f"{rec} is in use by another cellcal run (pid {first.pid})" in err
    assert first.finish()[0] == 0 and read_recording(rec).result["ok"]


def test_the_lock_of_a_killed_run_blocks_nobody(tmp_path: Path) -> None:
    config = write_toml(tmp_path / "slow.toml", slow_cell_document(settle_s=1.0))
    out = tmp_path / "out"
    crashed = CellcalProcess(["calibrate", "--config", str(config), "--out", str(out)])
    assert crashed.wait_for_line(AT_POSE[f"1/{N_POSES}"]), crashed.stderr_so_far()
    crashed.proc.send_signal(signal.SIGKILL)
    assert crashed.finish()[0] == -signal.SIGKILL
    assert LOCK_NAME in _names(out)  # left behind, but no longer locked
    code, _text, err = CellcalProcess(["calibrate", "--quiet", "--config", str(config), "--out", str(out),
                                       "--resume", "--no-report"]).finish()
    assert code == 0, err
    assert json.loads((out / "result.json").read_text())["resumed_poses"] == [0]
    assert _names(out) == ["result.json"]


# ---------------------------------------------------------------------- a full disk


def test_an_output_that_cannot_grow_is_an_environment_failure(tmp_path: Path) -> None:
    """A real file size limit (RLIMIT_FSIZE, EFBIG) while the run writes: exit 1, not 2, one line."""
    config = write_toml(tmp_path / "slow.toml", slow_cell_document(settle_s=0.0))
    out = tmp_path / "out"
    out.mkdir()
    (out / "result.json").write_text("earlier result\n")

    def small_files() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # the write fails with EFBIG instead of killing
        resource.setrlimit(resource.RLIMIT_FSIZE, (4096, 4096))

    code, _text, err = CellcalProcess(["calibrate", "--quiet", "--config", str(config), "--out", str(out)],
                                      preexec_fn=small_files).finish()
    assert code == 1, err
    line = _one_line(err)
    assert line.startswith("cellcal: error: ") and "File too large" in line, line
    assert (out / "result.json").read_text() == "earlier result\n"
    assert not [n for n in _names(out) if n.endswith(".tmp") or n == LOCK_NAME]


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only directories")
def test_an_output_in_a_read_only_directory_is_bad_input(tmp_path: Path) -> None:
    locked = tmp_path / "ro"
    locked.mkdir()
    locked.chmod(0o555)
    try:
        code, _text, err = CellcalProcess(["calibrate", "--quiet", "--out", str(locked / "out")]).finish()
    finally:
        locked.chmod(0o755)
    assert code == 2 and _one_line(err).endswith("Permission denied"), err


def test_an_output_path_that_cannot_be_a_directory_is_bad_input_before_any_move(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("")
    code, text, err = CellcalProcess(["calibrate", "--quiet", "--out", str(blocker / "out")]).finish()
    assert code == 2 and text == ""
    assert _one_line(err) == f"cellcal: error: cannot create {blocker / 'out'}: Not a directory"


# ---------------------------------------------------------------------- saved poses: this run's only


def test_interrupted_run_counts_only_its_own_saved_poses(tmp_path: Path) -> None:
    config = write_toml(tmp_path / "slow.toml", slow_cell_document(settle_s=0.6))
    out = tmp_path / "out"
    journal = journal_path(out / "result.json")
    first = CellcalProcess(["calibrate", "--config", str(config), "--out", str(out)])
    assert first.wait_for_line(AT_POSE[f"1/{N_POSES}"]), first.stderr_so_far()
    first.interrupt()
    code, _text, err = first.finish()
    assert code == 130 and f"1 of {N_POSES} poses are saved in {journal}" in _one_line(err)
    header = json.loads(journal.read_text().splitlines()[0])
    # a fresh run (no --resume) on the same output, interrupted during its first pose: the journal
    # on disk is the first run's, and this run saved nothing
    second = CellcalProcess(["calibrate", "--config", str(config), "--out", str(out)])
    assert second.wait_for_line(AT_POSE[f"0/{N_POSES}"]), second.stderr_so_far()  # the whole line, its newline too
    second.interrupt()
    code, _text, err = second.finish()
    assert code == 130 and _one_line(err) == "cellcal: interrupted", err
    assert err.endswith(f"{AT_POSE[f'0/{N_POSES}']}\ncellcal: interrupted\n"), err
    assert [e.index for e in read_journal(journal, header["fingerprint"])] == [0]  # the first run's, intact
    code, _text, err = CellcalProcess(["calibrate", "--quiet", "--config", str(config), "--out", str(out),
                                       "--resume", "--no-report"]).finish()
    assert code == 0, err
    assert json.loads((out / "result.json").read_text())["resumed_poses"] == [0]
