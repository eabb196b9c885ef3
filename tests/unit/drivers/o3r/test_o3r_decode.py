"""The O3R decoder's validity rule: the confidence image's invalid bit wins over a valid-looking distance."""

from __future__ import annotations

import dataclasses
import json
import logging
import struct
import time
from typing import Any

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_o3r_pcic import INTR, INTR_DIST, plane_frame

from cellcal.devices.errors import ProtocolError
from cellcal.devices.geometry.camera_model import pixel_grid_rays
from cellcal.devices.types import Frame, Intrinsics
from cellcal.drivers.o3r.decode import FrameDecoder
from cellcal.drivers.o3r.pcic import iter_messages, walk_chunks
from cellcal.sims.o3r.encoder import FrameEncoder
from cellcal.sims.o3r.wire import message, models_from_intrinsics

#: (row, col) -> confidence word: bit 0 set on pixels whose distance is a plausible 0.8 m plane;
#: other bits alone (as the VPU sets for e.g. low amplitude) must not invalidate a pixel.
CONFIDENCE = {(3, 5): 0x0001, (10, 20): 0x0081, (23, 31): 0xFFFF, (12, 7): 0x0002, (5, 5): 0x8000, (0, 9): 0x00FE}


def payload_with(confidence_bits: int) -> tuple[Frame, bytes]:
    frame = plane_frame(INTR)
    conf = np.where(frame.valid, 0, 1).astype(np.uint16)
    for (r, c), word in CONFIDENCE.items():
        conf[r, c] = word
    frame = Frame(distance=frame.distance, xyz=frame.xyz, amplitude=frame.amplitude, valid=frame.valid,
                  intrinsics=frame.intrinsics, timestamp=frame.timestamp, sequence=frame.sequence, confidence=conf)
    enc = FrameEncoder(models_from_intrinsics(INTR), confidence_bits=confidence_bits)
    return frame, next(iter_messages(message("0000", enc.payload(frame, 5)))).payload


@pytest.mark.parametrize("confidence_bits", [16, 8])
def test_invalid_bit_invalidates_a_pixel_with_a_valid_looking_distance(confidence_bits: int) -> None:
    frame, payload = payload_with(confidence_bits)
    out = FrameDecoder().decode(payload, received_at=1700000000.3).frame
    sent = {(r, c): w if confidence_bits == 16 else w & 0xFF for (r, c), w in CONFIDENCE.items()}
    for (r, c), word in sent.items():
        assert np.isfinite(frame.distance[r, c]) and frame.distance[r, c] > 0.7  # it looks like a measurement
        assert out.confidence is not None and int(out.confidence[r, c]) == word  # kept as sent
        if word & 1:
            assert not out.valid[r, c], (r, c, hex(word))
            assert np.isnan(out.distance[r, c]) and np.all(np.isnan(out.xyz[r, c]))
        else:
            assert out.valid[r, c], (r, c, hex(word))
            assert out.distance[r, c] == pytest.approx(frame.distance[r, c], abs=1e-3)
    # everything else: only the pixel without a distance is invalid
    expected_invalid = 1 + sum(1 for w in sent.values() if w & 1)
    assert int((~out.valid).sum()) == expected_invalid
    assert np.array_equal(np.isnan(out.distance), ~out.valid)


def test_a_frame_without_confidence_is_valid_wherever_it_has_a_distance() -> None:
    frame, payload = payload_with(16)
    chunks = [c for c in walk_chunks(payload) if c.chunk_type != 300]  # drop the confidence chunk
    out = FrameDecoder().decode(payload, chunks, received_at=1700000000.3).frame
    assert out.confidence is None
    assert int((~out.valid).sum()) == 1 and not out.valid[0, 0]  # only the raw-0 pixel
    assert out.valid[3, 5] and out.distance[3, 5] == pytest.approx(frame.distance[3, 5], abs=1e-3)


def encoded(frame: Frame, intr: Intrinsics = INTR, **encoder: Any) -> bytes:
    """The payload of one image message for ``frame`` (distorted lenses with their exact rays)."""
    rays = pixel_grid_rays(intr) if intr.has_distortion else None
    enc = FrameEncoder(models_from_intrinsics(intr, rays), **encoder)
    return next(iter_messages(message("0000", enc.payload(frame, 5)))).payload


