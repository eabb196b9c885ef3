"""PCIC framing, chunk walking, TOF_INFO and frame decoding (no sockets)."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from cellcal.devices.errors import ProtocolError
from cellcal.devices.geometry.camera_model import pixel_grid_rays
from cellcal.devices.types import Frame, Intrinsics
from cellcal.drivers.o3r.decode import FrameDecoder
from cellcal.drivers.o3r.pcic import (
    encode_message,
    image_view,
    iter_messages,
    parse_async_error,
    parse_header,
    walk_chunks,
)
from cellcal.drivers.o3r.tofinfo import IntrinsicModel, parse_tof_info, unit_vectors
from cellcal.sims.o3r.encoder import FrameEncoder
from cellcal.sims.o3r.wire import message, models_from_intrinsics

INTR = Intrinsics(width=32, height=24, fx=40.25, fy=41.5, cx=15.5, cy=11.25)
INTR_DIST = Intrinsics(width=32, height=24, fx=40.25, fy=41.5, cx=15.5, cy=11.25, k1=-0.05, k2=0.01, p1=3e-4,
                       p2=-2e-4, k3=0.002)


def plane_frame(intr: Intrinsics, z_m: float = 0.8, seq: int = 3) -> Frame:
    """A fronto-parallel plane at ``z_m`` seen through ``intr``'s exact rays."""
    rays = pixel_grid_rays(intr)
    dist = (z_m / rays[..., 2]).astype(np.float32)
    dist[0, 0] = np.nan  # one invalid pixel
    valid = np.isfinite(dist)
    xyz = (rays * dist[..., None]).astype(np.float32)
    amp = np.full(dist.shape, 123.0, np.float32)
    conf = np.where(valid, 0, 1).astype(np.uint16)
    return Frame(distance=dist, xyz=xyz, amplitude=amp, valid=valid, intrinsics=intr, timestamp=1700000000.25,
                 sequence=seq, confidence=conf)


def image_message(frame: Frame, *, header_version: int = 2, count: int = 7, intr: Intrinsics = INTR) -> bytes:
    rays = pixel_grid_rays(intr) if intr.has_distortion else None
    enc = FrameEncoder(models_from_intrinsics(intr, rays), header_version=header_version)
    return message("0000", enc.payload(frame, count))


# ---------------------------------------------------------------------- framing
def test_header_roundtrip_and_errors() -> None:
    msg = encode_message("1002", b"p7")
    assert msg == b"1002L000000008\r\n1002p7\r\n"
    assert parse_header(msg[:16]) == ("1002", 8)
    with pytest.raises(ProtocolError, match="offset 104"):
        parse_header(b"1002X000000008\r\n", offset=100)
    with pytest.raises(ProtocolError, match="offset 5"):
        parse_header(b"1002L00000000a\r\n")
    with pytest.raises(ProtocolError, match="offset 14"):
        parse_header(b"1002L000000008\n\n")
    with pytest.raises(ProtocolError, match="exceeds the cap"):
        parse_header(b"0000L999999999\r\n", max_payload=1000)
    with pytest.raises(ProtocolError, match="below the minimum"):
        parse_header(b"0000L000000003\r\n")


def test_iter_messages_checks_ticket_and_trailer() -> None:
    stream = encode_message("1000", b"*") + encode_message("0001", b"100000001:too many")
    msgs = list(iter_messages(stream))
    assert [m.ticket for m in msgs] == ["1000", "0001"]
    assert parse_async_error(msgs[1].content) == (100000001, "too many")
    bad = bytearray(stream)
    bad[16:20] = b"1001"
    with pytest.raises(ProtocolError, match="does not match header ticket") as ei:
        list(iter_messages(bytes(bad)))
    assert ei.value.offset == 16
    with pytest.raises(ProtocolError, match="truncated PCIC payload") as ei:
        list(iter_messages(stream[:-3]))
    assert ei.value.offset == len(encode_message("1000", b"*")) + 16


