"""Byte-level encoding of O3R frames for the emulator (written independently of the driver).

Chunk headers, TOF_INFO and chunk metadata as a real O3R writes them, and the camera's
OpenCV intrinsics as O3R intrinsic models (:func:`models_from_intrinsics`). All values
travel as float32. The frame encoder itself is :mod:`.encoder`.
"""

from __future__ import annotations

import json
import struct
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cellcal.devices.errors import CalibrationError
from cellcal.devices.types import Intrinsics

CHUNK_IDS = {"RADIAL_DISTANCE_COMPRESSED": 100, "AMPLITUDE_COMPRESSED": 101, "CONFIDENCE": 300, "TOF_INFO": 420}
#: Blob ids of an O3R 3D port the emulator accepts in a schema but does not produce (protocols.md A3).
KNOWN_UNSERVED_IDS = frozenset({"RADIAL_DISTANCE_NOISE", "REFLECTIVITY", "JPEG_IMAGE", "RGB_INFO",
                                "intrinsic_calibration", "inverse_intrinsic_calibration", "EXPOSURE_TIME",
                                "EXTRINSIC_CALIB", "O3R_RESULT_JSON", "O3R_RESULT_ARRAY2D", "O3R_RESULT_IMU"})
DEFAULT_CHUNKS = (100, 101, 300, 420)
#: Pixel formats.
FORMAT_8U = 0
FORMAT_16U = 2
#: Chunk header version per chunk type as in a real O3R capture (ifm3d's O3RBuffer.data): v3 with JSON
#: metadata for distance and amplitude, v2 for confidence and TOF_INFO.
REAL_HEADER_VERSIONS = {100: 3, 101: 3, 300: 2, 420: 2}
#: Metres per distance count of a real O3R (10 m over 16 bits, as in both real captures).
DISTANCE_RESOLUTION_M = 10.0 / 65535.0
#: Amplitude scale per count^2 (the simulated camera's amplitude units; real heads report ~2e-8 in theirs).
AMPLITUDE_RESOLUTION = 1e-6
#: Amplitude normalisation factors and exposure times (s) as in the real captures' TOF_INFO.
AMP_NORM_FACTORS = (0.0333333, 0.0025, 0.0002)
EXPOSURE_TIMES_S = (2.0e-5, 4.0e-4, 5.0e-3)
#: Imager of current O3R222 heads (the TOF_INFO v4 capture).
IMAGER = "IRS2381C"


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
        hsize = 48 + len(metadata)  # not padded: a real amplitude chunk has a 205-byte header
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
    forward_id: int = 0
    inverse_id: int = 1


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
    if intr.model == "fisheye":
        return _fisheye_models(intr, rays)
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


def _fisheye_models(intr: Intrinsics, rays: NDArray[np.float64] | None) -> O3RModels:
    """O3R fisheye models 2 (pixel -> ray) and 3 (ray -> pixel) of OpenCV fisheye intrinsics.

    Model 3 is OpenCV's fisheye projection exactly (``k1..k4``, ``theta_max`` = the widest
    pixel's angle); model 2 maps the distorted radius back, ``theta = theta_s (1 + k1'
    theta_s^2 + ... + k4' theta_s^8)``, its coefficients the least-squares fit over the
    pixel grid's exact rays.

    Raises:
        CalibrationError: Without the exact rays.
    """
    if rays is None:
        raise CalibrationError("exact pixel rays are needed to fit the forward model of a fisheye lens")
    f32 = np.float32
    mx, my = intr.cx + 0.5, intr.cy + 0.5
    fx, fy, mxf, myf = (float(f32(v)) for v in (intr.fx, intr.fy, mx, my))
    ok = np.all(np.isfinite(rays), axis=2)
    theta = np.arccos(np.clip(rays[..., 2][ok], -1.0, 1.0))              # true angle of each pixel's ray
    gx = (np.arange(intr.width) + 0.5 - mxf) / fx
    gy = (np.arange(intr.height) + 0.5 - myf) / fy
    theta_s = np.hypot(*np.meshgrid(gx, gy))[ok]                          # distorted radius (model 2's input)
    phi = theta_s ** 2
    use = theta_s > 1e-9
    # theta / theta_s - 1 = k1' phi + k2' phi^2 + k3' phi^3 + k4' phi^4
    a = np.column_stack([phi, phi ** 2, phi ** 3, phi ** 4])[use]
    coef, *_ = np.linalg.lstsq(a, theta[use] / theta_s[use] - 1.0, rcond=None)
    resid = a @ coef - (theta[use] / theta_s[use] - 1.0)
    theta_max = float(theta.max())
    forward = _pad32([intr.fx, intr.fy, mx, my, 0.0, *coef, float(theta_s.max())])
    inverse = _pad32([intr.fx, intr.fy, mx, my, 0.0, intr.k1, intr.k2, intr.k3, intr.k4, theta_max])
    return O3RModels(forward, inverse, float(np.sqrt(np.mean((resid * theta_s[use]) ** 2))), 2, 3)


