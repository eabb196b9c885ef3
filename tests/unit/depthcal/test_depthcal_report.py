"""``cellcal depthcal``'s words and pictures (core/depthcal/report.py) and the frames kept for ``--resume`` (run.py)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from cellcal.core.depthcal.report import format_summary, held_out_residuals
from cellcal.core.depthcal.run import load_frames, save_frames
from cellcal.core.depthcal.view import DepthcalView
from cellcal.devices.errors import CalibrationError
from cellcal.devices.measurement import MeasurementModel
from cellcal.devices.pose import Pose
from cellcal.devices.systematic import SystematicError, normalised_pixels
from cellcal.devices.types import Frame, Intrinsics

HEIGHT_M = 0.5
STEREO = MeasurementModel(kind="stereo", baseline_m=0.075, focal_px=450.0, disparity_sigma_px=0.1)
TOF = MeasurementModel(kind="tof", sigma_at_1m_m=0.003)


def plane_view(model: MeasurementModel, error: SystematicError) -> DepthcalView:
    """A camera 0.5 m above the plane z = 0 looking straight down, its depth distorted by ``error``."""
    intr = Intrinsics(width=40, height=30, fx=40.0, fy=40.0, cx=19.5, cy=14.5)
    cols, rows = np.meshgrid(np.arange(intr.width), np.arange(intr.height))
    ray = np.stack([(cols - intr.cx) / intr.fx, (rows - intr.cy) / intr.fy, np.ones(cols.shape)], axis=-1)
    ray /= np.linalg.norm(ray, axis=-1, keepdims=True)
    r_true = HEIGHT_M / ray[..., 2]
    u, v = normalised_pixels(intr.width, intr.height, intr.cx, intr.cy)
    if model.kind == "stereo":
        fb = model.fb_px_m
        z = fb / error.distort(fb / (r_true * ray[..., 2]), u, v)
        r = z / ray[..., 2]
    else:
        r = error.distort(r_true, u, v)
    xyz = (r[..., None] * ray).astype(np.float32)
    frame = Frame(distance=r.astype(np.float32), xyz=xyz, amplitude=np.ones(r.shape, np.float32),
                  valid=np.ones(r.shape, bool), intrinsics=intr, timestamp=1.0, sequence=3, measurement=model,
                  metadata={"device_timestamp_s": 2.5})
    flange = Pose.from_rotation_matrix(np.diag([1.0, -1.0, -1.0]), [0.0, 0.0, HEIGHT_M])
    return DepthcalView(frame, flange, "pose 1")


@pytest.mark.parametrize(("model", "error", "tol"), [
    (STEREO, SystematicError("stereo", fb_error=0.01, disparity_offset_px=0.2, field_order=2,
                             field_coeffs=(0.0, 0.0, 0.3, 0.0, 0.2)), 1e-4),
    (TOF, SystematicError("tof", scale_error=0.004, offset_m=0.003, field_order=1, field_coeffs=(0.002, -0.001)),
     1e-6),
])
def test_the_residual_maps_show_the_error_before_and_nothing_after(model: MeasurementModel, error: SystematicError,
                                                                   tol: float) -> None:
    view = plane_view(model, error)
    doc = {"kind": model.kind, "plane": {"normal_base": [0.0, 0.0, 1.0], "offset_m": 0.0}}
    before, after = held_out_residuals(view, Pose.identity(), doc, error)
    intr = view.frame.intrinsics
    u, v = normalised_pixels(intr.width, intr.height, intr.cx, intr.cy)
    true = (model.fb_px_m / HEIGHT_M) if model.kind == "stereo" else HEIGHT_M / np.cos(
        np.arctan(np.hypot((np.arange(intr.width)[None, :] - intr.cx), (np.arange(intr.height)[:, None] - intr.cy))
                  / intr.fx))
    assert np.allclose(before, error.distort(true, u, v) - true, atol=tol)  # float32 frames
    assert np.nanmax(np.abs(after)) < tol


def test_the_summary_speaks_in_percent_mm_and_px_and_says_how_to_apply(tmp_path: Path) -> None:
    error = SystematicError("stereo", fb_error=0.0065, disparity_offset_px=-0.03, field_order=2,
                            field_coeffs=(0.0, 0.0, 0.3, 0.0, 0.2),
                            covariance=tuple(tuple(0.0 if i != j else 1e-6 for j in range(7)) for i in range(7)))
    doc: dict[str, Any] = {
        "kind": "stereo", "correction": error.to_dict(), "correction_sigma": {"fb_error": 0.0005,
                                                                             "disparity_offset_px": 0.02},
        "field_order": 2, "order_scores": {"0": 0.28, "1": 0.28, "2": 0.256},
        "holdout": {"rms_before": 0.30, "rms_after": 0.256, "noise_only_rms": 0.253},
        "views": [{"name": "pose 4", "held_out": True, "rms_before": 0.3, "rms_after": 0.256, "rms_before_m": 0.003,
                   "rms_after_m": 0.0025}],
        "plane": {"normal_base": [0.0, 0.0, 1.0], "offset_m": -0.00012},
        "observability": {"parameters": [{"name": "fb_error", "observable": True},
                                         {"name": "field_u2v0", "observable": False, "reason": "one inclination"}]},
        "coverage": "3 heights (385-685 mm)", "notes": ["intervals widened 1.05x"]}
    text = format_summary(doc, tmp_path / "depthcal.json")
    assert "f*B scale error              +0.65 ± 0.098 %" in text
    assert "disparity offset             -0.03 ± 0.0392 px" in text
    assert "order 2, up to 0.5 px at the image corners" in text
    assert "2: 0.256 px (chosen)" in text and "0.3 px before -> 0.256 px after (3 -> 2.5 mm in depth)" in text
    assert "field_u2v0 NOT seen: one inclination" in text and "the plan: 3 heights" in text
    assert "note: intervals widened 1.05x" in text
    assert f'[camera.correction] file = "{tmp_path / "depthcal.json"}"' in text


def test_frames_kept_for_resume_come_back_bit_for_bit(tmp_path: Path) -> None:
    frame = plane_view(TOF, SystematicError("tof", offset_m=0.001)).frame
    save_frames(tmp_path / "pose-001.npz", [frame, frame])
    back = load_frames(tmp_path / "pose-001.npz")
    assert len(back) == 2
    for name in ("distance", "xyz", "amplitude", "valid"):
        assert np.array_equal(getattr(back[1], name), getattr(frame, name))
    assert back[0].intrinsics == frame.intrinsics and back[0].measurement == frame.measurement
    assert back[0].metadata == frame.metadata and back[0].sequence == 3
    with pytest.raises(CalibrationError, match="missing"):
        load_frames(tmp_path / "pose-002.npz")
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(CalibrationError, match="damaged"):
        load_frames(tmp_path / "bad.npz")
