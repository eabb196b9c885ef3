"""The study on a process pool: the same table as one process, Ctrl-C ends it cleanly, no worker left behind."""

from __future__ import annotations

import os
import re
import signal
import time
from pathlib import Path

import numpy as np
import pytest
from fault_cells import CellcalProcess

from cellcal.core.cli import EXIT_INTERRUPTED
from cellcal.core.study import BASE_ARTEFACTS, StudySettings, rows_to_csv, run_study
from cellcal.core.study.pool import default_jobs
from cellcal.devices.errors import CalibrationError

#: A small design: one height, no clutter and 30 % clutter (the example's condition), 3 trials each.
SMALL = StudySettings(trials=3, seed=11, heights_m=(0.46,), inclinations_deg=(80.0,), noise_scales=(1.0,),
                      clutter_fractions=(0.0, 0.3), artefact_levels=(BASE_ARTEFACTS,), headline_factor=1)


def test_two_processes_give_the_table_of_one() -> None:
    one = run_study(SMALL, jobs=1)
    two = run_study(SMALL, jobs=2)
    assert len(one.rows) == len(two.rows) > 0
    assert rows_to_csv(two.rows) == rows_to_csv(one.rows)  # every value, in the same order
    assert any(r["ok"] and r["method"] == "full_frame" for r in two.rows)
    # the example trial (plane-fit picture) is the same trial with the same frame
    assert one.example is not None and two.example is not None
    assert (two.example.condition, two.example.index, two.example.seed) == \
           (one.example.condition, one.example.index, one.example.seed)
    np.testing.assert_array_equal(two.example.frame.distance, one.example.frame.distance)
    assert two.full_frame_available == one.full_frame_available


def test_pictures_drawn_side_by_side_are_the_pictures_of_one_process(tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    from cellcal.core.study.plots import write_plots

    result = run_study(SMALL, jobs=1)
    one = write_plots(result, tmp_path / "one", jobs=1)
    two = write_plots(result, tmp_path / "two", jobs=2)
    assert list(one) == list(two) and {"perimeter", "clutter", "plane"} <= set(one)
    for name in one:
        assert two[name].parent == tmp_path / "two"
        assert two[name].read_bytes() == one[name].read_bytes(), name


def test_more_workers_than_trials_and_a_bad_job_count() -> None:
    tiny = StudySettings(trials=1, seed=2, heights_m=(0.59,), inclinations_deg=(80.0,), noise_scales=(1.0,),
                         clutter_fractions=(0.0,), artefact_levels=(BASE_ARTEFACTS,), headline_factor=1)
    assert rows_to_csv(run_study(tiny, jobs=8).rows) == rows_to_csv(run_study(tiny, jobs=1).rows)
    with pytest.raises(CalibrationError, match="jobs must be >= 1"):
        run_study(tiny, jobs=0)
    assert default_jobs() >= 1


def _children(pid: int) -> list[int]:
    """The processes whose parent is ``pid`` (Linux /proc)."""
    out = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                stat = Path(f"/proc/{entry}/stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:  # field 4: the parent's pid
                out.append(int(entry))
    return out


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads the process table from /proc")
def test_ctrl_c_during_a_parallel_study_is_130_and_leaves_no_worker(tmp_path: Path) -> None:
    """SIGINT to the whole process group, as a terminal sends it: parent and workers."""
    run = CellcalProcess(["study", "--quick", "--trials", "50", "--jobs", "2", "--no-plots",
                          "--out", str(tmp_path / "study")], preexec_fn=os.setsid)
    deadline = time.monotonic() + 60.0
    workers: list[int] = []
    while len(workers) < 2 and time.monotonic() < deadline and run.proc.poll() is None:
        time.sleep(0.05)
        workers = _children(run.pid)
    assert len(workers) == 2, f"workers never started: {run.stderr_so_far()!r}"
    # trials under way: the first progress line of a finished trial (hundreds of trials remain)
    assert run.wait_for_line(re.compile(r"trial \d+/\d+ done"), timeout_s=120.0), run.stderr_so_far()
    os.killpg(run.pid, signal.SIGINT)
    code, _out, err = run.finish(timeout_s=60.0)
    assert code == EXIT_INTERRUPTED, err
    assert "Traceback" not in err and err.rstrip("\n").endswith("cellcal: interrupted"), err
    assert not (tmp_path / "study" / "study.csv").exists()
    for pid in workers:  # joined by the parent: gone, not even a zombie
        assert not Path(f"/proc/{pid}").exists(), f"worker {pid} outlived the study"
    with pytest.raises(ProcessLookupError):
        os.killpg(run.pid, 0)  # nothing left in the study's process group
