"""O3R TOF_INFO (chunk 420) and the O3R intrinsic models (pure numpy).

:func:`parse_tof_info` reads the chunk; :func:`unit_vectors` evaluates a pixel -> ray
model as ifm's clients do; :func:`intrinsics_from_models` gives the OpenCV intrinsics;
:func:`optic_to_user` the extrinsic transform. Facts: ``shared/spec/protocols.md`` A8.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from cellcal.devices.errors import ProtocolError
from cellcal.devices.types import Intrinsics

#: Model ids.
MODEL_BOUGUET = 0
MODEL_BOUGUET_INVERSE = 1
MODEL_FISHEYE = 2
MODEL_FISHEYE_INVERSE = 3
#: Number of float parameters in an intrinsic calibration block.
N_MODEL_PARAMS = 32

_HEAD = struct.Struct("<I2f3f6f")            # version, dist res, ampl res, 3 norm, 6 extrinsic
_MODEL = struct.Struct("<I32f")
_V2 = struct.Struct("<3Q3f")
_V3 = struct.Struct("<f32s32s")
_V4 = struct.Struct("<I2f")                  # measurement block index, range min / max (m)
#: Largest plausible distance resolution, metres per count (65535 counts -> 655 m).
MAX_DISTANCE_RESOLUTION_M = 0.01
#: Largest plausible amplitude scale (keeps ``(a - 1)^2 x resolution`` finite in float32).
MAX_AMPLITUDE_RESOLUTION = 1e6
#: Data bytes needed per TOF_INFO version (v1 ends after the inverse intrinsics).
MIN_SIZE_V1 = _HEAD.size + 2 * _MODEL.size               # 312
MIN_SIZE_V2 = MIN_SIZE_V1 + _V2.size                     # 348
MIN_SIZE_V3 = MIN_SIZE_V2 + _V3.size                     # 416
MIN_SIZE_V4 = MIN_SIZE_V3 + _V4.size                     # 428
#: Newest TOF_INFO version whose layout is known; later versions are read as this one.
KNOWN_VERSION = 4


@dataclass(frozen=True)
class IntrinsicModel:
    """An O3R intrinsic calibration block.

    Models (parameters fx, fy, mx, my, alpha, then distortion):

    * 0: Bouguet, *pixel -> ray*: ``c = ((ix+0.5-mx)/fx, (iy+0.5-my)/fy)``,
      ``cx -= alpha*cy``, ``d = c*(1 + k1 r² + k2 r⁴ + k5 r⁶) + tangential(k3, k4)``,
      ray = normalise(dx, dy, 1).
    * 1: inverse Bouguet, *ray -> pixel*: the same polynomial applied to ``(x/z, y/z)``,
      then ``u = fx*(xd + alpha*yd) + mx - 0.5``, ``v = fy*yd + my - 0.5``. This is
      exactly OpenCV's Brown–Conrady projection with ``k1=k1, k2=k2, k3=k5, p1=k3,
      p2=k4`` (ifm's k3/k4 are the tangential terms, k5 the r⁶ term) and
      ``cx = mx - 0.5, cy = my - 0.5``.
    * 2 / 3: fisheye (fx, fy, mx, my, alpha, k1..k4, theta_max), forward / inverse.

    Attributes:
        model_id: 0 Bouguet, 1 inverse Bouguet, 2 fisheye, 3 inverse fisheye.
        params: The 32 float32 parameters (fx, fy, mx, my, alpha, k1.., ...).
    """

    model_id: int
    params: tuple[float, ...]


@dataclass(frozen=True)
class TofInfo:
    """Decoded TOF_INFO.

    Attributes:
        version: Structure version (1..4 understood; later versions are read as v4).
        distance_resolution_m: Metres per distance count.
        amplitude_resolution: Amplitude scale (``a² x`` this).
        amp_norm_factors: Three amplitude normalisation factors.
        extrinsic_optic_to_user: (transX, transY, transZ [m], rotX, rotY, rotZ [rad]).
        intrinsic: Pixel -> ray model (id 0 or 2).
        inverse_intrinsic: Ray -> pixel model (id 1 or 3).
        exposure_timestamps_ns: Up to three exposure timestamps, ns (v2+).
        exposure_times_s: Up to three exposure times, s (v2+).
        illumination_temperature_c: Illumination temperature, °C (v3+), else NaN.
        mode: Imager mode name (v3+).
        imager: Imager name (v3+).
        measurement_block_index: Sub-mode of a cycling mode (e.g. ``cyclic_4m_2m_4m_2m``)
            this frame was measured in, 0..N-1; always 0 in non-cycling modes and before v4.
        measurement_range_min_m, measurement_range_max_m: Measurement range of that
            block, metres (v4+; NaN before).
    """

    version: int
    distance_resolution_m: float
    amplitude_resolution: float
    amp_norm_factors: tuple[float, float, float]
    extrinsic_optic_to_user: tuple[float, float, float, float, float, float]
    intrinsic: IntrinsicModel
    inverse_intrinsic: IntrinsicModel
    exposure_timestamps_ns: tuple[int, ...] = ()
    exposure_times_s: tuple[float, ...] = ()
    illumination_temperature_c: float = float("nan")
    mode: str = ""
    imager: str = ""
    measurement_block_index: int = 0
    measurement_range_min_m: float = float("nan")
    measurement_range_max_m: float = float("nan")


def parse_tof_info(data: bytes | bytearray | memoryview, *, offset: int = 0) -> TofInfo:
    """Decode TOF_INFO chunk data.

    Layout (offsets from the start of the chunk data, little-endian): version u32,
    distanceResolution f32 (m per count), amplitudeResolution f32, three amplitude
    normalisation f32, extrinsicOpticToUser (transX/Y/Z m, rotX/Y/Z rad; 6 f32),
    intrinsic calibration (model id u32 + 32 f32), inverse intrinsic calibration (same),
    then for version >= 2 three exposure timestamps (u64 ns) and three exposure times
    (f32 s), for version >= 3 the illumination temperature (f32), mode and imager
    names (32 chars each), and for version >= 4 the measurement block index (u32) and
    the block's measurement range min / max (f32, m). Later versions are read as 4.

    Args:
        data: The chunk's data bytes (after its header).
        offset: Stream offset of ``data[0]``, for error messages.

    Raises:
        ProtocolError: Too few bytes for the announced version, version 0, or a
            distance or amplitude resolution that is not finite or out of range.
    """
    mv = memoryview(data).cast("B")
    if len(mv) < MIN_SIZE_V1:
        raise ProtocolError(f"TOF_INFO has {len(mv)} bytes, needs at least {MIN_SIZE_V1}", offset=offset)
    head = _HEAD.unpack_from(mv, 0)
    version = head[0]
    if version == 0:
        raise ProtocolError("TOF_INFO version 0 is not defined", offset=offset)
    need = (MIN_SIZE_V1, MIN_SIZE_V2, MIN_SIZE_V3, MIN_SIZE_V4)[min(version, KNOWN_VERSION) - 1]
    if len(mv) < need:
        raise ProtocolError(f"TOF_INFO version {version} needs {need} bytes, got {len(mv)}", offset=offset)
    dist_res = float(head[1])
    if not (np.isfinite(dist_res) and 0 < dist_res <= MAX_DISTANCE_RESOLUTION_M):
        raise ProtocolError(f"TOF_INFO distanceResolution {dist_res!r} is not in (0, {MAX_DISTANCE_RESOLUTION_M}] m",
                            offset=offset + 4)
    amp_res = float(head[2])
    if not (np.isfinite(amp_res) and 0 <= amp_res <= MAX_AMPLITUDE_RESOLUTION):
        raise ProtocolError(f"TOF_INFO amplitudeResolution {amp_res!r} is not in [0, {MAX_AMPLITUDE_RESOLUTION:g}]",
                            offset=offset + 8)
    intrinsic, inverse = _models(mv)
    return TofInfo(
        version=version, distance_resolution_m=dist_res, amplitude_resolution=amp_res,
        amp_norm_factors=(float(head[3]), float(head[4]), float(head[5])),
        extrinsic_optic_to_user=tuple(float(x) for x in head[6:12]),  # type: ignore[arg-type]
        intrinsic=intrinsic, inverse_intrinsic=inverse, **_later_fields(mv, version))


def _later_fields(mv: memoryview, version: int) -> dict[str, Any]:
    """The fields versions 2 (exposures), 3 (temperature, mode, imager) and 4 (measurement block) add."""
    out: dict[str, Any] = {}
    if version >= 2:
        v2 = _V2.unpack_from(mv, MIN_SIZE_V1)
        out.update(exposure_timestamps_ns=tuple(int(x) for x in v2[:3]),
                   exposure_times_s=tuple(float(x) for x in v2[3:]))
    if version >= 3:
        t, mraw, iraw = _V3.unpack_from(mv, MIN_SIZE_V2)
        out.update(illumination_temperature_c=float(t), mode=mraw.split(b"\0", 1)[0].decode("ascii", "replace"),
                   imager=iraw.split(b"\0", 1)[0].decode("ascii", "replace"))
    if version >= 4:
        block, rmin, rmax = _V4.unpack_from(mv, MIN_SIZE_V3)
        out.update(measurement_block_index=int(block), measurement_range_min_m=float(rmin),
                   measurement_range_max_m=float(rmax))
    return out


_MODELS_SEEN: dict[bytes, tuple[IntrinsicModel, IntrinsicModel]] = {}


def _models(mv: memoryview) -> tuple[IntrinsicModel, IntrinsicModel]:
    """The two intrinsic models of a TOF_INFO, parsed once per distinct byte content (they rarely change)."""
    key = bytes(mv[_HEAD.size:MIN_SIZE_V1])
    found = _MODELS_SEEN.get(key)
    if found is None:
        m0 = _MODEL.unpack_from(key, 0)
        m1 = _MODEL.unpack_from(key, _MODEL.size)
        found = (IntrinsicModel(int(m0[0]), tuple(float(x) for x in m0[1:])),
                 IntrinsicModel(int(m1[0]), tuple(float(x) for x in m1[1:])))
        if len(_MODELS_SEEN) >= 16:  # a bounded memo: heads seen by this process
            _MODELS_SEEN.clear()
        _MODELS_SEEN[key] = found
    return found


def unit_vectors(model: IntrinsicModel, width: int, height: int) -> NDArray[np.float32]:
    """Unit ray of every pixel in the optical frame, as ifm's clients evaluate it.

    Evaluated in float32 like ifm's reference code, so XYZ agrees with ifm3d's to
    float32 rounding. ifm's clients compute XYZ as these unit vectors (of the model-0
    or 2 intrinsic calibration) times the radial distance, in the *optical* frame;
    ifm then applies extrinsicOpticToUser (:func:`optic_to_user`).

    Args:
        model: A pixel -> ray model (id 0 Bouguet or 2 fisheye).
        width, height: Image size, px.

    Returns:
        float32 array (height, width, 3).

    Raises:
        ProtocolError: For a model id that is not a pixel -> ray model.
    """
    f32 = np.float32
    p = np.asarray(model.params[:10], dtype=f32)
    fx, fy = p[0], p[1]
    if fx == 0 or fy == 0 or not np.all(np.isfinite(p)):
        raise ProtocolError(f"intrinsic model {model.model_id}: degenerate parameters {p.tolist()}")
    with np.errstate(all="ignore"):
        return _unit_vectors(model, p, width, height)


def _unit_vectors(model: IntrinsicModel, p: NDArray[np.float32], width: int, height: int) -> NDArray[np.float32]:
    f32 = np.float32
    fx, fy, mx, my, alpha = p[0], p[1], p[2], p[3], p[4]
    ix = np.arange(width, dtype=f32) + f32(0.5)
    iy = np.arange(height, dtype=f32) + f32(0.5)
    cx = ((ix[None, :] - mx) / fx).astype(f32)
    cy = ((iy[:, None] - my) / fy).astype(f32)
    cx = cx - alpha * cy
    cy = np.broadcast_to(cy, cx.shape)
    out = np.empty((height, width, 3), dtype=f32)
    if model.model_id == MODEL_BOUGUET:
        k1, k2, k3, k4, k5 = p[5], p[6], p[7], p[8], p[9]
        r2 = cx * cx + cy * cy
        frad = f32(1) + r2 * (k1 + r2 * (k2 + r2 * k5))
        h = f32(2) * cx * cy
        dx = frad * cx + (k3 * h + k4 * (r2 + f32(2) * cx * cx))
        dy = frad * cy + (k3 * (r2 + f32(2) * cy * cy) + k4 * h)
        fnorm = f32(1) / np.sqrt(dx * dx + dy * dy + f32(1))
        out[..., 0] = fnorm * dx
        out[..., 1] = fnorm * dy
        out[..., 2] = fnorm
        return out
    if model.model_id == MODEL_FISHEYE:
        k1, k2, k3, k4, theta_max = p[5], p[6], p[7], p[8], p[9]
        theta_s = np.sqrt(cx * cx + cy * cy)
        phi = np.minimum(theta_s, theta_max) ** 2
        theta = theta_s * (f32(1) + phi * (k1 + phi * (k2 + phi * (k3 + phi * k4))))
        theta = np.clip(theta, f32(0), f32(np.pi))
        s = np.sin(theta)
        with np.errstate(invalid="ignore", divide="ignore"):
            out[..., 0] = np.where(theta_s > 0, cx / theta_s * s, f32(0))
            out[..., 1] = np.where(theta_s > 0, cy / theta_s * s, f32(0))
        out[..., 2] = np.cos(theta)
        return out
    raise ProtocolError(f"intrinsic model id {model.model_id} is not a pixel->ray model (0 or 2)")


def intrinsics_from_models(info: TofInfo, width: int, height: int) -> Intrinsics:
    """OpenCV-convention :class:`Intrinsics` of the depth stream, from the inverse (ray -> pixel) model.

    * Model 1 (Bouguet, O3R222/252) *is* OpenCV's Brown projection: ``cx = mx - 0.5``,
      ``cy = my - 0.5``, OpenCV ``k1, k2, k3 = k1, k2, k5`` and ``p1, p2 = k3, k4``.
    * Model 3 (fisheye, O3R225) *is* OpenCV's fisheye projection (``cv2.fisheye``):
      ``theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)``, pixel
      ``f theta_d + (m - 0.5)``; ifm clamps theta at ``theta_max`` inside the polynomial,
      which changes nothing within the image. The result has ``model = "fisheye"``.

    The skew ``alpha`` has no place in :class:`Intrinsics` and is dropped (O3R heads
    report 0). The values are exactly the float32 numbers on the wire. A stream whose
    inverse model is neither falls back to the forward model's pinhole part.
    """
    model = info.inverse_intrinsic
    if model.model_id not in (MODEL_BOUGUET_INVERSE, MODEL_FISHEYE_INVERSE):
        model = info.intrinsic  # fall back to the forward model's pinhole part
    fx, fy, mx, my = model.params[:4]
    k1, k2, k3, k4, k5 = model.params[5:10]
    if model.model_id == MODEL_BOUGUET_INVERSE:
        return Intrinsics(width=width, height=height, fx=fx, fy=fy, cx=mx - 0.5, cy=my - 0.5,
                          k1=k1, k2=k2, k3=k5, p1=k3, p2=k4)
    if model.model_id == MODEL_FISHEYE_INVERSE:  # k5 is theta_max here
        return Intrinsics(width=width, height=height, fx=fx, fy=fy, cx=mx - 0.5, cy=my - 0.5,
                          k1=k1, k2=k2, k3=k3, k4=k4, model="fisheye")
    return Intrinsics(width=width, height=height, fx=fx, fy=fy, cx=mx - 0.5, cy=my - 0.5)


def optic_to_user(extrinsic: tuple[float, ...]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Rotation matrix ``Rx(rotX) Ry(rotY) Rz(rotZ)`` and translation (m) of extrinsicOpticToUser.

    ``p_user = R @ p_optic + t``: ifm rotates optical-frame XYZ, then translates.
    """
    tx, ty, tz, rx, ry, rz = extrinsic[:6]
    rot = Rotation.from_euler("XYZ", [rx, ry, rz]).as_matrix()
    return rot, np.array([tx, ty, tz], dtype=np.float64)
