"""The driver against real O3R data: two captures from ifm's ifm3d test data (see tests/data/o3r/NOTICE.md).

``O3RBuffer.data`` is a whole 3D-port result payload of older firmware (chunk header
versions 3 and 2 mixed, a 205-byte header, 8-bit confidence, TOF_INFO v1, the VPU's own
clock); ``tof_info.data`` a TOF_INFO v4 of current firmware behind ifm3d's 16-byte test
buffer header (width, height, channels, pixel format). The chunk table and pixel data are
read here with ``struct`` / numpy on their own, so the decoder is checked, not echoed.
"""

from __future__ import annotations

import logging
import math
import struct
from pathlib import Path

import numpy as np
import pytest

from cellcal.devices.errors import ProtocolError
from cellcal.devices.types import Intrinsics
from cellcal.drivers.o3r.decode import FrameDecoder
from cellcal.drivers.o3r.tofinfo import MIN_SIZE_V4, parse_tof_info
from cellcal.sims.o3r.wire import models_from_intrinsics, tof_info
from tests.support.repo_paths import O3R_DATA

DATA = O3R_DATA
BUFFER = DATA / "O3RBuffer.data"
TOF_V4 = DATA / "tof_info.data"
#: The real captures' distance resolution: 10 m over 16 bits.
RES = 10.0 / 65535.0


def _read(path: Path) -> bytes:
    return path.read_bytes()  # committed under tests/data/o3r: a missing file is an error, not a skip


def _chunk_table(payload: bytes) -> dict[int, tuple[int, int, int, int, int, int]]:
    """type -> (header version, header size, data offset, width, height, pixel format), walked with struct alone."""
    out = {}
    pos = 8  # after the ticket and "star"
    while pos < len(payload) - 6:
        ctype, csize, hsize, version, w, h, fmt = struct.unpack_from("<7I", payload, pos)
        out[ctype] = (version, hsize, pos + hsize, w, h, fmt)
        pos += csize
    return out


def test_real_frame_decodes_with_8_bit_confidence_and_mixed_headers() -> None:
    payload = _read(BUFFER)
    table = _chunk_table(payload)
    assert {v[0] for v in table.values()} == {2, 3}  # header versions mixed in one frame
    assert table[101][1] == 205  # an odd header size: the amplitude data is not 2-byte aligned
    assert table[300][5] == 0  # 8-bit confidence
    _, _, d_off, w, h, _ = table[100]
    raw = np.frombuffer(payload, "<u2", w * h, d_off).reshape(h, w)
    conf = np.frombuffer(payload, "u1", w * h, table[300][2]).reshape(h, w)

    received = 1.7e9
    out = FrameDecoder().decode(payload, received_at=received)
    f = out.frame
    assert f.distance.shape == (172, 224)
    # invalid exactly where the raw distance is 0 or the confidence's bit 0 is set
    invalid = (raw == 0) | (conf & 1 == 1)
    assert np.array_equal(~f.valid, invalid)
    assert 0.1 < f.valid.mean() < 0.9
    # distance = raw x resolution, bit for bit in float32
    want = raw.astype(np.float32) * np.float32(RES)
    assert np.array_equal(f.distance[f.valid], want[f.valid])
    assert np.all(np.isnan(f.distance[~f.valid]))
    # XYZ is a unit ray times the distance
    np.testing.assert_allclose(np.linalg.norm(f.xyz[f.valid], axis=1), f.distance[f.valid], rtol=2e-6)
    assert f.confidence is not None and f.confidence.dtype == np.uint8
    assert np.array_equal(f.confidence, conf)
    assert f.metadata["confidence_bits"] == 8 and f.metadata["tof_info_version"] == 1
    assert f.sequence == 1544


def test_real_tof_info_v1_and_its_factory_extrinsic() -> None:
    payload = _read(BUFFER)
    out = FrameDecoder().decode(payload, received_at=1.7e9)
    info = out.tof_info
    assert info.version == 1
    assert info.distance_resolution_m == pytest.approx(RES, rel=1e-7)
    # the v3 chunk header's JSON says the same resolution as TOF_INFO
    assert b'"DistanceResolution":0.00015259021893143654' in payload[:200]
    assert info.extrinsic_optic_to_user[2] == pytest.approx(-0.01529, abs=1e-5)  # not zero on a real head
    assert info.intrinsic.model_id == 0 and info.inverse_intrinsic.model_id == 1
    intr = out.frame.intrinsics
    assert (intr.fx, intr.cx, intr.cy) == pytest.approx((124.344284, 111.0, 85.0), abs=1e-5)
    assert math.isnan(info.measurement_range_max_m) and info.measurement_block_index == 0


