"""A wide-angle O3R225 head (fisheye models 2 / 3): intrinsics carry OpenCV's fisheye model, not a pinhole part,
and the full-frame fit on its frames finds the plane."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cellcal.core.methods.fullframe import fit_full_frame
from cellcal.devices.geometry.camera_model import pixel_grid_rays, project
from cellcal.devices.types import Frame, Intrinsics
from cellcal.drivers.o3r.decode import FrameDecoder
from cellcal.drivers.o3r.pcic import walk_chunks
from cellcal.drivers.o3r.tofinfo import MODEL_FISHEYE, MODEL_FISHEYE_INVERSE, parse_tof_info
from cellcal.sims.o3r.encoder import FrameEncoder
from cellcal.sims.o3r.wire import models_from_intrinsics

#: An O3R225-like head: 224 x 172 over about 105 x 80 degrees, OpenCV fisheye coefficients.
FISHEYE = Intrinsics(224, 172, fx=121.5, fy=121.5, cx=111.25, cy=85.75, k1=0.031, k2=-0.0042, k3=0.0007,
                     k4=-0.00005, model="fisheye")


def tilted_plane(intr: Intrinsics, tilt_deg: float = 20.0, distance_m: float = 0.8) -> tuple[Frame, np.ndarray]:
    """A plane ``distance_m`` ahead along the axis, tilted about x, seen through ``intr``'s exact rays."""
    rays = pixel_grid_rays(intr)
    a = math.radians(tilt_deg)
    n = np.array([0.0, math.sin(a), -math.cos(a)])          # normal toward the camera
    d = distance_m * math.cos(a)                             # n . p + d = 0 through (0, 0, distance_m)
    t = -d / (rays @ n)
    dist = np.where(t > 0, t, np.nan).astype(np.float32)
    valid = np.isfinite(dist)
    xyz = (rays * dist[..., None]).astype(np.float32)
    amp = np.full(dist.shape, 500.0, np.float32)
    frame = Frame(distance=dist, xyz=xyz, amplitude=amp, valid=valid, intrinsics=intr, timestamp=1.7e9, sequence=1)
    return frame, np.append(n, d)


def decode(frame: Frame) -> tuple[Frame, object]:
    enc = FrameEncoder(models_from_intrinsics(frame.intrinsics, pixel_grid_rays(frame.intrinsics)))
    payload = bytes(enc.encode(enc.counts(frame), 1, int(frame.timestamp * 1e9)))[16:]
    out = FrameDecoder().decode(payload, walk_chunks(payload), received_at=frame.timestamp)
    return out.frame, out.tof_info


def test_fisheye_head_gives_fisheye_intrinsics() -> None:
    frame, _ = tilted_plane(FISHEYE)
    out, info = decode(frame)
    assert info.intrinsic.model_id == MODEL_FISHEYE and info.inverse_intrinsic.model_id == MODEL_FISHEYE_INVERSE
    intr = out.intrinsics
    assert intr.model == "fisheye"
    for name in ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4"):  # float32 on the wire
        assert getattr(intr, name) == pytest.approx(getattr(FISHEYE, name), rel=1e-6, abs=1e-9), name
    assert (intr.p1, intr.p2, intr.k5) == (0.0, 0.0, 0.0)
    # corner rays are 63 degrees off axis: a pinhole part would put them tens of pixels off
    v = out.valid
    rows, cols = np.nonzero(v)
    uv = project(intr, out.xyz[v].astype(np.float64))
    err = np.hypot(uv[:, 0] - cols, uv[:, 1] - rows)
    assert np.percentile(err, 95) < 0.05 and err.max() < 0.2
    pinhole = Intrinsics(224, 172, intr.fx, intr.fy, intr.cx, intr.cy)
    uv_p = project(pinhole, out.xyz[v].astype(np.float64))
    assert np.hypot(uv_p[:, 0] - cols, uv_p[:, 1] - rows).max() > 20.0
    # the decoder's model-2 rays agree with OpenCV's fisheye back-projection of the model-3 intrinsics
    ang = np.arccos(np.clip(np.sum(out.xyz[v] / out.distance[v][:, None] * pixel_grid_rays(intr)[v], axis=1), -1, 1))
    assert ang.max() < 1e-3


def test_tof_info_of_a_fisheye_head_round_trips() -> None:
    models = models_from_intrinsics(FISHEYE, pixel_grid_rays(FISHEYE))
    enc = FrameEncoder(models)
    frame, _ = tilted_plane(FISHEYE)
    payload = bytes(enc.encode(enc.counts(frame), 1, 0))[16:]
    c = next(c for c in walk_chunks(payload) if c.chunk_type == 420)
    info = parse_tof_info(payload[c.data_offset:c.data_offset + c.data_size])
    theta_max = info.inverse_intrinsic.params[9]
    corner = np.degrees(theta_max)
    assert 60.0 < corner < 66.0  # the widest pixel's angle
    assert models.fit_rms_rad < 1e-4


def test_full_frame_fit_on_a_fisheye_frame_finds_the_plane() -> None:
    frame, (nx, ny, nz, d) = tilted_plane(FISHEYE, tilt_deg=25.0, distance_m=0.7)
    out, _ = decode(frame)
    result = fit_full_frame(out)
    got = result.plane
    normal = np.asarray(got.normal)
    assert abs(float(normal @ [nx, ny, nz])) > math.cos(math.radians(0.05))
    assert abs(abs(got.offset_m) - d) < 2e-4
