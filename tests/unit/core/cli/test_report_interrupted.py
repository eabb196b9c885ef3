"""Ctrl-C while a run's report is drawn: exit 130, the results stay, one line says how to draw the page later.

A hand-eye report (matplotlib's pictures) is drawn in a child: here a held one (it starts a
worker of its own, as the real one forks two, says so in a file and waits); the Ctrl-C, a real
SIGINT to this process, is sent once the child is known to be drawing, never after a sleep. A
calibrate report is drawn in the run's own process (ADR 0051): the SIGINT is sent while its
third picture is drawn. ``cellcal.core.cli.main`` runs in process, with its own Ctrl-C handling.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import signal
import sys
import threading
import time
from importlib import resources
from pathlib import Path
from typing import Any

import pytest

from cellcal.core.calibration.outlock import LOCK_NAME
from cellcal.core.calibration.report import RESULT_SCHEMA
from cellcal.core.cli import EXIT_INTERRUPTED, EXIT_OK, main
from cellcal.core.console import Interrupted
from cellcal.core.report import load_report_data
from cellcal.core.report import render as render_module
from cellcal.core.report import runs as runs_module
from cellcal.core.report.runs import RunReport

HANDEYE_CONFIG = resources.files("cellcal.configs").joinpath("sim_handeye.toml")

#: The held drawing child: starts a worker, optionally writes the page first (atomically), then writes
#: "PID WORKER_PID" to the marker file and waits for its end.
HELD_CHILD = """if True:
    import os, subprocess, sys, time
    marker, page = sys.argv[1], sys.argv[2]
    worker = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(600)"])
    if page:
        with open(page + ".tmp", "w") as fh:
            fh.write("<!DOCTYPE html><title>drawn by this run</title>")
        os.replace(page + ".tmp", page)
    with open(marker + ".tmp", "w") as fh:
        fh.write(f"{os.getpid()} {worker.pid}")
    os.replace(marker + ".tmp", marker)
    time.sleep(600)
"""


def _alive(pid: int) -> bool:
    """Whether process ``pid`` still runs (a zombie waiting to be reaped does not)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return False
    return fields[0] != "Z"


def _ctrl_c_once_drawing(marker: Path, pids: list[int]) -> threading.Thread:
    """A thread that sends SIGINT to this process once the held child has written ``marker`` (60 s at most)."""

    def watch() -> None:
        deadline = time.monotonic() + 60.0
        while not marker.exists():
            if time.monotonic() > deadline:
                return  # never drawing: no Ctrl-C (the test fails on the missing pids)
            time.sleep(0.01)
        pids.extend(int(p) for p in marker.read_text().split())
        os.kill(os.getpid(), signal.SIGINT)

    thread = threading.Thread(target=watch, daemon=True)
    thread.start()
    return thread


@pytest.mark.parametrize("before", ["nothing", "an earlier page", "page written"])
def test_ctrl_c_while_the_report_is_drawn_in_a_child(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                     capsys: pytest.CaptureFixture[str], before: str) -> None:
    out = tmp_path / "out"
    page = out / "report.html"
    if before == "an earlier page":
        out.mkdir()
        page.write_text("an earlier run's page")
    marker = tmp_path / "drawing"
    writes = str(page) if before == "page written" else ""
    monkeypatch.setattr(runs_module, "draw_command", lambda _dir: [sys.executable, "-c", HELD_CHILD, str(marker),
                                                                   writes])
    pids: list[int] = []
    watcher = _ctrl_c_once_drawing(marker, pids)
    code = main(["handeye", "--config", str(HANDEYE_CONFIG), "--quiet", "--out", str(out)])
    watcher.join(5.0)
    err = capsys.readouterr().err
    assert code == EXIT_INTERRUPTED and pids, err
    if before == "page written":
        expected = f"cellcal: interrupted; the report was written to {page}"
    else:
        expected = (f"cellcal: interrupted while drawing the report: {page} was not written"
                    + (" (the one there is an earlier run's)" if before == "an earlier page" else "")
                    + f"; 'cellcal report {out} --out {page}' draws it from {out / 'report-data.json'}")
    assert ("\n" + err).endswith(f"\n{expected}\n"), err  # the last line, on a line of its own
    # the child and the worker it started are stopped (SIGINT to the child's own process group)
    deadline = time.monotonic() + 30.0
    while any(_alive(pid) for pid in pids) and time.monotonic() < deadline:
        time.sleep(0.02)
    assert not any(_alive(pid) for pid in pids)
    # what was written before stays whole: the result, the report's data and text; nothing half-written
    result = json.loads((out / "handeye.json").read_text())
    assert load_report_data(out)["handeye"]["result"] == result and result["mount"]
    assert f"result written to {out / 'handeye.json'}" in (out / "report.txt").read_text()
    left = sorted(p.name for p in out.iterdir())
    assert not [n for n in left if n.endswith(".tmp") or n == LOCK_NAME], left
    if before == "nothing":
        assert "report.html" not in left
        _draws_the_page(expected, page)
    elif before == "an earlier page":
        assert page.read_text() == "an earlier run's page"
    else:
        assert "drawn by this run" in page.read_text()


