"""``cellcal paper``: output, JSON, and exit status 2 with a one-line message on bad files."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import pytest
from repo_paths import TEST_DATA

from cellcal.core.cli import main

DATA = TEST_DATA
TABLE = DATA / "paper_table2.csv"


def expected_h1() -> dict[int, tuple[float, float]]:
    with (DATA / "paper_expected_H1.csv").open() as fh:
        return {int(r["perimeter_px"]): (float(r["law_of_cosines_deg"]), float(r["plane_fit_deg"]))
                for r in csv.DictReader(fh)}


def write_rows(path: Path, rows: list[list[str]], header: list[str] | None = None) -> Path:
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header or ["height", "perimeter_px", "point", "x_mm", "y_mm", "z_mm"])
        w.writerows(rows)
    return path


def table_rows() -> list[list[str]]:
    with TABLE.open() as fh:
        return list(csv.reader(fh))[1:]


def test_json_output_reproduces_paper(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["paper", str(TABLE), "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert len(rows) == 12
    keys = {"height", "perimeter_px", "law_of_cosines_deg", "plane_fit_deg",
            "law_of_cosines_error_pct", "plane_fit_error_pct"}
    assert all(keys <= set(r) for r in rows)
    exp = expected_h1()
    for r in rows:
        if r["height"] == "H1":
            loc, fit = exp[r["perimeter_px"]]
            assert abs(r["law_of_cosines_deg"] - loc) < 1e-7
            assert abs(r["plane_fit_deg"] - fit) < 1e-4
        assert r["plane_fit_error_pct"] == pytest.approx(abs(r["plane_fit_deg"] - 80) / 80 * 100)


def test_true_angle_changes_errors(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["paper", str(TABLE), "--json", "--true-angle", "75"]) == 0
    r = json.loads(capsys.readouterr().out)[0]
    assert r["law_of_cosines_error_pct"] == pytest.approx(abs(r["law_of_cosines_deg"] - 75) / 75 * 100)


def test_human_output_has_tables_and_averages(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["paper", str(TABLE)]) == 0
    out = capsys.readouterr().out
    assert "81.75414348" in out and "79.3466" in out
    assert "Averages by height" in out and "Averages by perimeter" in out
    avg_h1 = next(line for line in out.splitlines() if line.startswith("H1 ") and "76.3" in line)
    # mean of the four H1 law-of-cosines angles
    mean_h1 = sum(v[0] for v in expected_h1().values()) / 4
    assert f"{mean_h1:.8f}" in avg_h1
    assert "law of cosines 7.48 %, plane fit 1.02 %" in out


def run_bad(tmp_path: Path, rows: list[list[str]], capsys: pytest.CaptureFixture[str],
            header: list[str] | None = None) -> str:
    path = write_rows(tmp_path / "bad.csv", rows, header)
    assert main(["paper", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("cellcal: error:") and "\n" not in err
    assert "Traceback" not in err
    return err


def test_missing_column(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rows = [r[:5] for r in table_rows()]
    err = run_bad(tmp_path, rows, capsys, ["height", "perimeter_px", "point", "x_mm", "y_mm"])
    assert "missing column(s) z_mm" in err


def test_non_numeric_value_names_the_row(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rows = table_rows()
    rows[6][4] = "4O"  # line 8 of the file (header is line 1)
    err = run_bad(tmp_path, rows, capsys)
    assert "row 8" in err and "y_mm" in err and "'4O'" in err


def test_incomplete_set_names_data_set(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rows = table_rows()
    del rows[13]  # H1 / 30 px, P5
    err = run_bad(tmp_path, rows, capsys)
    assert "H1 / 30 px" in err and "row 11" in err and "missing P5" in err


def test_repeated_and_unknown_points(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rows = table_rows()
    rows[1][2] = "P1"
    assert "row 3: P1 repeated" in run_bad(tmp_path, rows, capsys)
    rows = table_rows()
    rows[0][2] = "P10"
    assert "row 2: point must be one of P1..P9" in run_bad(tmp_path, rows, capsys)


def test_perimeter_outside_image(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rows = [r for r in table_rows() if r[0] == "H1" and r[1] == "20"]
    for r in rows:
        r[1] = "120"
    assert "outside the 224x172 image" in run_bad(tmp_path, rows, capsys)


def test_empty_and_missing_files(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert "no data rows" in run_bad(tmp_path, [], capsys)
    assert main(["paper", str(tmp_path / "nope.csv")]) == 2
    assert "cannot read" in capsys.readouterr().err


def test_bad_true_angle(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["paper", str(TABLE), "--true-angle", "0"]) == 2
    assert "--true-angle" in capsys.readouterr().err


def test_console_script_subprocess(tmp_path: Path) -> None:
    exe = Path(sys.executable).with_name("cellcal")
    if not exe.exists():
        pytest.skip("cellcal console script not installed in this environment")
    ok = subprocess.run([str(exe), "paper", str(TABLE), "--json"], capture_output=True,
                        text=True, timeout=60, check=False)
    assert ok.returncode == 0, ok.stderr
    assert len(json.loads(ok.stdout)) == 12
    bad = write_rows(tmp_path / "bad.csv", [["H1", "20", "P1", "x", "1", "2"]])
    res = subprocess.run([str(exe), "paper", str(bad)], capture_output=True, text=True,
                         timeout=60, check=False)
    assert res.returncode == 2
    assert res.stderr.strip().splitlines() == [
        f"cellcal: error: {bad}: row 2: x_mm is not a number: 'x'"]
