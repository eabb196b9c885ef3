"""The flatness gate in sensor terms (ADR 0060): a bend within the camera's field allowance is accepted
and said so, a bend beyond it is refused as a bend (where, how large), a box is refused as before.

The camera is the stereo sim's (configs/sim_oak.toml: an OAK-D 400P pair, 3 subpixel bits, 0.25 px
disparity noise) looking at a table 0.55 m away at an 80 deg inclination; its systematic error is
drawn here with ``SystematicError.distort`` (a radial bow: the field's value at the image corner,
zero at the centre), as the sim's ``[sim.systematic]`` defaults do (0.5 px); the last tests use the
stereo sim itself with those defaults.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from cellcal.core.calibration.config import look_at_pose
from cellcal.core.methods.fullframe import check_gates, fit_full_frame
from cellcal.core.methods.fullframe.staircase import lattice_share
from cellcal.devices.errors import CalibrationQualityError
from cellcal.devices.measurement import MeasurementModel
from cellcal.devices.pose import Pose
from cellcal.devices.systematic import SystematicError, normalised_pixels
from cellcal.devices.types import Frame, Intrinsics
from cellcal.sims.scene import Box, Scene
from cellcal.sims.stereo import SimStereoCamera, SimStereoConfig
from cellcal.sims.systematic import SystematicConfig
from cellcal.sims.world import SimWorld

W, H = 640, 400
FX = 320.0 / math.tan(math.radians(36.0))          # 440.4 px: 72 deg HFOV
B = 0.075
INTR = Intrinsics(width=W, height=H, fx=FX, fy=FX, cx=(W - 1) / 2, cy=(H - 1) / 2)


def _model(**kw: float) -> MeasurementModel:
    return MeasurementModel(kind="stereo", baseline_m=B, focal_px=FX, subpixel_bits=3, disparity_sigma_px=0.25,
                            source="sim", **kw)


def _bow(bow_px: float) -> SystematicError:
    """A radial bow: ``bow · r²/r_corner²`` (the sim's ``disparity_bow_px``), as field monomials u², v²."""
    a2 = (W / H) ** 2
    return SystematicError("stereo", field_order=2, field_coeffs=(0.0, 0.0, bow_px * a2 / (a2 + 1), 0.0,
                                                                  bow_px / (a2 + 1)))


def _frame(bow_px: float, model: MeasurementModel, box_m: float = 0.0, seed: int = 1) -> Frame:
    """A table tilted 10 deg about x, 0.55 m along the axis; ``box_m``: a box top that high in the middle."""
    rng = np.random.default_rng(seed)
    cols, rows = np.meshgrid(np.arange(W), np.arange(H))
    x, y = (cols - INTR.cx) / FX, (rows - INTR.cy) / FX
    t = math.radians(10.0)
    n = np.array([0.0, -math.sin(t), -math.cos(t)])
    z = 0.55 * math.cos(t) / -(n[0] * x + n[1] * y + n[2])               # the plane's Z-depth per pixel
    if box_m:
        inside = (abs(cols - W / 2) < W / 4) & (abs(rows - H / 2) < H / 3)
        z = np.where(inside, (0.55 * math.cos(t) - box_m) / -(n[0] * x + n[1] * y + n[2]), z)
    u, v = normalised_pixels(W, H, INTR.cx, INTR.cy)
    d = _bow(bow_px).distort(FX * B / z, u, v) + 0.25 * rng.standard_normal(z.shape)
    d = np.round(d * 8.0) / 8.0
    zm = FX * B / d
    xyz = np.stack([x * zm, y * zm, zm], axis=2).astype(np.float32)
    return Frame(distance=np.linalg.norm(xyz, axis=2).astype(np.float32), xyz=xyz,
                 amplitude=np.ones((H, W), np.float32), valid=np.ones((H, W), bool), intrinsics=INTR,
                 timestamp=0.0, sequence=0, measurement=model)


def test_an_ideal_flat_table_passes_without_a_note() -> None:
    result = fit_full_frame(_frame(0.0, _model()))
    check_gates(result)
    assert not any("bend" in note for note in result.interval_notes)


def test_the_sims_default_bow_is_accepted_within_the_allowance_and_said_so() -> None:
    frame = _frame(0.5, _model())
    ideal = fit_full_frame(frame.__class__(**{**frame.__dict__, "measurement": _model(field_allowance=0.0)}))
    with pytest.raises(CalibrationQualityError) as info:                 # a camera stated ideal: a bend
        check_gates(ideal)
    assert info.value.gate == "flatness" and "a bend of " in str(info.value)
    result = fit_full_frame(frame)                                       # the default allowance: 0.5 px
    assert result.gates["flatness"][2], result.flatness_where
    notes = [n for n in result.interval_notes if n.startswith("flatness accepted a bend of ")]
    assert notes and "within the camera's" in notes[0] and "field allowance" in notes[0]


def test_a_bend_beyond_the_allowance_is_refused_as_a_bend_and_says_where() -> None:
    result = fit_full_frame(_frame(1.5, _model()))
    with pytest.raises(CalibrationQualityError) as info:
        check_gates(result)
    text = str(info.value)
    assert info.value.gate == "flatness" and info.value.unit == "m"
    assert "a bend of " in text and "beyond the camera's" in text and "field allowance" in text
    assert "corner" in text and "columns" in text and "rows" in text
    # the bend is a radial 1.5 px: at 0.55-0.65 m, 1.5 px less the plane's share is 10-25 mm of depth
    size_mm = float(text.split("a bend of ")[1].split(" mm")[0])
    allowance_mm = float(text.split("beyond the camera's ")[1].split(" mm")[0])
    assert 8.0 < size_mm < 25.0 and 2.0 < allowance_mm < size_mm / 1.5


@pytest.mark.parametrize("bow_px", [0.0, 0.5])
def test_a_box_on_the_table_still_fails_flatness(bow_px: float) -> None:
    result = fit_full_frame(_frame(bow_px, _model(), box_m=0.05))
    with pytest.raises(CalibrationQualityError) as info:
        check_gates(result)
    assert info.value.gate == "flatness"
    assert info.value.value > 0.03                                       # the box top, 50 mm up
    assert "a bend of " not in str(info.value) and "a staircase of " not in str(info.value)


def test_lattice_share_finds_a_pitch_a_few_per_cent_off() -> None:
    k = np.repeat(np.arange(40, 60), 50) * 1.02                          # levels on a 2 % longer pitch
    assert lattice_share(k) > 0.95
    assert lattice_share(k + np.random.default_rng(0).uniform(-0.5, 0.5, k.size)) < 0.5


# ---------------------------------------------------------------------- the stereo sim itself ([sim.systematic])
UP = np.array([0.0, 0.0, 1.0])


def _sim_frame(systematic: SystematicConfig, boxes: tuple[Box, ...] = (), height_m: float = 0.59) -> Frame:
    """configs/sim_oak.toml's camera over the table from one of the plan's heights at 80 deg."""
    world = SimWorld(Scene(np.zeros(3), UP, boxes), Pose.identity(), seed=3, systematic=systematic)
    cam = SimStereoCamera(SimStereoConfig(seed=3), world=world)
    return cam.render(look_at_pose(np.array([0.3, 0.0, 0.0]), UP, height_m, math.radians(80.0), "x"))


@pytest.mark.parametrize("height_m", [0.46, 0.61])
def test_the_stereo_sims_flat_table_is_accepted_with_its_default_bow_and_says_so(height_m: float) -> None:
    result = fit_full_frame(_sim_frame(SystematicConfig(), height_m=height_m))
    check_gates(result)                                                  # every gate passes
    notes = [n for n in result.interval_notes if n.startswith("flatness accepted a bend of ")]
    assert len(notes) == 1 and "within the camera's" in notes[0]         # measured: 2.5-4.3 mm within 3.7-6.5 mm


def test_the_stereo_sims_table_with_a_larger_bow_is_refused_as_a_bend() -> None:
    result = fit_full_frame(_sim_frame(SystematicConfig(disparity_bow_px=1.5)))
    with pytest.raises(CalibrationQualityError) as info:
        check_gates(result)
    text = str(info.value)
    assert info.value.gate == "flatness" and "a bend of " in text and "beyond the camera's" in text


@pytest.mark.parametrize("systematic", [SystematicConfig(), SystematicConfig.off()], ids=["default", "off"])
def test_a_box_on_the_stereo_sims_table_still_fails_flatness(systematic: SystematicConfig) -> None:
    result = fit_full_frame(_sim_frame(systematic, (Box((0.3, 0.0), (0.36, 0.28, 0.05)),)))
    with pytest.raises(CalibrationQualityError) as info:
        check_gates(result)
    assert info.value.gate == "flatness"
    assert 0.04 < info.value.value < 0.06                                # its top, 50 mm up (47.8 / 49.8 mm)
    assert "planar region" in str(info.value)                            # refused as before, not as a bend


# ---------------------------------------------------------------------- a ToF camera: the allowance in metres
def _tof_frame(bow_m: float, **allowance: float) -> Frame:
    """A 224x172 ToF camera (0.3 mm range noise) over a plane 0.6 m away tilted 10 deg; a radial range bow."""
    w, h, f = 224, 172, 200.0
    intr = Intrinsics(width=w, height=h, fx=f, fy=f, cx=(w - 1) / 2, cy=(h - 1) / 2)
    cols, rows = np.meshgrid(np.arange(w), np.arange(h))
    x, y = (cols - intr.cx) / f, (rows - intr.cy) / f
    t = math.radians(10.0)
    z = 0.6 * math.cos(t) / (math.sin(t) * y + math.cos(t))
    u, v = normalised_pixels(w, h, intr.cx, intr.cy)
    a2 = (w / h) ** 2
    r = z * np.sqrt(x * x + y * y + 1.0) + bow_m * (a2 * u * u + v * v) / (a2 + 1.0)
    r += 0.0003 * np.random.default_rng(1).standard_normal(r.shape)
    ray = np.stack([x, y, np.ones_like(x)], axis=2)
    ray /= np.linalg.norm(ray, axis=2, keepdims=True)
    model = MeasurementModel(kind="tof", sigma_at_1m_m=0.0003, distance_exponent=0.0, source="sim", **allowance)
    return Frame(distance=r.astype(np.float32), xyz=(ray * r[..., None]).astype(np.float32),
                 amplitude=np.ones((h, w), np.float32), valid=np.ones((h, w), bool), intrinsics=intr,
                 timestamp=0.0, sequence=0, measurement=model)


def test_a_tof_bend_is_judged_against_the_allowance_in_metres() -> None:
    accepted = fit_full_frame(_tof_frame(0.0025))                        # the ToF default: 2 mm at the corner
    check_gates(accepted)
    assert any(n.startswith("flatness accepted a bend of ") and "within the camera's 2 mm field allowance" in n
               for n in accepted.interval_notes)                         # measured: a 1.56 mm bend
    with pytest.raises(CalibrationQualityError) as info:                 # a camera stated ideal
        check_gates(fit_full_frame(_tof_frame(0.0025, field_allowance=0.0)))
    assert "a bend of " in str(info.value) and "beyond the camera's 0 mm field allowance" in str(info.value)
    with pytest.raises(CalibrationQualityError) as info:                 # 8 mm at the corner: beyond 2 mm
        check_gates(fit_full_frame(_tof_frame(0.008)))
    assert info.value.gate == "flatness" and "beyond the camera's 2 mm field allowance" in str(info.value)