# ---------------------------------------------------------------------- chunks + decoding
@pytest.mark.parametrize("header_version", [1, 2, 3])
def test_decode_plane_exact(header_version: int) -> None:
    frame = plane_frame(INTR)
    msg = next(iter_messages(image_message(frame, header_version=header_version)))
    chunks = walk_chunks(msg.payload)
    assert [c.chunk_type for c in chunks] == [100, 101, 300, 420]
    assert all(c.header_version == header_version for c in chunks)
    dec = FrameDecoder().decode(msg.payload, chunks, received_at=1700000000.3)
    out = dec.frame
    assert out.sequence == 7 and dec.frame_count == 7
    assert not out.valid[0, 0] and np.isnan(out.distance[0, 0]) and np.all(np.isnan(out.xyz[0, 0]))
    assert int(out.valid.sum()) == out.valid.size - 1
    # distance quantised to a VPU's 10 m / 65535 counts; XYZ from model-0 unit vectors (pinhole: exact rays)
    np.testing.assert_allclose(out.distance[out.valid], frame.distance[out.valid], atol=0.5 * 10 / 65535 + 1e-6)
    np.testing.assert_allclose(out.xyz[out.valid], frame.xyz[out.valid], atol=0.0001)
    # amplitude travels as sqrt(a / 1e-6) + 1 in uint16: half a step near 123 is 0.011
    np.testing.assert_allclose(out.amplitude[out.valid], 123.0, atol=0.012)
    assert out.intrinsics == INTR  # float32-representable values round-trip exactly
    if header_version >= 2:  # the device clock is Unix time (0.05 s from the receive time): kept
        assert out.timestamp == pytest.approx(1700000000.25, abs=1e-6)
        assert out.metadata["timestamp_source"] == "device"


def test_decode_distorted_lens_fits_model0_and_keeps_opencv_intrinsics() -> None:
    frame = plane_frame(INTR_DIST)
    out = FrameDecoder().decode(next(iter_messages(image_message(frame, intr=INTR_DIST))).payload).frame
    np.testing.assert_allclose(out.xyz[out.valid], frame.xyz[out.valid], atol=0.0002)
    for name in ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "p1", "p2"):
        assert getattr(out.intrinsics, name) == pytest.approx(float(np.float32(getattr(INTR_DIST, name))), abs=0)


def test_unit_vectors_pinhole_match_exact_rays() -> None:
    m = models_from_intrinsics(INTR)
    uv = unit_vectors(IntrinsicModel(0, m.forward), INTR.width, INTR.height)
    np.testing.assert_allclose(uv, pixel_grid_rays(INTR), atol=2e-7)
    np.testing.assert_allclose(np.linalg.norm(uv, axis=2), 1.0, atol=1e-6)


def test_tof_info_fields() -> None:
    frame = plane_frame(INTR)
    enc = FrameEncoder(models_from_intrinsics(INTR), extrinsic_optic_to_user=(0.01, 0.02, 0.03, 0.1, -0.2, 0.3))
    payload = message("0000", enc.payload(frame, 1))[16:]
    c = next(c for c in walk_chunks(payload) if c.chunk_type == 420)
    info = parse_tof_info(payload[c.data_offset:c.data_offset + c.data_size])
    assert info.version == 4 and info.mode == "standard_range4m" and info.imager == "IRS2381C"
    assert info.measurement_block_index == 0 and info.measurement_range_max_m == pytest.approx(4.14)
    assert info.distance_resolution_m == pytest.approx(10 / 65535, rel=1e-7)
    assert info.extrinsic_optic_to_user == pytest.approx((0.01, 0.02, 0.03, 0.1, -0.2, 0.3), rel=1e-6)
    assert info.intrinsic.model_id == 0 and info.inverse_intrinsic.model_id == 1
    with pytest.raises(ProtocolError, match="needs at least 312"):
        parse_tof_info(payload[c.data_offset:c.data_offset + 100])


