"""Decode an O3R image payload into a cellcal :class:`Frame` (numpy, one pass per output).

Pixel data is never copied as raw bytes: the uint16 chunks are read through
``numpy.frombuffer`` views of the received payload and converted straight into the
float32 outputs. Unit vectors are cached per (model, image size).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cellcal.devices.errors import CalibrationError, ProtocolError
from cellcal.devices.types import Frame, Intrinsics

from .pcic import (
    CHUNK_CONFIDENCE,
    CHUNK_NORM_AMPLITUDE,
    CHUNK_RADIAL_DISTANCE,
    CHUNK_TOF_INFO,
    Chunk,
    blob_view,
    image_view,
    walk_chunks,
)
from .tofinfo import TofInfo, intrinsics_from_models, optic_to_user, parse_tof_info, unit_vectors

#: Confidence bit marking an invalid pixel.
CONF_INVALID_BIT = 1
#: Confidence pixel formats ifm devices send: 8U (older firmware) and 16U.
CONFIDENCE_FORMATS = (0, 2)
#: Default largest |device clock - receive time| still taken as Unix time, seconds.
DEFAULT_CLOCK_TOLERANCE_S = 30.0

_log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DecodedFrame:
    """A decoded frame plus the O3R-specific extras.

    Attributes:
        frame: The cellcal frame (xyz in the optical frame, or in ifm's user frame if
            the decoder was built with ``apply_extrinsic=True``).
        tof_info: The frame's TOF_INFO.
        frame_count: FRAME_COUNT of the distance chunk.
    """

    frame: Frame
    tof_info: TofInfo
    frame_count: int


class FrameDecoder:
    """Turns validated image payloads into frames; caches unit vectors.

    Time: a VPU without SNTP stamps frames with its own clock (time since boot, or
    whatever it was set to), not Unix time. When a frame's device time is more than
    ``clock_tolerance_s`` from its receive time, ``Frame.timestamp`` is the receive
    time; the device time is always kept in ``Frame.metadata["device_timestamp_s"]``
    and the choice in ``metadata["timestamp_source"]`` (logged once per decoder).

    Args:
        apply_extrinsic: If True, XYZ is transformed by extrinsicOpticToUser (ifm's
            user frame, what ifm3d's XYZ buffer holds); if False (default) XYZ stays in
            the camera optical frame, which is what :class:`Frame` documents.
        clock_tolerance_s: Largest device-vs-receive clock difference taken as Unix time, s.
    """

    def __init__(self, apply_extrinsic: bool = False, clock_tolerance_s: float = DEFAULT_CLOCK_TOLERANCE_S) -> None:
        self.apply_extrinsic = apply_extrinsic
        self.clock_tolerance_s = clock_tolerance_s
        self._clock_logged = False
        self._uv_key: tuple[object, ...] | None = None
        self._uv: NDArray[np.float32] | None = None
        self._intr_key: tuple[object, ...] | None = None
        self._intr: Intrinsics | None = None

    def _unit_vectors(self, info: TofInfo, width: int, height: int) -> NDArray[np.float32]:
        """Cached unit vectors, planar: float32 (3, height, width)."""
        key = (info.intrinsic, width, height)
        if self._uv is None or key != self._uv_key:
            self._uv = np.ascontiguousarray(unit_vectors(info.intrinsic, width, height).transpose(2, 0, 1))
            self._uv_key = key
        return self._uv

    def intrinsics(self, info: TofInfo, width: int, height: int) -> Intrinsics:
        """Cached :func:`intrinsics_from_models`."""
        key = (info.inverse_intrinsic, info.intrinsic, width, height)
        if self._intr is None or key != self._intr_key:
            try:
                self._intr = intrinsics_from_models(info, width, height)
            except CalibrationError as exc:
                raise ProtocolError(f"TOF_INFO intrinsic calibration is unusable: {exc}") from None
            self._intr_key = key
        return self._intr

    def decode(self, payload: bytes | bytearray | memoryview, chunks: list[Chunk] | None = None, *,
               offset: int = 0, received_at: float | None = None) -> DecodedFrame:
        """Decode one image payload (``<ticket>star ... stop\\r\\n``).

        Args:
            payload: The whole payload.
            chunks: Its chunk list from :func:`walk_chunks` (computed if None).
            offset: Stream offset of ``payload[0]`` for error messages.
            received_at: Receive time, epoch seconds: the frame time when the chunks carry
                no timestamp or the device clock is not Unix time (None: now).

        Raises:
            ProtocolError: Missing distance or TOF_INFO chunk, mismatching image sizes (TOF_INFO header included),
                wrong pixel formats, or any framing fault of the payload.
        """
        if chunks is None:
            chunks = walk_chunks(payload, offset=offset)
        by_type, dist_c, info_c = _required_chunks(chunks, offset)
        info = parse_tof_info(blob_view(payload, info_c), offset=offset + info_c.data_offset)
        distance, valid, conf = self._distance(payload, by_type, dist_c, info, offset)
        h, w = distance.shape
        amplitude = self._amplitude_image(payload, by_type.get(CHUNK_NORM_AMPLITUDE), info, (h, w), offset)
        intr = self.intrinsics(info, w, h)
        xyz = self._xyz(info, distance)
        timestamp, meta = self._timestamp(dist_c, received_at)
        meta.update(_info_metadata(info, conf))
        frame = Frame(distance=distance, xyz=xyz, amplitude=amplitude, valid=valid,
                      intrinsics=intr, timestamp=timestamp, sequence=int(dist_c.frame_count), confidence=conf,
                      metadata=meta)
        return DecodedFrame(frame, info, int(dist_c.frame_count))

    def _timestamp(self, dist_c: Chunk, received_at: float | None) -> tuple[float, dict[str, Any]]:
        """Frame time (epoch seconds) and the clock metadata: device time if it is Unix time, else receive time."""
        received = time.time() if received_at is None else float(received_at)
        ts_ns = dist_c.timestamp_ns or (dist_c.timestamp_us * 1000)  # v1 headers carry only microseconds
        if not ts_ns:  # the chunks carry no time at all
            return received, {"timestamp_source": "receive", "device_timestamp_s": None}
        device = ts_ns / 1e9
        offset = device - received
        if abs(offset) <= self.clock_tolerance_s:
            return device, {"timestamp_source": "device", "device_timestamp_s": device}
        if not self._clock_logged:
            self._clock_logged = True
            _log.warning("O3R clock reads %.3f s, %.0f s from this host's clock: not Unix time (set up SNTP on "
                         "the VPU, /device/clock/sntp); frames are stamped with their receive time, the device "
                         "time is kept in Frame.metadata['device_timestamp_s']", device, offset)
        return received, {"timestamp_source": "receive", "device_timestamp_s": device}

    def _distance(self, payload: bytes | bytearray | memoryview, by_type: dict[int, Chunk], dist_c: Chunk,
                  info: TofInfo, offset: int
                  ) -> tuple[NDArray[np.float32], NDArray[np.bool_], NDArray[np.unsignedinteger[Any]] | None]:
        """Radial distance (metres, float32, NaN where invalid), validity and the raw confidence image.

        A pixel is invalid where its raw distance is 0 (no measurement) or, if the
        payload has a confidence chunk, where its confidence has the invalid bit set.
        """
        raw = image_view(payload, dist_c, offset=offset, expect_format=(2,))
        h, w = raw.shape
        info_c = by_type[CHUNK_TOF_INFO]
        if (info_c.width, info_c.height) != (w, h):  # on the O3R, TOF_INFO's header carries the image size
            raise ProtocolError(f"distance image is {w}x{h} but its TOF_INFO says {info_c.width}x{info_c.height}",
                                offset=offset + info_c.offset + 16)
        # uint16 counts -> float32 metres in one ufunc
        distance = np.multiply(raw, np.float32(info.distance_resolution_m), dtype=np.float32)
        # raw 0 = no measurement
        invalid = raw == 0
        conf: NDArray[np.unsignedinteger[Any]] | None = None
        conf_c = by_type.get(CHUNK_CONFIDENCE)
        if conf_c is not None:
            # 8-bit (older firmware) or 16-bit confidence, kept as sent
            conf = image_view(payload, conf_c, offset=offset,  # type: ignore[assignment]
                              expect_format=CONFIDENCE_FORMATS)
            assert conf is not None
            self._check_shape(conf_c, conf, (h, w), offset)
            # the confidence's invalid bit also marks a pixel invalid
            invalid |= (conf & CONF_INVALID_BIT) != 0
        # invalid pixels read NaN metres
        np.copyto(distance, np.float32(np.nan), where=invalid)
        return distance, ~invalid, conf

    def _amplitude_image(self, payload: bytes | bytearray | memoryview, amp_c: Chunk | None, info: TofInfo,
                         shape: tuple[int, int], offset: int) -> NDArray[np.float32]:
        """Normalised amplitude from the amplitude chunk, or zeros (float32, ``shape``) without one."""
        if amp_c is None:
            return np.zeros(shape, dtype=np.float32)
        araw = image_view(payload, amp_c, offset=offset, expect_format=(2,))
        self._check_shape(amp_c, araw, shape, offset)
        return self._amplitude(araw, info.amplitude_resolution)  # type: ignore[arg-type]

    def _xyz(self, info: TofInfo, distance: NDArray[np.float32]) -> NDArray[np.float32]:
        """XYZ (metres, float32, (H, W, 3)): unit vectors times radial distance, optionally in ifm's user frame.

        XYZ is computed planar (3, H, W) -- one contiguous multiply per channel, ~6x
        faster than an interleaved (H, W, 3) broadcast -- and handed out as a
        (H, W, 3) view of it, which is what :class:`Frame` documents.
        """
        h, w = distance.shape
        uv = self._unit_vectors(info, w, h)
        with np.errstate(invalid="ignore", over="ignore"):
            # optical frame: unit ray x radial distance, per channel
            planar = uv * distance
            if self.apply_extrinsic:
                # user frame: p_user = R p_optic + t (extrinsicOpticToUser), as one (3, 3) @ (3, H*W)
                rot, trans = optic_to_user(info.extrinsic_optic_to_user)
                flat = rot.astype(np.float32) @ planar.reshape(3, -1)
                flat += trans.astype(np.float32)[:, None]
                planar = flat.reshape(3, h, w)
        out: NDArray[np.float32] = planar.transpose(1, 2, 0)
        return out

    @staticmethod
    def _amplitude(raw: NDArray[np.uint16], resolution: float) -> NDArray[np.float32]:
        """ifm's normalised amplitude: ``(raw - 1)^2 x resolution``, -1 where raw is 0."""
        a = np.subtract(raw, np.float32(1.0), dtype=np.float32)
        np.multiply(a, a, out=a)
        a *= np.float32(resolution)
        np.copyto(a, np.float32(-1.0), where=raw == 0)
        return a

    @staticmethod
    def _check_shape(chunk: Chunk, arr: NDArray[np.generic], shape: tuple[int, int], offset: int) -> None:
        if arr.shape[:2] != shape:
            raise ProtocolError(f"chunk {chunk.chunk_type} is {arr.shape[1]}x{arr.shape[0]}, distance image is "
                                f"{shape[1]}x{shape[0]}", offset=offset + chunk.offset + 16)


def _required_chunks(chunks: list[Chunk], offset: int) -> tuple[dict[int, Chunk], Chunk, Chunk]:
    """The payload's chunks by type (first of each type), its distance chunk and its TOF_INFO chunk.

    Raises:
        ProtocolError: If the distance (100) or TOF_INFO (420) chunk is missing.
    """
    by_type: dict[int, Chunk] = {}
    for c in chunks:
        by_type.setdefault(c.chunk_type, c)
    dist_c = by_type.get(CHUNK_RADIAL_DISTANCE)
    info_c = by_type.get(CHUNK_TOF_INFO)
    if dist_c is None or info_c is None:
        missing = [n for n, c in (("RADIAL_DISTANCE (100)", dist_c), ("TOF_INFO (420)", info_c)) if c is None]
        raise ProtocolError(f"image lacks chunk(s) {', '.join(missing)}", offset=offset + 8)
    return by_type, dist_c, info_c


def _info_metadata(info: TofInfo, conf: NDArray[np.unsignedinteger[Any]] | None) -> dict[str, Any]:
    """The TOF_INFO facts a caller needs per frame (JSON data; NaN ranges as None)."""
    def finite(v: float) -> float | None:
        return v if math.isfinite(v) else None

    return {"tof_info_version": info.version, "mode": info.mode, "imager": info.imager,
            "measurement_block_index": info.measurement_block_index,
            "measurement_range_min_m": finite(info.measurement_range_min_m),
            "measurement_range_max_m": finite(info.measurement_range_max_m),
            "confidence_bits": None if conf is None else 8 * conf.dtype.itemsize}
