"""The OAK's grey image beside its depth: depthai ``ImgFrame`` → float32, and the same-capture check.

Used by :class:`~cellcal.drivers.oak.camera.OakCamera` for ``Frame.amplitude``.
Design: docs/adr/0015-vendor-drivers.md.
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from cellcal.devices.errors import FrameSyncError, ProtocolError

# ImgFrame types whose first plane is the grey image, and the numpy dtype of one pixel of it.
# NV12 / NV21 / YUV420p / YUV400p start with the full-size luma (Y) plane: the grey image itself.
GREY_PLANE_DTYPES: dict[str, type[np.generic]] = {
    "GRAY8": np.uint8, "RAW8": np.uint8, "NV12": np.uint8, "NV21": np.uint8, "YUV420p": np.uint8,
    "YUV400p": np.uint8, "RAW16": np.uint16, "GRAYF16": np.float16,
}


def grey_image(msg: Any, shape: tuple[int, int]) -> NDArray[np.float32]:
    """The grey image carried by a depthai ``ImgFrame``, as float32 in its own units.

    8-bit types (mono ``GRAY8`` / ``RAW8``, or the luma plane of a colour ``NV12`` frame)
    give grey levels 0..255; ``RAW16`` (a ToF amplitude image) gives the sensor's raw
    amplitude counts 0..65535; ``GRAYF16`` gives its half-float values. Row padding
    (``getStride()``) is skipped.

    Args:
        msg: The ``dai.ImgFrame``.
        shape: Expected (height, width), pixels — the depth image's.

    Returns:
        float32 (H, W) image.

    Raises:
        ProtocolError: If the type is not a grey-carrying one, the size differs from
            ``shape``, or the buffer is shorter than its size and stride say.
    """
    type_name = str(msg.getType().name)
    dtype = GREY_PLANE_DTYPES.get(type_name)
    if dtype is None:
        raise ProtocolError(f"oak: image frame of type {type_name} carries no grey image "
                            f"(expected one of {', '.join(GREY_PLANE_DTYPES)})")
    height, width = int(msg.getHeight()), int(msg.getWidth())
    if (height, width) != shape:
        raise ProtocolError(f"oak: image frame is {width} x {height}, expected {shape[1]} x {shape[0]} "
                            "(the depth's size)")
    row_bytes = width * np.dtype(dtype).itemsize
    stride = int(msg.getStride())
    data = np.asarray(msg.getData(), dtype=np.uint8).ravel()
    if stride < row_bytes or data.size < stride * height:
        raise ProtocolError(f"oak: {type_name} image buffer of {data.size} bytes is too short for "
                            f"{width} x {height} with a stride of {stride} bytes")
    # Rows of `stride` bytes, padding cut off, reinterpreted as pixels of the type's dtype.
    rows = data[:stride * height].reshape(height, stride)[:, :row_bytes]
    pixels = np.ascontiguousarray(rows).view(dtype)
    return pixels.astype(np.float32)


def check_same_capture(depth: Any, image: Any, match: Literal["sequence", "time"], max_dt_s: float) -> None:
    """Refuse a depth / image pair that does not belong to one capture.

    Args:
        depth: The depth ``ImgFrame``.
        image: The image ``ImgFrame``.
        match: ``"sequence"`` when both come from one sensor's frame (stereo rectified
            image, ToF amplitude): the sequence numbers must be equal; ``"time"`` when
            they come from two sensors (colour camera): the capture times must be
            within ``max_dt_s``.
        max_dt_s: Largest capture-time difference, s (``"time"`` only).

    Raises:
        FrameSyncError: If they belong to different captures.
    """
    if match == "sequence":
        seq_depth, seq_image = int(depth.getSequenceNum()), int(image.getSequenceNum())
        if seq_depth != seq_image:
            raise FrameSyncError(f"oak: depth frame {seq_depth} came with image frame {seq_image} "
                                 "(different captures)")
        return
    dt = abs(depth.getTimestamp().total_seconds() - image.getTimestamp().total_seconds())
    if dt > max_dt_s:
        raise FrameSyncError(f"oak: depth and image were captured {dt * 1e3:.1f} ms apart "
                             f"(more than {max_dt_s * 1e3:.1f} ms: different captures)")