def test_xyz_is_in_the_optical_frame_unless_the_user_frame_is_asked_for() -> None:
    frame = plane_frame(INTR)
    extrinsic = (0.01, -0.02, 0.35, 0.1, -0.2, 0.3)  # tx, ty, tz (m), rotX, rotY, rotZ (rad)
    payload = encoded(frame, extrinsic_optic_to_user=extrinsic)
    optic = FrameDecoder().decode(payload, received_at=1700000000.3).frame
    user = FrameDecoder(apply_extrinsic=True).decode(payload, received_at=1700000000.3).frame
    ok = optic.valid
    np.testing.assert_allclose(optic.xyz[ok], frame.xyz[ok], atol=1e-4)
    # p_user = Rx(rotX) Ry(rotY) Rz(rotZ) p_optic + t, written here with scipy's intrinsic XYZ angles
    rot = Rotation.from_euler("XYZ", extrinsic[3:]).as_matrix()
    expected = optic.xyz[ok].astype(np.float64) @ rot.T + np.array(extrinsic[:3])
    np.testing.assert_allclose(user.xyz[ok], expected, atol=1e-5)
    assert np.all(np.isnan(user.xyz[~ok])) and user.xyz.dtype == np.float32 and user.xyz.shape == (24, 32, 3)
    np.testing.assert_array_equal(user.distance, optic.distance)  # ranges do not depend on the frame


def test_one_decoder_serves_changing_lenses_and_sizes() -> None:
    """Cached unit vectors and intrinsics follow the lens and the image size of each frame."""
    small = Intrinsics(width=16, height=12, fx=20.25, fy=21.5, cx=7.5, cy=5.25)
    payloads = [encoded(plane_frame(INTR)), encoded(plane_frame(INTR_DIST), INTR_DIST),
                encoded(plane_frame(small), small), encoded(plane_frame(INTR))]
    shared = FrameDecoder()
    for payload in payloads:
        got = shared.decode(payload, received_at=1700000000.3).frame
        fresh = FrameDecoder().decode(payload, received_at=1700000000.3).frame
        assert got.intrinsics == fresh.intrinsics
        np.testing.assert_array_equal(got.xyz, fresh.xyz)
    assert shared.decode(payloads[2], received_at=1.0).frame.intrinsics.width == 16


def test_a_pixel_without_a_distance_is_invalid_whatever_its_confidence() -> None:
    payload = bytearray(encoded(plane_frame(INTR)))
    conf_c = next(c for c in walk_chunks(payload) if c.chunk_type == 300)
    struct.pack_into("<H", payload, conf_c.data_offset, 0)  # pixel (0, 0): raw distance 0, confidence says valid
    out = FrameDecoder().decode(bytes(payload), received_at=1700000000.3).frame
    assert out.confidence is not None and int(out.confidence[0, 0]) == 0
    assert not out.valid[0, 0] and np.isnan(out.distance[0, 0]) and int((~out.valid).sum()) == 1
    assert out.distance.dtype == np.float32


def test_without_an_amplitude_chunk_the_amplitude_is_zero() -> None:
    payload = encoded(plane_frame(INTR))
    chunks = [c for c in walk_chunks(payload) if c.chunk_type != 101]
    out = FrameDecoder().decode(payload, chunks, received_at=1700000000.3).frame
    assert out.amplitude.dtype == np.float32 and out.amplitude.shape == (24, 32) and not out.amplitude.any()


def spoil(payload: bytes, chunk_type: int, field_off: int, fmt: str, value: int) -> tuple[bytes, int]:
    """The payload with one header field of the first chunk of ``chunk_type`` changed; the field's offset."""
    out = bytearray(payload)
    c = next(c for c in walk_chunks(out) if c.chunk_type == chunk_type)
    struct.pack_into(fmt, out, c.offset + field_off, value)
    return bytes(out), c.offset + field_off


@pytest.mark.parametrize(("chunk_type", "field_off", "fmt", "value", "message", "at"), [
    (100, 24, "<I", 3, r"chunk 100: PIXEL_FORMAT 3, expected one of \(2,\)", 24),
    (101, 24, "<I", 0, r"chunk 101: PIXEL_FORMAT 0, expected one of \(2,\)", 24),
    (300, 24, "<I", 6, r"chunk 300: PIXEL_FORMAT 6, expected one of \(0, 2\)", 24),
    (101, 16, "<2I", (16, 24), r"chunk 101 is 16x24, distance image is 32x24", 16),
    (300, 16, "<2I", (32, 12), r"chunk 300 is 32x12, distance image is 32x24", 16),
])
def test_bad_chunks_are_named_at_their_stream_offset(chunk_type: int, field_off: int, fmt: str, value: Any,
                                                     message: str, at: int) -> None:
    payload = bytearray(encoded(plane_frame(INTR)))
    c = next(c for c in walk_chunks(payload) if c.chunk_type == chunk_type)
    struct.pack_into(fmt, payload, c.offset + field_off, *(value if isinstance(value, tuple) else (value,)))
    with pytest.raises(ProtocolError, match=message) as info:
        FrameDecoder().decode(bytes(payload), offset=5000, received_at=1700000000.3)
    assert info.value.offset == 5000 + c.offset + at


