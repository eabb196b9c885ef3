"""Report data of real simulated runs (as ``cellcal calibrate`` makes it) and the decoding of the report's PNGs."""

from __future__ import annotations

import copy
import json
import tomllib
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from cellcal.core.calibration.calibrator import Calibrator, build_devices
from cellcal.core.calibration.config import parse_config
from cellcal.devices.errors import CalibrationQualityError

SIM: dict[str, Any] = tomllib.loads(resources.files("cellcal.configs").joinpath("sim.toml").read_text())


def box_document() -> dict[str, Any]:
    """sim.toml with a 0.15 m box under the camera: the table the cell expects is not the plane it sees."""
    doc = copy.deepcopy(SIM)
    doc["sim"]["boxes"] = [{"center_xy_m": [0.3, 0.0], "size_m": [0.36, 0.28, 0.15]}]
    return doc


def thin_plate_document() -> dict[str, Any]:
    """sim.toml with an 8 mm plate on the table under the camera: the surface is not flat."""
    doc = copy.deepcopy(SIM)
    doc["sim"]["boxes"] = [{"center_xy_m": [0.3, 0.0], "size_m": [0.16, 0.16, 0.008]}]
    return doc


def corner_box_document() -> dict[str, Any]:
    """sim.toml with a 0.1 m box at the image's edge and every coverage cell required to hold the plane."""
    doc = copy.deepcopy(SIM)
    doc["sim"]["boxes"] = [{"center_xy_m": [0.4, 0.1], "size_m": [0.08, 0.08, 0.1]}]
    doc.setdefault("full_frame", {})["min_coverage"] = 1.0
    return doc


def run_report(doc: dict[str, Any], out: Path) -> tuple[dict[str, Any], Exception | None]:
    """Run ``doc``'s plan as ``cellcal calibrate`` does with its report; the report data and the error."""
    from cellcal.core.report.runs import CalibrationReport

    config = parse_config(doc, "<test>")
    camera, arm = build_devices(config)
    report = CalibrationReport(config, camera, out)
    calibrator = Calibrator(config, report.camera, arm, observer=report.observer())  # type: ignore[arg-type]
    error: Exception | None = None
    try:
        report.finished(json.loads(json.dumps(calibrator.run())))
    except CalibrationQualityError as exc:
        error = exc
        report.failed_run(exc, f"cellcal: error: {exc}", calibrator.poses)
    return json.loads(json.dumps(report.data)), error


def decode(png: bytes) -> np.ndarray:
    """The PNG as an (H, W, 3) RGB uint8 image."""
    import cv2

    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    bgr = cv2.imdecode(np.frombuffer(png, dtype=np.uint8), cv2.IMREAD_COLOR)
    assert bgr is not None
    return bgr[..., ::-1]


def rgb(hex_colour: str) -> np.ndarray:
    return np.array([int(hex_colour[i:i + 2], 16) for i in (1, 3, 5)])


def share_of_class_in_colour(image: np.ndarray, classes: np.ndarray, cls: int, colour: str) -> float:
    """Of the class map's pixels of ``cls`` (away from other classes), the share drawn in ``colour`` in the panel."""
    from cellcal.core.report import figures

    left, bottom, width, height = figures.CLASS_AXES
    h_img, w_img = image.shape[:2]
    x0, x1 = left * w_img, (left + width) * w_img
    y0, y1 = (1 - bottom - height) * h_img, (1 - bottom) * h_img
    mask = classes == cls
    # only pixels whose 3x3 neighbourhood is the same class (the drawing resamples at the borders)
    core = mask.copy()
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            core &= np.roll(np.roll(mask, dr, 0), dc, 1)
    core[[0, -1], :] = False
    core[:, [0, -1]] = False
    rows, cols = np.nonzero(core)
    hm, wm = classes.shape
    ys = np.floor(y0 + (rows + 0.5) / hm * (y1 - y0)).astype(int)
    xs = np.floor(x0 + (cols + 0.5) / wm * (x1 - x0)).astype(int)
    drawn = image[ys, xs].astype(int)
    return float(np.mean(np.all(np.abs(drawn - rgb(colour)) <= 3, axis=1)))
