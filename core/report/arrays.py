"""Compact arrays in JSON: a downsampled map as ``{"dtype", "shape", "zlib_b64"}`` (ADR 0037)."""

from __future__ import annotations

import base64
import zlib
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["MAX_MAP_WIDTH_PX", "decode_array", "downsample_step", "encode_array"]

#: Widest map stored per pose, pixels: wider images are kept every ``step``-th pixel.
MAX_MAP_WIDTH_PX = 320
#: dtypes an encoded array may have (float16 maps in mm, uint8 class maps).
_DTYPES = {"float16", "float32", "uint8"}


def downsample_step(width_px: int, max_width_px: int = MAX_MAP_WIDTH_PX) -> int:
    """The stride that keeps at most ``max_width_px`` columns of an image ``width_px`` wide."""
    return max(1, -(-int(width_px) // max_width_px))


def encode_array(array: NDArray[Any], dtype: str) -> dict[str, Any]:
    """``array`` cast to ``dtype``, zlib-compressed and base64-encoded, with its shape (JSON data)."""
    if dtype not in _DTYPES:
        raise ValueError(f"dtype {dtype!r}: expected one of {sorted(_DTYPES)}")
    data = np.ascontiguousarray(array, dtype=np.dtype(dtype).newbyteorder("<"))
    return {"dtype": dtype, "shape": list(data.shape),
            "zlib_b64": base64.b64encode(zlib.compress(data.tobytes(), 6)).decode("ascii")}


def decode_array(doc: dict[str, Any]) -> NDArray[Any]:
    """The array of :func:`encode_array` (native byte order).

    Raises:
        ValueError: Malformed entry (unknown dtype, or a size that does not match its shape).
    """
    dtype = str(doc.get("dtype"))
    if dtype not in _DTYPES:
        raise ValueError(f"dtype {dtype!r}: expected one of {sorted(_DTYPES)}")
    shape = tuple(int(n) for n in doc["shape"])
    raw = zlib.decompress(base64.b64decode(doc["zlib_b64"]))
    out = np.frombuffer(raw, dtype=np.dtype(dtype).newbyteorder("<"))
    if out.size != int(np.prod(shape)):
        raise ValueError(f"{out.size} values for shape {list(shape)}")
    return out.reshape(shape).astype(np.dtype(dtype))