def _draws_the_page(line: str, page: Path) -> None:
    """The command ``line`` names draws ``page`` (with every picture)."""
    command = re.search(r"'(cellcal report [^']+)'", line)
    assert command is not None
    assert main(shlex.split(command.group(1))[1:]) == EXIT_OK
    text = page.read_text(encoding="utf-8")
    assert text.lower().startswith("<!doctype html") and text.count("<img ") >= 3


def _interrupt_at_picture(monkeypatch: pytest.MonkeyPatch, n: int) -> list[str]:
    """A real SIGINT to this process as the ``n``-th picture of a drawing in this process starts; the pictures
    started (their file names)."""
    draw = render_module._draw
    started: list[str] = []

    def counted(job: tuple[str, str, str, tuple[Any, ...]]) -> bytes:
        started.append(job[0])
        if len(started) == n:
            os.kill(os.getpid(), signal.SIGINT)
        return draw(job)

    monkeypatch.setattr(render_module, "_draw", counted)
    return started


@pytest.mark.parametrize("before", ["nothing", "an earlier page"])
def test_ctrl_c_while_calibrate_draws_its_report_in_its_own_process(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                                    capsys: pytest.CaptureFixture[str],
                                                                    before: str) -> None:
    out = tmp_path / "out"
    page = out / "report.html"
    if before == "an earlier page":
        out.mkdir()
        page.write_text("an earlier run's page")
    # no child draws a calibrate report: one would fail the drawing in other words
    monkeypatch.setattr(runs_module, "draw_command", lambda _dir: [sys.executable, "-c", "raise SystemExit(9)"])
    started = _interrupt_at_picture(monkeypatch, 3)
    code = main(["calibrate", "--out", str(out)])
    err = capsys.readouterr().err
    assert code == EXIT_INTERRUPTED and len(started) == 3, err
    expected = (f"cellcal: interrupted while drawing the report: {page} was not written"
                + (" (the one there is an earlier run's)" if before == "an earlier page" else "")
                + f"; 'cellcal report {out} --out {page}' draws it from {out / 'report-data.json'}")
    assert ("\n" + err).endswith(f"\n{expected}\n"), err
    result = json.loads((out / "result.json").read_text())
    assert result["schema"] == RESULT_SCHEMA and load_report_data(out)["calibrate"]["result"] == result
    left = sorted(p.name for p in out.iterdir())
    # nothing half-written, and no picture of this run: they are written once all are drawn
    assert not [n for n in left if n.endswith((".tmp", ".png")) or n == LOCK_NAME], left
    if before == "nothing":
        assert "report.html" not in left
        monkeypatch.undo()
        _draws_the_page(expected, page)
    else:
        assert page.read_text() == "an earlier run's page"


def test_a_drawing_that_fails_costs_the_calibrate_run_one_line(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                               capsys: pytest.CaptureFixture[str]) -> None:
    def broken(_job: object) -> bytes:
        raise RuntimeError("no such glyph")

    monkeypatch.setattr(render_module, "_draw", broken)
    out = tmp_path / "out"
    assert main(["calibrate", "--quiet", "--out", str(out)]) == EXIT_OK
    err = capsys.readouterr().err
    assert err == "cellcal: report not drawn: RuntimeError: no such glyph\n"
    assert json.loads((out / "result.json").read_text())["poses"]
    assert sorted(p.name for p in out.iterdir()) == ["report-data.json", "report.txt", "result.json"]


def test_ctrl_c_before_the_report_data_is_written_says_there_is_no_report(tmp_path: Path,
                                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    def interrupted(*_args: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(runs_module, "write_report_data", interrupted)
    report = RunReport("monitor", tmp_path / "out", "sim (cell 'test')", None)
    with pytest.raises(Interrupted) as caught:
        report.write()
    assert caught.value.line == f"cellcal: interrupted before the report was written: no report of this run in " \
                                f"{tmp_path / 'out'}"
    (tmp_path / "out").mkdir(exist_ok=True)
    (tmp_path / "out" / "report.html").write_text("an earlier run's page")
    with pytest.raises(Interrupted) as caught:
        report.write()
    assert caught.value.line.endswith(f" ({tmp_path / 'out' / 'report.html'} is an earlier run's)")


def test_a_drawing_that_takes_too_long_is_stopped_with_its_workers(tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    marker = tmp_path / "drawing"
    monkeypatch.setattr(runs_module, "draw_command", lambda _dir: [sys.executable, "-c", HELD_CHILD, str(marker), ""])
    page, note = runs_module.draw_in_child(tmp_path, timeout_s=2.0)
    assert page is None and note == "report not drawn: the drawing took more than 2 s"
    # whatever the child had started by then is gone with it (on an idle machine: the child and its worker)
    pids = [int(p) for p in marker.read_text().split()] if marker.exists() else []
    deadline = time.monotonic() + 30.0
    while any(_alive(pid) for pid in pids) and time.monotonic() < deadline:
        time.sleep(0.02)
    assert not any(_alive(pid) for pid in pids)
