"""The commands' reports end to end on the simulated cell: written by default, re-rendered from the JSON alone."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tomllib
from importlib import resources
from pathlib import Path

import pytest
from toml_files import write_toml

from cellcal.core.cli import main

pytest.importorskip("matplotlib")

REPORT_FILES = {"report.html", "report.txt", "report-data.json"}


def test_calibrate_writes_the_report_with_the_terminals_words(tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "run"
    assert main(["calibrate", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    names = {p.name for p in out.iterdir()}
    assert REPORT_FILES | {"result.json", "poses.png", "consistency.png"} <= names
    assert {f"pose-{n}-{kind}.png" for n in (1, 2, 3) for kind in ("image", "fit")} <= names
    text = (out / "report.txt").read_text()
    # the same words as the terminal, up to the line that says where the report is
    assert printed == text + f"report written to {out / 'report.html'}\n"
    assert "full frame (every valid pixel; [95 % interval]):" in text and "result written to" in text
    data = json.loads((out / "report-data.json").read_text())
    assert data["schema"] == "cellcal.report/1" and data["status"] == "ok"
    assert data["calibrate"]["result"] == json.loads((out / "result.json").read_text())


def test_report_renders_again_from_the_json_alone(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "run"
    assert main(["calibrate", "--quiet", "--out", str(out)]) == 0
    alone = tmp_path / "colleague"
    alone.mkdir()
    shutil.copy(out / "report-data.json", alone)  # nothing else: no result.json, no PNGs
    page = tmp_path / "again.html"
    capsys.readouterr()
    assert main(["report", str(alone), "--out", str(page)]) == 0
    assert capsys.readouterr().out == f"report written to {page}\n"
    first, again = (out / "report.html").read_text(), page.read_text()
    assert again.count("<img ") == first.count("<img ") == 8
    assert first == again  # the same data draws the same page


def test_report_opens_the_page_or_prints_its_path(tmp_path: Path) -> None:
    out = tmp_path / "run"
    assert main(["calibrate", "--quiet", "--out", str(out)]) == 0
    opened = tmp_path / "opened.txt"
    browser = tmp_path / "browser.sh"
    browser.write_text(f"#!/bin/sh\necho \"$1\" > {opened}\n")
    browser.chmod(0o755)
    env = {**os.environ, "BROWSER": str(browser)}
    done = subprocess.run([sys.executable, "-m", "cellcal.core.cli", "report", str(out)], env=env,
                          capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 0, done.stderr
    assert opened.read_text().strip() == (out / "report.html").resolve().as_uri()
    bare = {k: v for k, v in os.environ.items() if k not in ("BROWSER", "DISPLAY", "WAYLAND_DISPLAY")}
    bare["PATH"] = str(Path(sys.executable).parent)  # no console browser either
    done = subprocess.run([sys.executable, "-m", "cellcal.core.cli", "report", str(out)], env=bare,
                          capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 0, done.stderr
    assert done.stdout == f"no web browser found; the report is {(out / 'report.html').resolve()}\n"


def test_a_refused_gate_still_writes_a_report_that_shows_why(tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    doc = tomllib.loads(resources.files("cellcal.configs").joinpath("sim.toml").read_text())
    doc["sim"]["boxes"] = [{"center_xy_m": [0.3, 0.0], "size_m": [0.36, 0.28, 0.15]}]
    config = write_toml(tmp_path / "box.toml", doc)
    out = tmp_path / "run"
    assert main(["calibrate", "--config", str(config), "--out", str(out), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "quality gate 'expected_plane' failed" in err
    assert not (out / "result.json").exists()
    assert (out / "report.txt").read_text() == err  # the error line, word for word
    page = (out / "report.html").read_text()
    assert "The run failed:" in page and page.count("<img ") == 3
    assert {"pose-1-image.png", "pose-1-fit.png"} <= {p.name for p in out.iterdir()}


def test_no_report_writes_only_the_result(tmp_path: Path) -> None:
    out = tmp_path / "run"
    assert main(["calibrate", "--quiet", "--no-report", "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["result.json"]


def test_without_matplotlib_the_page_says_so_in_one_line(tmp_path: Path) -> None:
    out = tmp_path / "run"
    assert main(["calibrate", "--quiet", "--out", str(out)]) == 0
    (out / "report.html").unlink()
    code = ("import sys; sys.modules['matplotlib'] = None\n"
            "from cellcal.core.report.__main__ import main\n"
            f"raise SystemExit(main([{str(out)!r}]))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 0
    assert done.stderr == "report without pictures: matplotlib is not installed (pip install 'cellcal[plots]')\n"
    page = (out / "report.html").read_text()
    assert "<img " not in page and "matplotlib is not installed" in page and "tilt x (deg)" in page


def test_handeye_with_both_methods_reports_the_board_and_opencvs_methods(tmp_path: Path) -> None:
    pytest.importorskip("cv2.aruco")
    config = resources.files("cellcal.configs").joinpath("sim_handeye.toml")
    out = tmp_path / "he"
    assert main(["handeye", "--config", str(config), "--method", "both", "--quiet", "--out", str(out)]) == 0
    names = {p.name for p in out.iterdir()}
    assert REPORT_FILES | {"handeye.json", "handeye-mount.png", "handeye-residuals.png",
                           "handeye-observability.png", "handeye-charuco.png"} <= names
    result = json.loads((out / "handeye.json").read_text())
    page = (out / "report.html").read_text()
    for method in result["charuco"]["methods"]:
        assert f"<td class='l'>{method}</td>" in page
    assert f'data-value="{result["mount"]["rpy_deg"][0]!r}"' in page


def test_monitor_writes_its_report_on_exit(tmp_path: Path) -> None:
    out = tmp_path / "mon"
    assert main(["monitor", "--frames", "40", "--quiet", "--out", str(out)]) == 0
    data = json.loads((out / "report-data.json").read_text())
    series = data["monitor"]["cameras"]["sim"]["series"]
    assert data["status"] == "ok" and len(series["t"]) == len(series["tilt_deg"]) > 10
    assert (out / "monitor-sim.png").stat().st_size > 10_000
    assert "monitor finished after" in (out / "report.txt").read_text()


def test_monitor_writes_its_report_on_ctrl_c(tmp_path: Path) -> None:
    from fault_cells import CellcalProcess

    out = tmp_path / "mon"
    with CellcalProcess(["monitor", "--out", str(out)], announce=True) as run:
        run.wait_ready()
        # the baseline line is printed at the first frame measured against the baseline, after the report's
        # capture has kept that frame's drift values: from then on the series has a value
        assert run.wait_for_stdout_line("[sim] baseline ", timeout_s=120.0), (run.stdout_so_far(),
                                                                              run.stderr_so_far())
        run.interrupt()
        code, text, err = run.finish(timeout_s=120.0)
    assert code == 130, err
    assert "[sim] baseline " in text and "monitor interrupted after" in text
    data = json.loads((out / "report-data.json").read_text())
    assert data["status"] == "interrupted" and data["monitor"]["cameras"]["sim"]["series"]["t"]
    assert "monitor interrupted after" in (out / "report.txt").read_text()
    assert (out / "monitor-sim.png").stat().st_size > 10_000
    assert f"report written to {out / 'report.html'}" in text
