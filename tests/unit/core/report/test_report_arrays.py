"""The compact map encoding of the report data: exact round trips, bounded width, malformed input refused."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cellcal.core.report.arrays import MAX_MAP_WIDTH_PX, decode_array, downsample_step, encode_array


def test_float16_and_uint8_maps_round_trip_through_json() -> None:
    rng = np.random.default_rng(3)
    depth_mm = rng.uniform(300.0, 900.0, (172, 224)).astype(np.float32)
    depth_mm[5:9, 10:20] = np.nan
    classes = rng.integers(0, 8, (172, 224)).astype(np.uint8)
    for array, dtype in ((depth_mm, "float16"), (classes, "uint8")):
        doc = json.loads(json.dumps(encode_array(array, dtype)))
        back = decode_array(doc)
        assert back.shape == array.shape and back.dtype == np.dtype(dtype)
        np.testing.assert_array_equal(back, array.astype(dtype))  # NaN where it was NaN
    # float16 keeps a depth in mm to 0.5 mm below 1 m
    assert np.nanmax(np.abs(decode_array(encode_array(depth_mm, "float16")) - depth_mm)) <= 0.25


def test_a_map_compresses() -> None:
    flat = np.zeros((800, 1280), dtype=np.uint8)
    assert len(encode_array(flat, "uint8")["zlib_b64"]) < 10_000  # 1 MB of zeros


def test_downsample_step_keeps_at_most_the_maximum_width() -> None:
    assert downsample_step(224) == 1
    assert downsample_step(MAX_MAP_WIDTH_PX) == 1
    assert downsample_step(1280) == 4
    assert len(range(0, 1281, downsample_step(1281))) <= MAX_MAP_WIDTH_PX


def test_malformed_entries_are_refused() -> None:
    doc = encode_array(np.arange(12, dtype=np.uint8).reshape(3, 4), "uint8")
    with pytest.raises(ValueError, match="for shape"):
        decode_array({**doc, "shape": [5, 5]})
    with pytest.raises(ValueError, match="dtype"):
        decode_array({**doc, "dtype": "object"})
    with pytest.raises(ValueError, match="dtype"):
        encode_array(np.zeros(3), "float64")
