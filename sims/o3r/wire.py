"""Byte-level encoding of O3R frames for the emulator (written independently of the driver).

Turns a cellcal :class:`Frame` into the O3R PCIC image payload (chunks 100, 101, 300,
420) and encodes the camera's OpenCV intrinsics as O3R intrinsic models
(:func:`models_from_intrinsics`). All values travel as float32.
"""

from __future__ import annotations

import json
import struct
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from cellcal.devices.errors import CalibrationError
from cellcal.devices.types import Frame, Intrinsics

CHUNK_IDS = {"RADIAL_DISTANCE_COMPRESSED": 100, "AMPLITUDE_COMPRESSED": 101, "CONFIDENCE": 300, "TOF_INFO": 420}
DEFAULT_CHUNKS = (100, 101, 300, 420)
#: Pixel formats.
FORMAT_8U = 0
FORMAT_16U = 2


def message(ticket: bytes | str, content: bytes) -> bytes:
    """One PCIC v3 message (16-byte header, ticket, content, CR LF)."""
    t = ticket.encode() if isinstance(ticket, str) else ticket
    return t + b"L" + b"%09d" % (len(content) + 6) + b"\r\n" + t + content + b"\r\n"


def chunk(chunk_type: int, data: bytes, *, width: int, height: int, pixel_format: int, frame_count: int,
          timestamp_s: float, header_version: int = 2, metadata: bytes = b"") -> bytes:
    """One image chunk with a v1 (36 B), v2 (48 B) or v3 (48 B + metadata) header."""
    ts_ns = max(0, round(timestamp_s * 1e9))
    sec, nsec = divmod(ts_ns, 1_000_000_000)
    sec &= 0xFFFFFFFF
    ts_us = (ts_ns // 1000) & 0xFFFFFFFF
    if header_version == 1:
        hsize = 36
    elif header_version == 2:
        hsize = 48
    elif header_version == 3:
        pad = (-len(metadata)) % 4
        metadata = metadata + b"\0" * pad
        hsize = 48 + len(metadata)
    else:
        raise ValueError(f"header_version must be 1, 2 or 3, got {header_version}")
    head = struct.pack("<9I", chunk_type, hsize + len(data), hsize, header_version, width, height, pixel_format,
                       ts_us, frame_count & 0xFFFFFFFF)
    if header_version >= 2:
        head += struct.pack("<3I", 0, sec, nsec)
    if header_version == 3:
        head += metadata
    return head + data


@dataclass(frozen=True)
class O3RModels:
    """The two O3R intrinsic models of a camera (32 float32 parameters each)."""

    forward: tuple[float, ...]
    inverse: tuple[float, ...]
    fit_rms_rad: float = 0.0


def _pad32(values: Sequence[float]) -> tuple[float, ...]:
    out = [float(np.float32(v)) for v in values] + [0.0] * (32 - len(values))
    return tuple(out)


def models_from_intrinsics(intr: Intrinsics, rays: NDArray[np.float64] | None = None) -> O3RModels:
    """Encode OpenCV intrinsics as O3R models 0 (forward) and 1 (inverse).

    * inverse model 1 (ray -> pixel) exactly: ``mx = cx + 0.5``, ``my = cy + 0.5``, ifm
      ``k1, k2, k3, k4, k5 = k1, k2, p1, p2, k3`` (OpenCV's k4..k6 and s1..s4 have no
      place in the model and must be 0);
    * forward model 0 (pixel -> ray): same fx, fy, mx, my; with distortion its five
      coefficients are the linear least-squares fit of the exact back-projection over
      the pixel grid (OpenCV undistortion), since model 0 *applies* its polynomial to
      pixel coordinates. Without distortion both models are identical.

    All values travel as float32, so the intrinsics round-trip to float32 precision
    (exactly for float32-representable values).

    Args:
        intr: The camera's intrinsics.
        rays: Exact unit rays (H, W, 3) of the pixel grid (pixel centres at integers,
            OpenCV convention); needed only when the intrinsics have distortion.

    Raises:
        CalibrationError: If the intrinsics use terms the Bouguet model lacks
            (k4..k6, s1..s4), or distortion is present but no rays are given.
    """
    extra = {n: getattr(intr, n) for n in ("k4", "k5", "k6", "s1", "s2", "s3", "s4") if getattr(intr, n) != 0}
    if extra:
        raise CalibrationError(f"O3R Bouguet model cannot carry OpenCV terms {sorted(extra)}")
    mx, my = intr.cx + 0.5, intr.cy + 0.5
    inverse = _pad32([intr.fx, intr.fy, mx, my, 0.0, intr.k1, intr.k2, intr.p1, intr.p2, intr.k3])
    if not intr.has_distortion:
        return O3RModels(_pad32([intr.fx, intr.fy, mx, my, 0.0, 0, 0, 0, 0, 0]), inverse)
    if rays is None:
        raise CalibrationError("exact pixel rays are needed to fit the forward model of a distorted lens")
    h, w = intr.height, intr.width
    f32 = np.float32
    fx, fy, mxf, myf = (float(f32(v)) for v in (intr.fx, intr.fy, mx, my))
    cx = (np.arange(w) + 0.5 - mxf) / fx
    cy = (np.arange(h) + 0.5 - myf) / fy
    cxg, cyg = np.meshgrid(cx, cy)
    ok = np.all(np.isfinite(rays), axis=2) & (rays[..., 2] > 0)
    tx = rays[..., 0][ok] / rays[..., 2][ok]
    ty = rays[..., 1][ok] / rays[..., 2][ok]
    x, y = cxg[ok], cyg[ok]
    r2 = x * x + y * y
    hxy = 2 * x * y
    # unknowns k1, k2, k3 (tangential a), k4 (tangential b), k5 (r^6)
    ax = np.column_stack([x * r2, x * r2 * r2, hxy, r2 + 2 * x * x, x * r2 ** 3])
    ay = np.column_stack([y * r2, y * r2 * r2, r2 + 2 * y * y, hxy, y * r2 ** 3])
    a = np.vstack([ax, ay])
    b = np.concatenate([tx - x, ty - y])
    coef, *_ = np.linalg.lstsq(a, b, rcond=None)
    k1, k2, k3, k4, k5 = (float(f32(c)) for c in coef)
    resid = a @ np.array([k1, k2, k3, k4, k5]) - b
    forward = _pad32([intr.fx, intr.fy, mx, my, 0.0, k1, k2, k3, k4, k5])
    return O3RModels(forward, inverse, float(np.sqrt(np.mean(resid ** 2))))


def tof_info(*, distance_resolution_m: float, amplitude_resolution: float, models: O3RModels,
             extrinsic_optic_to_user: Sequence[float] = (0, 0, 0, 0, 0, 0), version: int = 3,
             timestamp_ns: int = 0, exposure_s: float = 0.001, temperature_c: float = 42.0,
             mode: str = "standard_range4m", imager: str = "IRS2877C") -> bytes:
    """TOF_INFO data (416 bytes for version 3; 348 for 2; 312 for 1)."""
    out = struct.pack("<I2f3f6f", version, distance_resolution_m, amplitude_resolution, 1.0, 1.0, 1.0,
                      *extrinsic_optic_to_user)
    out += struct.pack("<I32f", 0, *models.forward)
    out += struct.pack("<I32f", 1, *models.inverse)
    if version >= 2:
        out += struct.pack("<3Q3f", timestamp_ns, timestamp_ns, timestamp_ns, exposure_s, exposure_s, 0.0)
    if version >= 3:
        out += struct.pack("<f32s32s", temperature_c, mode.encode(), imager.encode())
    return out


@dataclass
class FrameEncoder:
    """Encodes frames of one camera into image payloads.

    Attributes:
        models: The camera's O3R intrinsic models.
        distance_resolution_m: Metres per distance count (float32 on the wire).
        amplitude_resolution: Amplitude scale.
        extrinsic_optic_to_user: transX/Y/Z (m), rotX/Y/Z (rad).
        header_version: Chunk header version 1..3.
        tof_info_version: TOF_INFO structure version 1..3.
    """

    models: O3RModels
    distance_resolution_m: float = 0.000125
    amplitude_resolution: float = 0.05
    extrinsic_optic_to_user: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    header_version: int = 2
    tof_info_version: int = 3
    _meta: bytes = field(default=b'{"sensor":"emulated O3R"}', repr=False)

    def payload(self, frame: Frame, frame_count: int, chunks: Iterable[int] = DEFAULT_CHUNKS) -> bytes:
        """The image payload content ``star ... stop`` (without ticket and CR LF)."""
        h, w = frame.distance.shape
        res = float(np.float32(self.distance_resolution_m))
        valid = frame.valid & np.isfinite(frame.distance)
        counts = np.where(valid, np.round(np.nan_to_num(frame.distance, nan=0.0) / res), 0.0)
        too_far = counts > 65535
        counts = np.clip(counts, 0, 65535)
        counts[too_far] = 0
        dist = counts.astype("<u2")
        conf = (np.zeros((h, w), "<u2") if frame.confidence is None else frame.confidence.astype("<u2"))
        conf = conf | np.where(dist == 0, 1, 0).astype("<u2")
        amp = np.nan_to_num(frame.amplitude, nan=0.0).astype(np.float64)
        araw = np.where(amp >= 0, np.round(np.sqrt(np.maximum(amp, 0) / self.amplitude_resolution)) + 1, 0)
        araw = np.clip(araw, 0, 65535).astype("<u2")
        ts = frame.timestamp
        kw = {"frame_count": frame_count, "timestamp_s": ts, "header_version": self.header_version,
              "metadata": self._meta}
        parts = [b"star"]
        wanted = set(chunks)
        if 100 in wanted:
            parts.append(chunk(100, dist.tobytes(), width=w, height=h, pixel_format=FORMAT_16U, **kw))
        if 101 in wanted:
            parts.append(chunk(101, araw.tobytes(), width=w, height=h, pixel_format=FORMAT_16U, **kw))
        if 300 in wanted:
            parts.append(chunk(300, conf.tobytes(), width=w, height=h, pixel_format=FORMAT_16U, **kw))
        if 420 in wanted:
            info = tof_info(distance_resolution_m=res, amplitude_resolution=self.amplitude_resolution,
                            models=self.models, extrinsic_optic_to_user=self.extrinsic_optic_to_user,
                            version=self.tof_info_version, timestamp_ns=max(0, round(ts * 1e9)))
            parts.append(chunk(420, info, width=w, height=h, pixel_format=FORMAT_8U, **kw))  # a 1-D blob
        parts.append(b"stop")
        return b"".join(parts)


def schema_chunks(schema_json: str) -> tuple[int, ...]:
    """Chunk types a PCIC ``c`` schema selects (unknown blob ids are ignored).

    Raises:
        ValueError: If the schema is not JSON with an ``elements`` list.
    """
    doc = json.loads(schema_json)
    elements = doc.get("elements") if isinstance(doc, dict) else None
    if not isinstance(elements, list):
        raise ValueError("schema has no 'elements' list")
    out = []
    for el in elements:
        if isinstance(el, dict) and el.get("type") == "blob" and el.get("id") in CHUNK_IDS:
            out.append(CHUNK_IDS[el["id"]])
    return tuple(out)