def test_device_clock_far_from_unix_time_gives_receive_time_logged_once(caplog: pytest.LogCaptureFixture) -> None:
    payload = _read(BUFFER)
    dec = FrameDecoder()
    with caplog.at_level(logging.WARNING, logger="cellcal.drivers.o3r.decode"):
        a = dec.decode(payload, received_at=1.7e9).frame
        b = dec.decode(payload, received_at=1.7e9 + 0.05).frame
    # the capture's clock reads 3.76 days: time since boot, not Unix time
    assert a.metadata["device_timestamp_s"] == pytest.approx(324896.000402, abs=1e-6)
    assert a.metadata["timestamp_source"] == "receive" and a.timestamp == 1.7e9
    assert b.timestamp == 1.7e9 + 0.05
    warnings = [r for r in caplog.records if "not Unix time" in r.getMessage()]
    assert len(warnings) == 1 and "SNTP" in warnings[0].getMessage()
    # a device clock within the tolerance of the receive time is used as it is
    near = FrameDecoder(clock_tolerance_s=5.0).decode(payload, received_at=324896.000402 + 2.0).frame
    assert near.metadata["timestamp_source"] == "device"
    assert near.timestamp == pytest.approx(324896.000402, abs=1e-6)


def test_real_tof_info_v4_exposes_measurement_block_and_range() -> None:
    blob = _read(TOF_V4)
    width, height, channels, fmt = struct.unpack_from("<4I", blob)  # ifm3d's test-buffer header
    assert (width, height, channels, fmt) == (MIN_SIZE_V4, 1, 1, 0)
    info = parse_tof_info(blob[16:])
    # the values ifm3d's own test expects of this capture (modules/deserialize/test/data/tof_info_test_data.hpp)
    assert info.version == 4 and info.mode == "standard_range4m" and info.imager == "IRS2381C"
    assert info.distance_resolution_m == pytest.approx(0.00015259, abs=1e-9)
    assert info.measurement_block_index == 0
    assert info.measurement_range_min_m == 0.0
    assert info.measurement_range_max_m == pytest.approx(4.143615246, abs=1e-6)
    assert info.illumination_temperature_c == pytest.approx(58.336933, abs=1e-5)
    assert info.exposure_times_s == pytest.approx((0.0000199877, 0.0004, 0.00499938), rel=1e-5)  # ifm prints 6 digits
    assert info.extrinsic_optic_to_user == pytest.approx((0, 0, 0.00841006, -0.0204563, 0.0181109, -0.00622652),
                                                         abs=1e-7)
    deser = pytest.importorskip("ifm3dpy.deserialize")
    ifm = deser.TOFInfoV4.deserialize(np.frombuffer(blob[16:], np.uint8))
    assert (ifm.measurement_block_index, ifm.measurement_range_min) == (info.measurement_block_index,
                                                                        info.measurement_range_min_m)
    assert ifm.measurement_range_max == pytest.approx(info.measurement_range_max_m, rel=1e-7)
    assert ifm.mode.rstrip("\0") == info.mode


@pytest.mark.parametrize(("version", "size"), [(1, 312), (2, 348), (3, 416), (4, 428), (5, 428)])
def test_tof_info_versions_1_to_4_and_later_read_as_4(version: int, size: int) -> None:
    models = models_from_intrinsics(Intrinsics(224, 172, 120.0, 120.0, 111.5, 85.5))
    blob = tof_info(distance_resolution_m=RES, amplitude_resolution=1e-6, models=models, version=min(version, 4),
                    mode="cyclic_4m_2m_4m_2m", block=3, range_m=(0.1, 2.07))
    blob = struct.pack("<I", version) + blob[4:]
    assert len(blob) == size
    info = parse_tof_info(blob + b"\0" * 8)  # later versions may append fields
    assert info.version == version
    if version >= 4:
        assert info.measurement_block_index == 3
        assert (info.measurement_range_min_m, info.measurement_range_max_m) == pytest.approx((0.1, 2.07))
    else:
        assert info.measurement_block_index == 0 and math.isnan(info.measurement_range_max_m)
    if version >= 3:
        assert info.mode == "cyclic_4m_2m_4m_2m"
    short = "needs at least 312" if version == 1 else f"version {version} needs {size} bytes"
    with pytest.raises(ProtocolError, match=short):
        parse_tof_info(blob[:size - 1])