def tof_info(*, distance_resolution_m: float, amplitude_resolution: float, models: O3RModels,
             extrinsic_optic_to_user: Sequence[float] = (0, 0, 0, 0, 0, 0), version: int = 4,
             timestamp_ns: int = 0, exposure_s: Sequence[float] = EXPOSURE_TIMES_S, temperature_c: float = 42.0,
             mode: str = "standard_range4m", imager: str = IMAGER, block: int = 0,
             range_m: tuple[float, float] = (0.0, 4.14)) -> bytes:
    """TOF_INFO data: 312 bytes for version 1, 348 for 2, 416 for 3, 428 for 4 (ifm3d's ``TOFInfoV4``)."""
    out = struct.pack("<I2f3f6f", version, distance_resolution_m, amplitude_resolution, *AMP_NORM_FACTORS,
                      *extrinsic_optic_to_user)
    out += struct.pack("<I32f", models.forward_id, *models.forward)
    out += struct.pack("<I32f", models.inverse_id, *models.inverse)
    if version >= 2:
        out += struct.pack("<3Q3f", timestamp_ns, timestamp_ns, timestamp_ns, *exposure_s)
    if version >= 3:
        out += struct.pack("<f32s32s", temperature_c, mode.encode(), imager.encode())
    if version >= 4:
        out += struct.pack("<I2f", block, *range_m)
    return out


def chunk_metadata(chunk_type: int, distance_resolution_m: float, amplitude_resolution: float) -> bytes:
    """The v3 META_DATA JSON of a chunk as the real firmware writes it (NUL-terminated, not padded)."""
    doc: dict[str, object] = {}
    if chunk_type == 100:
        doc["DistanceResolution"] = float(np.float32(distance_resolution_m))
    elif chunk_type == 101:
        doc.update(AmpNormalizationFactors=[float(np.float32(v)) for v in AMP_NORM_FACTORS],
                   AmplitudeResolution=float(np.float32(amplitude_resolution)))
    doc["Version"] = "0.0.1"
    return json.dumps(doc, separators=(",", ":")).encode() + b"\0"


def cycle_ranges_m(mode: str) -> tuple[float, ...]:
    """Maximum range (m) of each measurement block of a mode: ``cyclic_4m_2m_4m_2m`` -> (4, 2, 4, 2).

    A non-cycling mode has one block (``standard_range2m`` -> (2,); unknown names -> (4,)).
    """
    def metres(word: str) -> float | None:
        digits = word.removeprefix("range").removesuffix("m")
        return float(digits) if word.endswith("m") and digits.replace(".", "", 1).isdigit() else None

    found = [m for m in (metres(w) for w in mode.split("_")) if m is not None]
    if mode.startswith("cyclic_") and found:
        return tuple(found)
    return (found[-1],) if found else (4.0,)


def schema_chunks(schema_json: str) -> tuple[int, ...]:
    """Chunk types a PCIC ``c`` schema selects.

    Blob ids of an O3R 3D port the emulator does not produce (:data:`KNOWN_UNSERVED_IDS`)
    are accepted and left out of the frames.

    Raises:
        ValueError: If the schema is not JSON with an ``elements`` list, or names a blob id
            an O3R does not know (a real device refuses the schema too).
    """
    doc = json.loads(schema_json)
    elements = doc.get("elements") if isinstance(doc, dict) else None
    if not isinstance(elements, list):
        raise ValueError("schema has no 'elements' list")
    out = []
    for el in elements:
        if not isinstance(el, dict) or el.get("type") != "blob":
            continue
        ident = el.get("id")
        if ident in CHUNK_IDS:
            out.append(CHUNK_IDS[ident])
        elif ident not in KNOWN_UNSERVED_IDS:
            raise ValueError(f"unknown blob id {ident!r}")
    return tuple(out)
