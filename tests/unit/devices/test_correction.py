"""devices/correction.py: a frame's depth correction, its leftover allowance, the correction file (ADR 0058)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from cellcal.devices.base import BackendContext
from cellcal.devices.correction import (
    CorrectedCamera,
    correct_frame,
    corrected_model,
    correction_from_table,
    leftover_allowance,
    load_correction_file,
    wiggle_passes,
)
from cellcal.devices.errors import CalibrationError, ConfigError
from cellcal.devices.measurement import MeasurementModel
from cellcal.devices.registry import default_registry
from cellcal.devices.systematic import SystematicError, field_basis, normalised_pixels
from cellcal.devices.types import Frame, Intrinsics

STEREO = MeasurementModel("stereo", baseline_m=0.075, focal_px=440.0, subpixel_bits=3, disparity_sigma_px=0.25)
TOF = MeasurementModel("tof", sigma_at_1m_m=0.003)
#: What float32 arithmetic keeps of a corrected point: a few ulps (2^-23 = 1.2e-7) relative.
FLOAT32_REL = 1e-6


def stereo_error(cov: bool = True) -> SystematicError:
    k = 7
    return SystematicError("stereo", fb_error=0.01, disparity_offset_px=0.3, field_order=2,
                           field_coeffs=(0.2, -0.1, 0.5, 0.1, -0.3),
                           covariance=(np.diag(np.arange(1, k + 1) * 1e-5) if cov else None))


def tof_error(cov: bool = True) -> SystematicError:
    k = 9
    c = np.diag(np.arange(1, k + 1) * 1e-8)
    c[2, 3] = c[3, 2] = 1e-8    # the wiggle's cos/sin correlated
    return SystematicError("tof", scale_error=0.003, offset_m=0.004, wiggle_cos_m=0.002, wiggle_sin_m=-0.0015,
                           wiggle_period_m=0.62, field_order=2, field_coeffs=(0.001, -0.0005, 0.002, 0.0, -0.001),
                           covariance=c if cov else None)


def make_frame(model: MeasurementModel, error: SystematicError, w: int = 160, h: int = 120
               ) -> tuple[Frame, np.ndarray]:
    """A tilted plane as a camera with ``error`` measures it, and the true points (H, W, 3)."""
    intr = Intrinsics(w, h, 150.0, 150.0, w / 2 - 0.5 + 3.0, h / 2 - 0.5 - 2.0)
    c, r = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    ray = np.stack([(c - intr.cx) / intr.fx, (r - intr.cy) / intr.fy, np.ones_like(c)], axis=-1)
    z = 0.5 + 0.1 * ray[..., 0] + 0.05 * ray[..., 1]
    u, v = normalised_pixels(w, h, intr.cx, intr.cy)
    if model.triangulating:
        z_meas = model.fb_px_m / error.distort(model.fb_px_m / z, u, v)
    else:
        r_true = z * np.linalg.norm(ray, axis=-1)
        z_meas = z * error.distort(r_true, u, v) / r_true
    xyz = (ray * z_meas[..., None]).astype(np.float32)
    valid = np.ones((h, w), bool)
    valid[::7, ::5] = False
    xyz[~valid] = np.nan
    frame = Frame(distance=np.linalg.norm(xyz, axis=-1).astype(np.float32), xyz=xyz,
                  amplitude=np.ones((h, w), np.float32), valid=valid, intrinsics=intr, timestamp=1.0, sequence=3,
                  measurement=model, metadata={"vendor": 1})
    return frame, ray * z[..., None]


@pytest.mark.parametrize("model,error", [(STEREO, stereo_error()), (TOF, tof_error())], ids=["stereo", "tof"])
def test_correct_frame_inverts_a_known_error_to_float32_precision(model: MeasurementModel,
                                                                  error: SystematicError) -> None:
    frame, truth = make_frame(model, error)
    before = np.nanmax(np.abs(frame.xyz - truth)[frame.valid])
    out = correct_frame(frame, error)
    rel = np.abs(out.xyz - truth)[frame.valid] / np.abs(truth[frame.valid]).max(axis=-1, keepdims=True)
    assert before > 1e-3                         # the error was millimetres
    assert rel.max() < FLOAT32_REL
    assert np.allclose(out.distance[frame.valid], np.linalg.norm(truth, axis=-1)[frame.valid], rtol=FLOAT32_REL)
    assert out.xyz.dtype == np.float32 and out.distance.dtype == np.float32
    assert np.array_equal(out.valid, frame.valid)                   # invalid pixels stay invalid, valid ones valid
    assert np.isnan(out.xyz[~frame.valid]).all() and np.isnan(out.distance[~frame.valid]).all()
    # the same as SystematicError.correct, pixel by pixel (float64)
    u, v = normalised_pixels(frame.intrinsics.width, frame.intrinsics.height, frame.intrinsics.cx,
                             frame.intrinsics.cy)
    if model.triangulating:
        want = model.fb_px_m / error.correct(model.fb_px_m / frame.xyz[..., 2].astype(float), u, v)
        got = out.xyz[..., 2]
    else:
        want, got = error.correct(frame.distance.astype(float), u, v), out.distance
    assert np.allclose(got[frame.valid], want[frame.valid], rtol=FLOAT32_REL, atol=0)
    assert out.amplitude is frame.amplitude and out.sequence == 3 and out.timestamp == 1.0
    assert out.metadata["vendor"] == 1 and out.metadata["depth_correction"]["applied"] is True
    assert out.metadata["depth_correction"]["vector"] == pytest.approx(list(error.vector))
    json.dumps(out.metadata)


def test_a_pixel_corrected_to_nothing_becomes_invalid() -> None:
    error = SystematicError("tof", offset_m=0.52)     # every range below 0.52 m corrected to <= 0
    frame, _ = make_frame(TOF, SystematicError("tof"))
    out = correct_frame(frame, error)
    gone = frame.valid & (frame.distance <= 0.52)
    assert gone.any() and (frame.valid & ~gone).any()
    assert not out.valid[gone].any() and out.valid[frame.valid & ~gone].all()
    assert np.isnan(out.xyz[gone]).all() and np.isnan(out.distance[gone]).all()
    stereo = SystematicError("stereo", disparity_offset_px=400.0)   # disparities ~130 px: none left
    frame, _ = make_frame(STEREO, SystematicError("stereo"))
    assert not correct_frame(frame, stereo).valid.any()


def test_the_allowance_after_correction_is_the_covariances() -> None:
    err = stereo_error()
    cov = np.asarray(err.covariance)
    b = field_basis([1, -1, 1, -1], [1, 1, -1, -1], 2)
    field = math.sqrt(max(float(row @ cov[2:, 2:] @ row) for row in b))   # the worst of the four corners
    want = (math.sqrt(cov[0, 0]), math.sqrt(cov[1, 1]), field)
    assert leftover_allowance(err) == pytest.approx(want)
    frame, _ = make_frame(STEREO, err)
    out = correct_frame(frame, err)
    assert out.measurement.allowance == pytest.approx(want)
    assert (out.measurement.scale_allowance, out.measurement.offset_allowance) == pytest.approx(want[:2])
    # ToF: the wiggle's largest 1-sigma amplitude is its own allowance, apart from the offset
    terr = tof_error()
    tcov = np.asarray(terr.covariance)
    wig = np.linalg.eigvalsh(tcov[2:4, 2:4])[-1]
    tb = field_basis([1, -1, 1, -1], [1, 1, -1, -1], 2)
    tfield = math.sqrt(max(float(row @ tcov[4:, 4:] @ row) for row in tb))
    assert leftover_allowance(terr) == pytest.approx((math.sqrt(tcov[0, 0]), math.sqrt(tcov[1, 1]), tfield))
    tmodel = corrected_model(MeasurementModel(kind="tof", sigma_at_1m_m=0.003), terr)
    assert tmodel.wiggle == pytest.approx((math.sqrt(wig), terr.wiggle_period_m))
    # no covariance: the model's allowance is kept
    plain = stereo_error(cov=False)
    assert leftover_allowance(plain) is None
    assert corrected_model(STEREO, plain) is STEREO
    assert correct_frame(make_frame(STEREO, plain)[0], plain).measurement.allowance == STEREO.allowance


def test_correcting_twice_or_the_wrong_kind_is_refused() -> None:
    frame, _ = make_frame(STEREO, stereo_error())
    out = correct_frame(frame, stereo_error())
    with pytest.raises(CalibrationError, match="corrected already"):
        correct_frame(out, stereo_error())
    with pytest.raises(CalibrationError, match="tof"):
        correct_frame(frame, tof_error())
    with pytest.raises(CalibrationError, match="disparity"):
        correct_frame(make_frame(TOF, tof_error())[0], stereo_error())


def test_wiggle_passes_meet_their_tolerance() -> None:
    assert wiggle_passes(SystematicError("tof")) == 0
    err = tof_error()
    n = wiggle_passes(err)
    amp = math.hypot(err.wiggle_cos_m, err.wiggle_sin_m) / (1 + err.scale_error)
    assert 1 <= n <= 8 and amp * (2 * math.pi / err.wiggle_period_m * amp) ** n <= 5e-8


# ------------------------------------------------------------------------------------------- the file
def _write(path: Path, data: object) -> Path:
    path.write_text(json.dumps(data))
    return path


def test_load_correction_file_reads_a_depthcal_result_and_a_bare_error(tmp_path: Path) -> None:
    err = tof_error()
    got = load_correction_file(_write(tmp_path / "a.json", {"schema": "cellcal.depthcal/1", "ok": True,
                                                            "correction": err.to_dict()}))
    assert got == err and got.covariance == err.covariance
    assert load_correction_file(_write(tmp_path / "b.json", err.to_dict())) == err


@pytest.mark.parametrize("content,reason", [
    (None, "file not found"),
    ("{", "not JSON"),
    ("[" * 100 + "]" * 100, "not JSON"),
    ("[1]", "expected a JSON object"),
    ('{"schema": "cellcal.handeye/1"}', "neither cellcal.depthcal/N"),
    ('{"schema": "cellcal.depthcal/1", "correction": null}', "holds no correction"),
    ('{"schema": "cellcal.depthcal/1", "correction": {"kind": "stereo", "fb_error": true}}',
     "correction.fb_error: must be a number"),
    ('{"schema": "cellcal.systematic/1", "kind": "tof", "bogus": 1}', "systematic.bogus: unknown key"),
])
def test_a_bad_correction_file_is_one_line_naming_the_key(tmp_path: Path, content: str | None, reason: str) -> None:
    path = tmp_path / "depthcal.json"
    if content is not None:
        path.write_text(content)
    with pytest.raises(ConfigError) as info:
        load_correction_file(path, source="cell.toml")
    text = str(info.value)
    assert "\n" not in text and reason in text and "camera.correction.file" in text and "cell.toml" in text


def test_a_directory_is_no_correction_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="directory"):
        load_correction_file(tmp_path)


def test_the_table_resolves_the_file_against_the_configuration(tmp_path: Path, monkeypatch: pytest.MonkeyPatch
                                                               ) -> None:
    config = tmp_path / "cell" / "cell.toml"
    config.parent.mkdir()
    config.write_text("")
    _write(config.parent / "depthcal.json", stereo_error().to_dict())
    monkeypatch.chdir(tmp_path)   # not where the file is
    ctx = BackendContext(source=str(config), section="camera")
    err, file = correction_from_table({"file": "depthcal.json"}, ctx)
    assert err == stereo_error() and Path(file) == config.parent / "depthcal.json"
    with pytest.raises(ConfigError, match=r"camera\.correction\.path.*unknown key"):
        correction_from_table({"file": "depthcal.json", "path": "x"}, ctx)
    with pytest.raises(ConfigError, match=r"'camera\.correction\.file'.*missing"):
        correction_from_table({}, ctx)
    with pytest.raises(ConfigError, match=r"'camera\.correction'.*expected a table"):
        correction_from_table("depthcal.json", ctx)


# ------------------------------------------------------------------------------------------- the camera
def test_the_registry_wraps_a_corrected_camera(tmp_path: Path) -> None:
    config = tmp_path / "cell.toml"
    config.write_text("")
    err = SystematicError("tof", offset_m=0.002, covariance=np.diag([1e-8, 1e-6, 0.0, 0.0]))
    _write(tmp_path / "depthcal.json", {"schema": "cellcal.depthcal/1", "correction": err.to_dict()})
    section = {"backend": "sim", "width": 64, "height": 48, "correction": {"file": "depthcal.json"}}
    ctx = BackendContext(source=str(config), section="camera")
    camera = default_registry().create_camera(section, ctx)
    assert isinstance(camera, CorrectedCamera) and camera.correction == err
    raw = default_registry().create_camera(section, ctx, apply_correction=False)
    assert not isinstance(raw, CorrectedCamera)
    assert camera.measurement_model.allowance == pytest.approx((1e-4, 1e-3, 0.0))
    assert camera.world is camera.raw.world       # the inner camera's attributes
    with camera:
        frame = camera.capture()
        plain = camera.raw_capture()
    assert frame.metadata["depth_correction"]["file"] == str(tmp_path / "depthcal.json")
    assert "depth_correction" not in plain.metadata
    assert frame.measurement.allowance == pytest.approx((1e-4, 1e-3, 0.0))
    assert camera.describe_correction().startswith(str(tmp_path / "depthcal.json"))
    bad = {**section, "correction": {"file": "nothere.json"}}
    with pytest.raises(ConfigError, match=r"camera\.correction\.file.*not found"):
        default_registry().create_camera(bad, ctx, apply_correction=False)   # checked even when not applied
    stereo = _write(tmp_path / "stereo.json", stereo_error().to_dict())
    with pytest.raises(ConfigError, match=r"camera\.correction\.file.*tof"):
        default_registry().create_camera({**section, "correction": {"file": str(stereo)}}, ctx)
