"""Synthetic stereo and ToF frames of a tilted plane with a systematic depth error (issue #39, ADR 0059).

Independent of ``cellcal.sims``: a pinhole camera with the principal point at the image centre
looks at a plane placed by its height along the optical axis and its tilts; the true disparity
(stereo, ``f·B / Z``) or range (ToF) of each pixel is distorted by a
:class:`~cellcal.devices.systematic.SystematicError` (``distort``), then noise is added (and, for
stereo, rounded to the subpixel step). Camera frame (OpenCV), metres.
"""

from __future__ import annotations

import math
import time

import numpy as np

from cellcal.core.geometry.planes import Plane
from cellcal.devices.measurement import MeasurementModel
from cellcal.devices.systematic import SystematicError, normalised_pixels
from cellcal.devices.types import Frame, Intrinsics

W, H = 320, 200                 # px
F = 300.0                       # px
B = 0.075                       # m (stereo baseline)


def truth_plane(height_m: float, tilt_x_deg: float, tilt_y_deg: float) -> Plane:
    """The plane seen ``height_m`` along the optical axis, the camera tilted by the given angles."""
    tx, ty = math.radians(tilt_x_deg), math.radians(tilt_y_deg)
    n = np.array([math.sin(ty), -math.sin(tx) * math.cos(ty), -math.cos(tx) * math.cos(ty)])   # toward camera
    n /= np.linalg.norm(n)
    return Plane.from_point_normal(np.array([0.0, 0.0, height_m]), n).oriented_toward_origin()


def _rays() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    cols, rows = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    return (cols - (W - 1) / 2.0) / F, (rows - (H - 1) / 2.0) / F, np.ones((H, W))


def intrinsics() -> Intrinsics:
    return Intrinsics(width=W, height=H, fx=F, fy=F, cx=(W - 1) / 2.0, cy=(H - 1) / 2.0)


def stereo_model(*, sigma_px: float = 0.05, bits: int = 3, zero: bool = False) -> MeasurementModel:
    """The stereo camera's model: the default allowance (1 %, 0.1 px, 0.5 px), or zero when ``zero``."""
    allow = {"scale_allowance": 0.0, "offset_allowance": 0.0, "field_allowance": 0.0} if zero else {}
    return MeasurementModel(kind="stereo", baseline_m=B, focal_px=F, subpixel_bits=bits, disparity_sigma_px=sigma_px,
                            source="sim", **allow)


def tof_model(*, sigma_1m: float = 0.002, zero: bool = False) -> MeasurementModel:
    allow = {"scale_allowance": 0.0, "offset_allowance": 0.0, "field_allowance": 0.0} if zero else {}
    return MeasurementModel(kind="tof", sigma_at_1m_m=sigma_1m, distance_exponent=1.5, source="sim", **allow)


def _frame(xyz: np.ndarray, valid: np.ndarray, model: MeasurementModel) -> Frame:
    xyz = np.where(valid[..., None], xyz, np.nan).astype(np.float32)
    dist = np.linalg.norm(xyz, axis=2).astype(np.float32)
    return Frame(distance=dist, xyz=xyz, amplitude=np.ones((H, W), np.float32), valid=valid.copy(),
                 intrinsics=intrinsics(), timestamp=time.time(), sequence=0, measurement=model)


def stereo_frame(plane: Plane, error: SystematicError | None, model: MeasurementModel, rng: np.random.Generator
                 ) -> Frame:
    """A stereo frame of ``plane``: true disparity distorted by ``error``, noise, rounding to the step."""
    x, y, one = _rays()
    n = np.asarray(plane.normal)
    z = -plane.offset_m / (n[0] * x + n[1] * y + n[2] * one)            # Z-depth along each pixel
    fb = F * B
    d = fb / z
    u, v = normalised_pixels(W, H, (W - 1) / 2.0, (H - 1) / 2.0)
    if error is not None:
        d = error.distort(d, u, v)
    d = d + rng.normal(0.0, model.disparity_sigma_px or 0.0, d.shape)
    q = model.disparity_step_px
    d = np.round(d / q) * q
    valid = d > 0
    zz = np.where(valid, fb / np.where(valid, d, 1.0), np.nan)
    return _frame(np.stack([x * zz, y * zz, zz], axis=2), valid, model)


def tof_frame(plane: Plane, error: SystematicError | None, model: MeasurementModel, rng: np.random.Generator
              ) -> Frame:
    """A ToF frame of ``plane``: true range distorted by ``error``, noise ``sigma·t^1.5/sqrt(cos)``."""
    x, y, one = _rays()
    rays = np.stack([x, y, one], axis=2)
    norm = np.linalg.norm(rays, axis=2)
    r = rays / norm[..., None]
    n = np.asarray(plane.normal)
    nr = r @ n
    t = -plane.offset_m / nr
    u, v = normalised_pixels(W, H, (W - 1) / 2.0, (H - 1) / 2.0)
    if error is not None:
        t = error.distort(t, u, v)
    sigma = (model.sigma_at_1m_m or 0.0) * t ** 1.5 / np.sqrt(np.abs(nr))
    t = t + rng.normal(0.0, 1.0, t.shape) * sigma
    valid = t > 0
    return _frame(r * t[..., None], valid, model)
