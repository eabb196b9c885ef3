"""Foxglove messages that make a recording viewable without cellcal.

``foxglove.CameraCalibration``, ``foxglove.RawImage`` (the distance image) and
``foxglove.PoseInFrame`` (each flange pose read back); replay never reads them.
"""

from __future__ import annotations

import base64
from typing import Any

import numpy as np

from cellcal.devices.pose import Pose
from cellcal.devices.types import Frame, Intrinsics

from .codec import seconds_to_ns

#: Frame ids used in the Foxglove messages.
CAMERA_FRAME_ID = "camera"
BASE_FRAME_ID = "base"


def stamp(seconds: float) -> dict[str, int]:
    """Foxglove ``Time`` of a time in seconds: whole seconds and nanoseconds (0 for invalid times)."""
    ns = seconds_to_ns(seconds)
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def camera_calibration(intr: Intrinsics, time_stamp: dict[str, int]) -> dict[str, Any]:
    """``foxglove.CameraCalibration`` of the depth stream (K, D, R = I, P = [K | 0]).

    Args:
        intr: Intrinsics (OpenCV conventions, pixels).
        time_stamp: Foxglove time, from :func:`stamp`.
    """
    # the rational model only when one of its extra coefficients is in use
    rational = any(getattr(intr, k) != 0.0 for k in ("k4", "k5", "k6"))
    d = [intr.k1, intr.k2, intr.p1, intr.p2, intr.k3] + ([intr.k4, intr.k5, intr.k6] if rational else [])
    return {"timestamp": time_stamp, "frame_id": CAMERA_FRAME_ID, "width": intr.width, "height": intr.height,
            "distortion_model": "rational_polynomial" if rational else "plumb_bob", "D": d,
            "K": intr.camera_matrix.ravel().tolist(), "R": np.eye(3).ravel().tolist(),
            "P": np.hstack([intr.camera_matrix, np.zeros((3, 1))]).ravel().tolist()}


def depth_image(frame: Frame) -> dict[str, Any]:
    """``foxglove.RawImage`` of the frame's distance image: ``32FC1``, metres, little-endian rows."""
    h, w = frame.shape
    data = np.ascontiguousarray(frame.distance, dtype="<f4").tobytes()
    return {"timestamp": stamp(frame.timestamp), "frame_id": CAMERA_FRAME_ID, "width": w, "height": h,
            "encoding": "32FC1", "step": 4 * w, "data": base64.b64encode(data).decode("ascii")}


def pose_in_frame(pose: Pose, seconds: float) -> dict[str, Any]:
    """``foxglove.PoseInFrame`` of a flange pose in the base frame (metres, quaternion x, y, z, w)."""
    x, y, z = (float(v) for v in pose.translation)
    qx, qy, qz, qw = (float(v) for v in pose.rotation.as_quat())
    return {"timestamp": stamp(seconds), "frame_id": BASE_FRAME_ID,
            "pose": {"position": {"x": x, "y": y, "z": z}, "orientation": {"x": qx, "y": qy, "z": qz, "w": qw}}}
