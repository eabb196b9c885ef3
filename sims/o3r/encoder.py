"""The emulator's frame encoder: one reused PCIC message buffer per chunk selection, filled in place.

The chunk headers, the chunk metadata and the TOF_INFO are laid out once per (chunk
selection, image size); per frame only the pixel data (through numpy views of the
buffer), the frame count, the timestamps and the TOF_INFO's per-frame fields are
written; an image handed in read-only is copied only when it is another array than the
last one copied into that buffer. :meth:`FrameEncoder.payload` keeps the old one-shot API
(a fresh ``bytes``).
"""

from __future__ import annotations

import functools
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

_cycle_ranges_m = functools.cache(cycle_ranges_m)  # per frame: parse each mode name once
_U32 = struct.Struct("<I")
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
    tof_data: int | None                  # offset of TOF_INFO data, if selected
    copied: dict[int, NDArray[np.generic]] = field(default_factory=dict)  # read-only image last copied, per chunk
    # the per-frame fields, written at once: a struct of (frame count per header, microseconds per v1 header,
    # seconds + nanoseconds per v2/v3 header, TOF_INFO v2+ exposure timestamps) and where its bytes go
    stamp_struct: struct.Struct = _U32
    stamp_bytes: NDArray[np.intp] = field(default_factory=lambda: np.zeros(0, np.intp))
    octets: NDArray[np.uint8] = field(default_factory=lambda: np.zeros(0, np.uint8))  # the buffer as bytes
    stamp_counts: tuple[int, int, int, int] = (0, 0, 0, 0)  # how many of each of the four
    tof_written: tuple[object, ...] = ()  # (extrinsic, block, range) last written into the TOF_INFO


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
        if isinstance(chunks, tuple):  # a connection's selection: found as asked, without sorting it again
            found = self._layouts.get((chunks, width, height))
            if found is not None:
                return found
        chunks = tuple(chunks)
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
        layout = _Layout(buf, {}, None)
        counts_at: list[int] = []
        usec_at: list[int] = []
        sec_nsec_at: list[int] = []
        pos = _FIRST
        for ctype in wanted:
            csize, hsize, version = struct.unpack_from("<3I", buf, pos + 4)
            counts_at.append(pos + 0x20)
            # v1 has only the microsecond field; later headers leave it 0, as a VPU does
            (usec_at if version == 1 else sec_nsec_at).append(pos + (0x1C if version == 1 else 0x28))
            if ctype == 420:
                layout.tof_data = pos + hsize
            else:
                dtype = "<u2" if ctype != 300 or conf_size == 2 else "u1"
                layout.views[ctype] = np.frombuffer(buf, dtype=dtype, count=width * height,
                                                    offset=pos + hsize).reshape(height, width)
            pos += csize
        has_exposure = layout.tof_data is not None and self.tof_info_version >= 2
        exposure = [layout.tof_data + _TI_EXPOSURE_TS] if layout.tof_data is not None and has_exposure else []
        layout.stamp_struct = struct.Struct("<" + "I" * (len(counts_at) + len(usec_at)) + "2I" * len(sec_nsec_at)
                                            + "3Q" * len(exposure))
        layout.stamp_bytes = np.array([at + i for ats, size in ((counts_at, 4), (usec_at, 4), (sec_nsec_at, 8),
                                                                (exposure, 24)) for at in ats for i in range(size)],
                                      np.intp)
        layout.stamp_counts = (len(counts_at), len(usec_at), len(sec_nsec_at), len(exposure))
        layout.octets = np.frombuffer(buf, np.uint8)
        self._layouts[key] = self._layouts[(chunks, width, height)] = layout
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
        n_count, n_usec, n_sec_nsec, n_exposure = layout.stamp_counts
        ts = max(0, timestamp_ns)
        sec, nsec = divmod(ts, 1_000_000_000)
        values = ((frame_count & 0xFFFFFFFF,) * n_count + ((timestamp_ns // 1000) & 0xFFFFFFFF,) * n_usec
                  + (sec & 0xFFFFFFFF, nsec) * n_sec_nsec + (ts, ts, ts) * n_exposure)
        # one pack, one scattered write (a third of the time of a write per field)
        layout.octets[layout.stamp_bytes] = np.frombuffer(layout.stamp_struct.pack(*values), np.uint8)
        if layout.tof_data is None:
            return
        at = layout.tof_data
        ranges = _cycle_ranges_m(self.mode)
        block = (frame_count - 1) % len(ranges)  # a cycling mode steps through its blocks frame by frame
        written = (self.extrinsic_optic_to_user, block, ranges[block])
        if written == layout.tof_written:
            return  # what changes only with the mode or the extrinsic is there already
        _EXTRINSIC.pack_into(buf, at + _TI_EXTRINSIC, *self.extrinsic_optic_to_user)
        if self.tof_info_version >= 4:
            _BLOCK.pack_into(buf, at + _TI_BLOCK, block, 0.0, ranges[block] * 1.035)
        layout.tof_written = written

    def encode(self, counts: FrameCounts, frame_count: int, timestamp_ns: int,
               chunks: Iterable[int] = DEFAULT_CHUNKS) -> memoryview:
        """The whole PCIC message of a frame, in the reused buffer (valid until the next encode)."""
        h, w = counts.distance.shape
        layout = self.layout(chunks, w, h)
        for ctype, view in layout.views.items():
            src = counts.distance if ctype == 100 else counts.amplitude if ctype == 101 else counts.confidence
            if src is view:
                continue  # written in place (PerPose)
            if src.flags.writeable:
                layout.copied.pop(ctype, None)
            elif layout.copied.get(ctype) is src:
                continue  # a read-only image already in the buffer
            else:
                layout.copied[ctype] = src  # held: its identity is not reused while it is compared
            np.copyto(view, src, casting="unsafe")  # 8-bit confidence keeps the low byte
        self.stamp(layout, frame_count, timestamp_ns)
        return memoryview(layout.buffer)

    def payload(self, frame: Frame, frame_count: int, chunks: Iterable[int] = DEFAULT_CHUNKS) -> bytes:
        """The image payload content ``star ... stop`` of a frame (a fresh copy), stamped with its timestamp."""
        msg = self.encode(self.counts(frame), frame_count, max(0, round(frame.timestamp * 1e9)), chunks)
        return bytes(msg[20:-2])
