"""The emulator's frame encoder: one reused PCIC message buffer per chunk selection, filled in place.

The chunk headers, the chunk metadata and the TOF_INFO are laid out once per (chunk
selection, image size); per frame only the pixel data (through numpy views of the
buffer), the frame count, the timestamps and the TOF_INFO's per-frame fields are
written. :meth:`FrameEncoder.payload` keeps the old one-shot API (a fresh ``bytes``).
"""

from __future__ import annotations

import struct
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from cellcal.devices.types import Frame

from .wire import (
    AMPLITUDE_RESOLUTION,
    DEFAULT_CHUNKS,
    DISTANCE_RESOLUTION_M,
    FORMAT_8U,
    FORMAT_16U,
    IMAGER,
    REAL_HEADER_VERSIONS,
    O3RModels,
    chunk,
    chunk_metadata,
    cycle_ranges_m,
    tof_info,
)

_U32 = struct.Struct("<I")
_SEC_NSEC = struct.Struct("<2I")
_EXPOSURE_TS = struct.Struct("<3Q")
_BLOCK = struct.Struct("<I2f")
_EXTRINSIC = struct.Struct("<6f")
#: Offsets inside TOF_INFO data (protocols.md A8; ifm3d's TOFInfoV4).
_TI_EXTRINSIC, _TI_EXPOSURE_TS, _TI_BLOCK = 0x18, 0x138, 0x1A0
#: Byte offset of the data of the first chunk in a message: PCIC header, ticket, "star".
_FIRST = 16 + 4 + 4


@dataclass
class FrameCounts:
    """The wire images of one frame: uint16 distance and amplitude counts, the confidence image."""

    distance: NDArray[np.uint16]
    amplitude: NDArray[np.uint16]
    confidence: NDArray[np.uint16]


@dataclass
class _Layout:
    """One reused message buffer and where its per-frame fields are."""

    buffer: bytearray
    views: dict[int, NDArray[np.generic]]
    headers: list[tuple[int, int]]        # (offset of chunk header, header version)
    tof_data: int | None                  # offset of TOF_INFO data, if selected


