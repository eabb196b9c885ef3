"""``cellcal board``: the printed page is the configured board, at the stated scale, on a page of its size."""

from __future__ import annotations

import re
import struct
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from repo_paths import REPO_ROOT

from cellcal.core.calibration.config import load_config
from cellcal.core.cli import main
from cellcal.core.handeye.board_config import board_spec
from cellcal.core.handeye.charuco import BoardSpec
from cellcal.devices.errors import ConfigError

CONFIG = REPO_ROOT / "configs" / "sim_handeye.toml"
INCH_M = 0.0254


def png_px_per_m(path: Path) -> int:
    """The PNG's pHYs resolution (pixels per metre, same on both axes)."""
    data = path.read_bytes()
    at = data.index(b"pHYs")
    x, y, unit = struct.unpack(">IIB", data[at + 4:at + 13])
    assert unit == 1 and x == y
    return x


def pdf_page_pt(path: Path) -> tuple[float, float]:
    """Width and height of the PDF's (only) page from its MediaBox, points."""
    boxes = re.findall(rb"/MediaBox\s*\[\s*([-\d.]+)\s+([-\d.]+)\s+([-\d.]+)\s+([-\d.]+)\s*\]", path.read_bytes())
    assert len(boxes) == 1
    x0, y0, x1, y1 = (float(v) for v in boxes[0])
    return x1 - x0, y1 - y0


def detect(path: Path, spec: BoardSpec) -> tuple[np.ndarray, np.ndarray]:
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    corners, ids, _, _ = cv2.aruco.CharucoDetector(spec.board()).detectBoard(image)
    assert ids is not None
    return corners.reshape(-1, 2), ids.ravel()


def corner_spacing_px(corners: np.ndarray, ids: np.ndarray, columns: int) -> float:
    """Mean distance between corners that are neighbours along a row of the board, pixels."""
    at = dict(zip(ids.tolist(), corners, strict=True))
    steps = [np.linalg.norm(at[i + 1] - at[i]) for i in at if i + 1 in at and (i + 1) % (columns - 1) != 0]
    return float(np.mean(steps))


def test_the_shipped_board_is_found_whole_at_its_printed_scale(tmp_path: Path,
                                                               capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["board", "--config", str(CONFIG), "--out", str(tmp_path / "board")]) == 0
    out = capsys.readouterr().out
    spec = board_spec(load_config(CONFIG))
    assert spec == BoardSpec((7, 5), 0.04, 0.75, "4X4_50")
    png, pdf = tmp_path / "board.png", tmp_path / "board.pdf"
    corners, ids = detect(png, spec)
    assert sorted(ids.tolist()) == list(range(6 * 4))  # every inner corner of a 7 x 5 board
    # 300 dpi asked: 472 px per 40 mm square (299.72 dpi), stated in the PNG and on the command line
    ppm = png_px_per_m(png)
    assert ppm == 11800 and abs(ppm * INCH_M - 300.0) < 0.5
    assert corner_spacing_px(corners, ids, 7) == pytest.approx(0.04 * ppm, abs=0.2)
    assert "299.72 dpi (472 px per square)" in out and "board 280 x 200 mm" in out
    # the PDF's page is the PNG's page at its physical size: the 280 x 200 mm board plus margins
    height_px, width_px = cv2.imread(str(png), cv2.IMREAD_GRAYSCALE).shape
    width_m, height_m = width_px / ppm, height_px / ppm
    w_pt, h_pt = pdf_page_pt(pdf)
    assert w_pt == pytest.approx(width_m / INCH_M * 72, abs=0.01)
    assert h_pt == pytest.approx(height_m / INCH_M * 72, abs=0.01)
    assert 0.300 < width_m < 0.31 and 0.24 < height_m < 0.25
    assert "the bar must be 100 mm and a square 40 mm" in out


def test_another_board_at_another_dpi(tmp_path: Path) -> None:
    cfg = tmp_path / "c.toml"
    cfg.write_text(CONFIG.read_text().replace("[handeye]\n", "[handeye]\ncharuco_squares = [5, 4]\n"
                                              "charuco_square_m = 0.025\ncharuco_dictionary = \"5X5_100\"\n", 1)
                   .replace("squares = [7, 5]\nsquare_m = 0.04\nmarker_ratio = 0.75\ndictionary = \"4X4_50\"\n", ""))
    cfg.write_text(re.sub(r"(?m)^charuco_(squares|square_m|dictionary) = .*# .*\n", "", cfg.read_text()))
    cfg.write_text(cfg.read_text().replace("[sim.charuco]\n", "[sim.charuco]\nsquares = [5, 4]\nsquare_m = 0.025\n"
                                           "dictionary = \"5X5_100\"\n"))
    assert main(["board", "--config", str(cfg), "--out", str(tmp_path / "b.png"), "--dpi", "200"]) == 0
    spec = BoardSpec((5, 4), 0.025, 0.75, "5X5_100")
    corners, ids = detect(tmp_path / "b.png", spec)
    assert len(ids) == 4 * 3
    ppm = png_px_per_m(tmp_path / "b.png")
    assert ppm == round(round(0.025 * 200 / INCH_M) / 0.025)  # 197 px per 25 mm square
    assert corner_spacing_px(corners, ids, 5) == pytest.approx(0.025 * ppm, abs=0.2)
    assert not (tmp_path / "b.pdf").exists()  # a .png asks for the PNG only
    width_px = cv2.imread(str(tmp_path / "b.png"), cv2.IMREAD_GRAYSCALE).shape[1]
    assert width_px / ppm >= 0.124  # the 100 mm bar fits beside a 125 mm board, with margins


def test_a_board_the_sim_does_not_show_is_refused_naming_both_keys(tmp_path: Path,
                                                                   capsys: pytest.CaptureFixture[str]) -> None:
    cfg = tmp_path / "c.toml"
    cfg.write_text(CONFIG.read_text().replace("charuco_square_m = 0.04 ", "charuco_square_m = 0.05 "))
    with pytest.raises(ConfigError, match=r"\[sim.charuco\] square_m = 0.04 but \[handeye\] charuco_square_m = "
                                          r"0.05"):
        board_spec(load_config(cfg))
    assert main(["board", "--config", str(cfg), "--out", str(tmp_path / "b")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "charuco_square_m" in err[0]


def test_bad_suffix_is_one_line_and_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["board", "--config", str(CONFIG), "--out", str(tmp_path / "b.svg")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "expected a .png or .pdf file" in err[0]
    assert not list(tmp_path.iterdir())


def test_without_matplotlib_the_png_is_written_and_the_pdf_named(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setitem(sys.modules, "matplotlib.figure", None)  # import fails as if the extra were missing
    assert main(["board", "--config", str(CONFIG), "--out", str(tmp_path / "b"), "--dpi", "100"]) == 0
    out = capsys.readouterr().out
    assert (tmp_path / "b.png").exists() and not (tmp_path / "b.pdf").exists()
    assert "b.pdf not written" in out and "plots" in out
    assert main(["board", "--config", str(CONFIG), "--out", str(tmp_path / "c.pdf"), "--dpi", "100"]) == 1
    assert "plots" in capsys.readouterr().err and not (tmp_path / "c.pdf").exists()
