"""A recorded frame decodes to the same bits, its per-frame vendor metadata included."""

from __future__ import annotations

import numpy as np
import pytest

from cellcal.devices.errors import RecordingError
from cellcal.devices.recording.codec import decode_frame, encode_frame
from cellcal.devices.types import Frame, Intrinsics


def _frame(metadata: dict[str, object]) -> Frame:
    intr = Intrinsics(width=4, height=3, fx=5.0, fy=5.0, cx=2.0, cy=1.5, k1=-0.1)
    rng = np.random.default_rng(3)
    xyz = rng.uniform(0.2, 1.0, (3, 4, 3)).astype(np.float32)
    return Frame(distance=np.linalg.norm(xyz, axis=2).astype(np.float32), xyz=xyz,
                 amplitude=rng.uniform(0, 1, (3, 4)).astype(np.float32), valid=np.ones((3, 4), bool),
                 intrinsics=intr, timestamp=1.7e9 + 0.125, sequence=42, metadata=metadata)


def test_metadata_round_trips_with_the_arrays() -> None:
    meta = {"device_timestamp_s": 324896.0004, "measurement_block_index": 1, "mode": "cyclic_4m_2m_4m_2m"}
    back = decode_frame(encode_frame(_frame(meta)))
    assert back.metadata == meta
    assert back.timestamp == 1.7e9 + 0.125 and back.sequence == 42
    assert np.array_equal(back.xyz, _frame(meta).xyz)


def test_a_frame_without_metadata_records_no_key() -> None:
    doc = encode_frame(_frame({}))
    assert "metadata" not in doc
    assert decode_frame(doc).metadata == {}


def test_metadata_that_is_not_an_object_is_refused() -> None:
    doc = encode_frame(_frame({}))
    doc["metadata"] = [1, 2]
    with pytest.raises(RecordingError, match="metadata is a list, not an object"):
        decode_frame(doc)