def test_missing_chunks_and_an_unusable_lens_model_are_protocol_errors() -> None:
    payload = encoded(plane_frame(INTR))
    chunks = walk_chunks(payload)
    for drop, names in ((100, "RADIAL_DISTANCE (100)"), (420, "TOF_INFO (420)")):
        with pytest.raises(ProtocolError) as info:
            FrameDecoder().decode(payload, [c for c in chunks if c.chunk_type != drop], offset=100)
        assert str(info.value) == f"image lacks chunk(s) {names} (at byte offset 108)"
    with pytest.raises(ProtocolError, match=r"image lacks chunk\(s\) RADIAL_DISTANCE \(100\), TOF_INFO \(420\)"):
        FrameDecoder().decode(payload, [c for c in chunks if c.chunk_type not in (100, 420)])
    # a TOF_INFO whose inverse (ray -> pixel) model has focal length 0: no camera, refused
    bad = bytearray(payload)
    info_c = next(c for c in chunks if c.chunk_type == 420)
    blob = bytes(bad[info_c.data_offset:info_c.data_offset + info_c.data_size])
    fx_at = info_c.data_offset + blob.rindex(struct.pack("<f", np.float32(INTR.fx)))  # the inverse model's fx
    struct.pack_into("<f", bad, fx_at, 0.0)
    with pytest.raises(ProtocolError, match=r"^TOF_INFO intrinsic calibration is unusable: "):
        FrameDecoder().decode(bytes(bad), received_at=1700000000.3)


def stamped(timestamp_s: float, header_version: int = 2, **encoder: Any) -> bytes:
    frame = dataclasses.replace(plane_frame(INTR), timestamp=timestamp_s)
    return encoded(frame, header_version=header_version, **encoder)


def test_device_time_is_the_frame_time_when_it_is_unix_time() -> None:
    device = 1700000000.0  # whole seconds: exact in float64 nanoseconds, so the 5 s edge is exact
    out = FrameDecoder(clock_tolerance_s=5.0).decode(stamped(device), received_at=device + 5.0).frame
    assert out.timestamp == device
    assert (out.metadata["timestamp_source"], out.metadata["device_timestamp_s"]) == ("device", device)
    out = FrameDecoder(clock_tolerance_s=5.0).decode(stamped(device), received_at=device - 5.0).frame
    assert out.timestamp == device and out.metadata["timestamp_source"] == "device"


def test_a_device_clock_that_is_not_unix_time_gives_the_receive_time_and_one_warning(
        caplog: pytest.LogCaptureFixture) -> None:
    device = 1700000000.0
    decoder = FrameDecoder(clock_tolerance_s=5.0)
    with caplog.at_level(logging.WARNING, logger="cellcal.drivers.o3r.decode"):
        for received in (device + 5.5, device - 7.0, device + 1e6):
            out = decoder.decode(stamped(device), received_at=received).frame
            assert out.timestamp == received
            assert (out.metadata["timestamp_source"], out.metadata["device_timestamp_s"]) == ("receive", device)
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1
    assert warnings[0].getMessage() == (
        "O3R clock reads 1700000000.000 s, -6 s from this host's clock: not Unix time (set up SNTP on the VPU, "
        "/device/clock/sntp); frames are stamped with their receive time, the device time is kept in "
        "Frame.metadata['device_timestamp_s']")
    # the default tolerance is 30 s
    assert FrameDecoder().decode(stamped(device), received_at=device + 29.0).frame.timestamp == device
    assert FrameDecoder().decode(stamped(device), received_at=device + 31.0).frame.timestamp == device + 31.0


def test_frames_without_a_clock_and_old_headers() -> None:
    before = time.time()
    out = FrameDecoder().decode(stamped(0.0)).frame  # no time in the chunks, no receive time given: now
    assert before <= out.timestamp <= time.time()
    assert (out.metadata["timestamp_source"], out.metadata["device_timestamp_s"]) == ("receive", None)
    # header version 1 carries a 32-bit microsecond counter only
    device_us = (round(1700000000.25 * 1e6)) & 0xFFFFFFFF
    out = FrameDecoder().decode(stamped(1700000000.25, header_version=1), received_at=1700000000.3).frame
    assert out.metadata["device_timestamp_s"] == pytest.approx(device_us * 1e-6, abs=1e-6)
    assert out.timestamp == 1700000000.3 and out.metadata["timestamp_source"] == "receive"
    near = FrameDecoder().decode(stamped(1700000000.25, header_version=1), received_at=device_us * 1e-6 + 1.0)
    assert near.frame.metadata["timestamp_source"] == "device"