@dataclass
class FrameEncoder:
    """Encodes frames of one camera into O3R image messages.

    Attributes:
        models: The camera's O3R intrinsic models.
        distance_resolution_m: Metres per distance count (float32 on the wire).
        amplitude_resolution: Amplitude scale per count².
        extrinsic_optic_to_user: transX/Y/Z (m), rotX/Y/Z (rad).
        header_version: Chunk header version 1..3 for every chunk, or None for the mix of
            a real O3R (:data:`~.wire.REAL_HEADER_VERSIONS`).
        tof_info_version: TOF_INFO structure version 1..4.
        confidence_bits: 16 (current firmware) or 8 (older firmware: the low byte).
        mode: Imager mode name; a ``cyclic_...`` mode cycles the measurement block per frame.
        imager: Imager name.
    """

    models: O3RModels
    distance_resolution_m: float = DISTANCE_RESOLUTION_M
    amplitude_resolution: float = AMPLITUDE_RESOLUTION
    extrinsic_optic_to_user: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    header_version: int | None = None
    tof_info_version: int = 4
    confidence_bits: int = 16
    mode: str = "standard_range4m"
    imager: str = IMAGER
    _layouts: dict[tuple[object, ...], _Layout] = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        if self.header_version not in (None, 1, 2, 3):
            raise ValueError(f"header_version must be 1, 2, 3 or None, got {self.header_version}")
        if self.confidence_bits not in (8, 16):
            raise ValueError(f"confidence_bits must be 8 or 16, got {self.confidence_bits}")

    # ------------------------------------------------------------------ quantisation
    def counts(self, frame: Frame) -> FrameCounts:
        """The wire images of a frame: distance / resolution (0 invalid), ``sqrt(a / res) + 1``, confidence."""
        res = float(np.float32(self.distance_resolution_m))
        valid = frame.valid & np.isfinite(frame.distance)
        # metres -> counts; invalid and beyond-16-bit pixels are 0 (no measurement)
        counts = np.where(valid, np.round(np.nan_to_num(frame.distance, nan=0.0) / res), 0.0)
        counts[counts > 65535] = 0
        dist = np.clip(counts, 0, 65535).astype("<u2")
        # the confidence's bit 0 marks every pixel without a distance
        conf = np.zeros(dist.shape, "<u2") if frame.confidence is None else frame.confidence.astype("<u2")
        conf = conf | (dist == 0).astype("<u2")
        # amplitude = (raw - 1)^2 x resolution  ->  raw = sqrt(amplitude / resolution) + 1
        amp = np.nan_to_num(frame.amplitude, nan=0.0).astype(np.float64)
        araw = np.where(amp >= 0, np.round(np.sqrt(np.maximum(amp, 0) / self.amplitude_resolution)) + 1, 0)
        return FrameCounts(dist, np.clip(araw, 0, 65535).astype("<u2"), conf)

    # ------------------------------------------------------------------ layout
    def _version(self, chunk_type: int) -> int:
        return self.header_version if self.header_version is not None else REAL_HEADER_VERSIONS[chunk_type]

    def layout(self, chunks: Iterable[int], width: int, height: int) -> _Layout:
        """The reused buffer for a chunk selection and image size (built on first use)."""
        wanted = tuple(c for c in DEFAULT_CHUNKS if c in set(chunks))
        key = (wanted, width, height)
        found = self._layouts.get(key)
        if found is not None:
            return found
        conf_fmt, conf_size = (FORMAT_16U, 2) if self.confidence_bits == 16 else (FORMAT_8U, 1)
        parts = [b"star"]
        for ctype in wanted:
            version = self._version(ctype)
            meta = chunk_metadata(ctype, self.distance_resolution_m, self.amplitude_resolution) if version == 3 else b""
            if ctype == 420:
                data, fmt = self._tof_info(block=0), FORMAT_8U  # a 1-D blob carrying the image size
            else:
                fmt = conf_fmt if ctype == 300 else FORMAT_16U
                data = bytes(width * height * (conf_size if ctype == 300 else 2))
            parts.append(chunk(ctype, data, width=width, height=height, pixel_format=fmt, frame_count=0,
                               timestamp_s=0.0, header_version=version, metadata=meta))
        parts.append(b"stop")
        content = b"".join(parts)
        buf = bytearray(b"0000L%09d\r\n0000" % (len(content) + 6) + content + b"\r\n")
        layout = _Layout(buf, {}, [], None)
        pos = _FIRST
        for ctype in wanted:
            csize, hsize, version = struct.unpack_from("<3I", buf, pos + 4)
            layout.headers.append((pos, version))
            if ctype == 420:
                layout.tof_data = pos + hsize
            else:
                dtype = "<u2" if ctype != 300 or conf_size == 2 else "u1"
                layout.views[ctype] = np.frombuffer(buf, dtype=dtype, count=width * height,
                                                    offset=pos + hsize).reshape(height, width)
            pos += csize
        self._layouts[key] = layout
        return layout

    def _tof_info(self, block: int) -> bytes:
        ranges = cycle_ranges_m(self.mode)
        return tof_info(distance_resolution_m=float(np.float32(self.distance_resolution_m)),
                        amplitude_resolution=self.amplitude_resolution, models=self.models,
                        extrinsic_optic_to_user=self.extrinsic_optic_to_user, version=self.tof_info_version,
                        mode=self.mode, imager=self.imager, block=block,
                        range_m=(0.0, ranges[block % len(ranges)] * 1.035))

    # ------------------------------------------------------------------ per frame
    def stamp(self, layout: _Layout, frame_count: int, timestamp_ns: int) -> None:
        """Write the frame count, timestamps and TOF_INFO per-frame fields into a layout's buffer."""
        buf = layout.buffer
        sec, nsec = divmod(max(0, timestamp_ns), 1_000_000_000)
        for pos, version in layout.headers:
            _U32.pack_into(buf, pos + 0x20, frame_count & 0xFFFFFFFF)
            if version == 1:  # v1 has only the microsecond field; later headers leave it 0, as a VPU does
                _U32.pack_into(buf, pos + 0x1C, (timestamp_ns // 1000) & 0xFFFFFFFF)
            else:
                _SEC_NSEC.pack_into(buf, pos + 0x28, sec & 0xFFFFFFFF, nsec)
        if layout.tof_data is None:
            return
        at = layout.tof_data
        _EXTRINSIC.pack_into(buf, at + _TI_EXTRINSIC, *self.extrinsic_optic_to_user)
        if self.tof_info_version >= 2:
            _EXPOSURE_TS.pack_into(buf, at + _TI_EXPOSURE_TS, *(max(0, timestamp_ns),) * 3)
        if self.tof_info_version >= 4:
            ranges = cycle_ranges_m(self.mode)
            block = (frame_count - 1) % len(ranges)  # a cycling mode steps through its blocks frame by frame
            _BLOCK.pack_into(buf, at + _TI_BLOCK, block, 0.0, ranges[block] * 1.035)

    def encode(self, counts: FrameCounts, frame_count: int, timestamp_ns: int,
               chunks: Iterable[int] = DEFAULT_CHUNKS) -> memoryview:
        """The whole PCIC message of a frame, in the reused buffer (valid until the next encode)."""
        h, w = counts.distance.shape
        layout = self.layout(chunks, w, h)
        for ctype, view in layout.views.items():
            src = counts.distance if ctype == 100 else counts.amplitude if ctype == 101 else counts.confidence
            np.copyto(view, src, casting="unsafe")  # 8-bit confidence keeps the low byte
        self.stamp(layout, frame_count, timestamp_ns)
        return memoryview(layout.buffer)

    def payload(self, frame: Frame, frame_count: int, chunks: Iterable[int] = DEFAULT_CHUNKS) -> bytes:
        """The image payload content ``star ... stop`` of a frame (a fresh copy), stamped with its timestamp."""
        msg = self.encode(self.counts(frame), frame_count, max(0, round(frame.timestamp * 1e9)), chunks)
        return bytes(msg[20:-2])