@pytest.mark.parametrize(("field_off", "value", "match"), [
    (4, float("nan"), "distanceResolution nan"),
    (4, 0.0, "distanceResolution 0.0"),
    (4, 5.0, "distanceResolution 5.0"),          # 65535 counts would be 330 km
    (8, float("inf"), "amplitudeResolution inf"),
    (8, 1e30, r"amplitudeResolution 1\.0\d*e\+30"),       # (a-1)^2 x 1e30 overflows float32
    (8, -1.0, "amplitudeResolution -1.0"),
])
def test_tof_info_rejects_absurd_resolutions(field_off: int, value: float, match: str) -> None:
    payload = bytearray(message("0000", FrameEncoder(models_from_intrinsics(INTR)).payload(plane_frame(INTR), 1))[16:])
    c = next(c for c in walk_chunks(payload) if c.chunk_type == 420)
    struct.pack_into("<f", payload, c.data_offset + field_off, value)
    with pytest.raises(ProtocolError, match=match) as err:
        parse_tof_info(payload[c.data_offset:c.data_offset + c.data_size], offset=c.data_offset)
    assert err.value.offset == c.data_offset + field_off


def _first_chunk_field(payload: bytearray, off: int, value: int) -> bytearray:
    struct.pack_into("<I", payload, 8 + off, value)
    return payload


@pytest.mark.parametrize(("field_off", "value", "match", "at"), [
    (4, 0x7FFFFFF0, "runs past 'stop'", 12),
    (4, 10, "smaller than HEADER_SIZE", 12),
    (8, 20, "too small for header version", 16),
    (12, 9, "unsupported HEADER_VERSION", 20),
    (16, 100000, "absurd image size", 24),
])
def test_walk_chunks_violations_name_offset(field_off: int, value: int, match: str, at: int) -> None:
    payload = bytearray(image_message(plane_frame(INTR))[16:])
    _first_chunk_field(payload, field_off, value)
    with pytest.raises(ProtocolError, match=match) as ei:
        walk_chunks(payload)
    assert ei.value.offset == at


def test_missing_markers_and_short_pixel_data() -> None:
    good = image_message(plane_frame(INTR))[16:]
    with pytest.raises(ProtocolError, match="'star'") as ei:
        walk_chunks(good[:4] + b"STAR" + good[8:])
    assert ei.value.offset == 4
    with pytest.raises(ProtocolError, match="'stop'"):
        walk_chunks(good[:-6] + b"stap\r\n")
    p = bytearray(good)
    struct.pack_into("<I", p, 8 + 16, 64)  # distance chunk claims 64 columns
    chunk = walk_chunks(p)[0]
    with pytest.raises(ProtocolError, match="data bytes"):
        image_view(p, chunk)


@pytest.mark.parametrize(("width", "height"), [(224, 172), (32, 23), (33, 24), (0, 0)])
def test_frame_whose_size_disagrees_with_its_tof_info_is_refused(width: int, height: int) -> None:
    payload = bytearray(image_message(plane_frame(INTR))[16:])
    info = next(c for c in walk_chunks(payload) if c.chunk_type == 420)
    struct.pack_into("<2I", payload, info.offset + 16, width, height)  # the TOF_INFO header's IMAGE_WIDTH/HEIGHT
    with pytest.raises(ProtocolError, match=f"distance image is 32x24 but its TOF_INFO says {width}x{height}") as ei:
        FrameDecoder().decode(payload, offset=1000)
    assert ei.value.offset == 1000 + info.offset + 16
    struct.pack_into("<2I", payload, info.offset + 16, 32, 24)
    assert FrameDecoder().decode(payload).frame.distance.shape == (24, 32)


# The bounded fuzz of this parser lives in tests/integration/faults/test_fuzz_parsers.py (targets shared with
# benchmarks/fuzz_parsers.py, see tests/support/fuzz_targets.py).