@pytest.mark.parametrize(("confidence_bits", "with_confidence", "expected_bits"),
                         [(16, True, 16), (8, True, 8), (16, False, None)])
def test_metadata_names_the_mode_imager_range_and_confidence_bits(confidence_bits: int, with_confidence: bool,
                                                                  expected_bits: int | None) -> None:
    payload = stamped(1700000000.25, confidence_bits=confidence_bits)
    chunks = [c for c in walk_chunks(payload) if with_confidence or c.chunk_type != 300]
    meta = FrameDecoder().decode(payload, chunks, received_at=1700000000.3).frame.metadata
    assert {k: meta[k] for k in ("tof_info_version", "mode", "imager", "measurement_block_index",
                                 "confidence_bits")} == {
        "tof_info_version": 4, "mode": "standard_range4m", "imager": "IRS2381C", "measurement_block_index": 0,
        "confidence_bits": expected_bits}
    assert meta["measurement_range_max_m"] == pytest.approx(4.14, abs=1e-6)
    assert meta["measurement_range_min_m"] is None or 0.0 <= meta["measurement_range_min_m"] < 4.14
    json.dumps(meta, allow_nan=False)  # plain JSON: NaN ranges come out as None


def test_amplitude_is_ifm_s_normalised_value_and_minus_one_without_a_measurement() -> None:
    payload = bytearray(encoded(plane_frame(INTR)))
    amp_c = next(c for c in walk_chunks(payload) if c.chunk_type == 101)
    raw = np.array([0, 1, 2, 1001, 65535], dtype="<u2")  # the first five pixels of row 0
    payload[amp_c.data_offset:amp_c.data_offset + raw.nbytes] = raw.tobytes()
    decoded = FrameDecoder().decode(bytes(payload), received_at=1700000000.3)
    resolution = decoded.tof_info.amplitude_resolution
    assert resolution == pytest.approx(1e-6, rel=1e-6)
    expected = [-1.0, 0.0, resolution, 1e6 * resolution, 65534.0 ** 2 * resolution]  # (raw - 1)^2 x resolution
    assert decoded.frame.amplitude[0, :5].tolist() == pytest.approx(expected, rel=1e-6)
    assert decoded.frame.amplitude.dtype == np.float32


def test_errors_found_anywhere_in_the_payload_carry_its_stream_offset() -> None:
    payload = encoded(plane_frame(INTR))
    decoded = FrameDecoder().decode(payload, received_at=1700000000.3)
    assert decoded.tof_info.mode == "standard_range4m" and decoded.frame_count == 5
    # chunk walking (no chunk list given), default offset 0 and a given one
    bad, at = spoil(payload, 100, 12, "<I", 9)  # HEADER_VERSION 9
    for offset in (0, 7000):
        with pytest.raises(ProtocolError, match="unsupported HEADER_VERSION") as info:
            FrameDecoder().decode(bad, offset=offset) if offset else FrameDecoder().decode(bad)
        assert info.value.offset == offset + at
    # a pixel format, default offset
    bad, at = spoil(payload, 100, 24, "<I", 3)
    with pytest.raises(ProtocolError, match="PIXEL_FORMAT 3") as info:
        FrameDecoder().decode(bad)
    assert info.value.offset == at
    # a TOF_INFO field
    info_c = next(c for c in walk_chunks(payload) if c.chunk_type == 420)
    broken = bytearray(payload)
    struct.pack_into("<f", broken, info_c.data_offset + 4, 0.0)  # distanceResolution 0
    with pytest.raises(ProtocolError, match=r"distanceResolution 0\.0") as info:
        FrameDecoder().decode(bytes(broken), offset=300)
    assert info.value.offset == 300 + info_c.data_offset + 4


def test_a_measurement_range_the_head_does_not_know_is_none() -> None:
    payload = bytearray(stamped(1700000000.25))
    info_c = next(c for c in walk_chunks(payload) if c.chunk_type == 420)
    blob = bytes(payload[info_c.data_offset:info_c.data_offset + info_c.data_size])
    at = info_c.data_offset + blob.index(struct.pack("<f", np.float32(4.14)))  # rangeMax; rangeMin just before
    struct.pack_into("<2f", payload, at - 4, float("nan"), float("inf"))
    meta = FrameDecoder().decode(bytes(payload), received_at=1700000000.3).frame.metadata
    assert meta["measurement_range_min_m"] is None and meta["measurement_range_max_m"] is None
    json.dumps(meta, allow_nan=False)
