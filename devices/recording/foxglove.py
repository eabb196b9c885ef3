"""Foxglove messages that make a recording viewable without cellcal.

``foxglove.CameraCalibration``, ``foxglove.RawImage`` (the distance image) and
``foxglove.PoseInFrame`` (each flange pose read back); replay never reads them. The
scene of a frame (:class:`~.scene.Scene`) becomes ``foxglove.PointCloud``,
``foxglove.SceneUpdate`` (plane and normal), ``foxglove.FrameTransforms`` and a
``cellcal.Drift`` message — the same JSON in recordings and in the live view (ADR 0020).
"""

from __future__ import annotations

import base64
from typing import Any

import numpy as np

from cellcal.devices.pose import Pose
from cellcal.devices.types import Frame, Intrinsics

from .codec import seconds_to_ns
from .scene import (
    BASE_FRAME_ID,
    CAMERA_FRAME_ID,
    FLANGE_FRAME_ID,
    NORMAL_ARROW_FRACTION,
    NORMAL_ARROW_SHAFT_RATIO,
    NORMAL_RGBA,
    PLANE_RGBA,
    PLANE_THICKNESS_M,
    POINT_OFFSETS,
    POINT_STRIDE,
    Scene,
    normal_arrow,
    packed_points,
    plane_patch,
)
from .schema import TOPIC_DRIFT, TOPIC_PLANE, TOPIC_POINTS, TOPIC_TF, TOPIC_TRACK

#: ``foxglove.NumericType`` values used in point-cloud fields.
UINT8, FLOAT32 = 1, 7


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


def pose_json(pose: Pose) -> dict[str, Any]:
    """``foxglove.Pose`` of a pose (metres, quaternion x, y, z, w)."""
    x, y, z = (float(v) for v in pose.translation)
    qx, qy, qz, qw = (float(v) for v in pose.rotation.as_quat())
    return {"position": {"x": x, "y": y, "z": z}, "orientation": {"x": qx, "y": qy, "z": qz, "w": qw}}


def pose_in_frame(pose: Pose, seconds: float) -> dict[str, Any]:
    """``foxglove.PoseInFrame`` of a flange pose in the base frame (metres, quaternion x, y, z, w)."""
    return {"timestamp": stamp(seconds), "frame_id": BASE_FRAME_ID, "pose": pose_json(pose)}


def _rgba(rgba: tuple[float, float, float, float]) -> dict[str, float]:
    return dict(zip("rgba", rgba, strict=True))


def point_cloud(scene: Scene) -> dict[str, Any]:
    """``foxglove.PointCloud`` of the valid points, camera frame; inliers green, outliers red.

    Fields ``x, y, z`` (float32, m) and ``blue, green, red, alpha`` (uint8): pick the
    "RGBA (separate fields)" colour mode in Foxglove's 3D panel.
    """
    data, _ = packed_points(scene)
    fields = [{"name": n, "offset": POINT_OFFSETS[n], "type": FLOAT32} for n in ("x", "y", "z")]
    fields += [{"name": n, "offset": POINT_OFFSETS["bgra"] + i, "type": UINT8}
               for i, n in enumerate(("blue", "green", "red", "alpha"))]
    return {"timestamp": stamp(scene.timestamp), "frame_id": scene.camera_frame_id,
            "pose": pose_json(Pose.identity()), "point_stride": POINT_STRIDE, "fields": fields,
            "data": base64.b64encode(data).decode("ascii")}


def scene_update(scene: Scene) -> dict[str, Any]:
    """``foxglove.SceneUpdate``: the fitted plane as a thin cube over the inliers and its normal as an arrow.

    Without a plane, an update that deletes the previous one.
    """
    time_stamp = stamp(scene.timestamp)
    if not scene.has_plane:
        return {"deletions": [{"timestamp": time_stamp, "type": 1, "id": ""}], "entities": []}
    patch, size_x, size_y = plane_patch(scene)
    length = NORMAL_ARROW_FRACTION * max(size_x, size_y)
    entity = {"timestamp": time_stamp, "frame_id": scene.camera_frame_id, "id": "plane",
              "lifetime": {"sec": 0, "nsec": 0}, "frame_locked": True, "metadata": [],
              "cubes": [{"pose": pose_json(patch), "size": {"x": size_x, "y": size_y, "z": PLANE_THICKNESS_M},
                         "color": _rgba(PLANE_RGBA)}],
              "arrows": [{"pose": pose_json(normal_arrow(scene, patch)), "shaft_length": 0.8 * length,
                          "shaft_diameter": length / NORMAL_ARROW_SHAFT_RATIO, "head_length": 0.2 * length,
                          "head_diameter": length / 8, "color": _rgba(NORMAL_RGBA)}]}
    return {"deletions": [], "entities": [entity]}


def frame_transforms(scene: Scene) -> dict[str, Any]:
    """``foxglove.FrameTransforms``: base -> flange (the arm's pose) and flange -> camera (the mount), when known."""
    pairs = [(BASE_FRAME_ID, FLANGE_FRAME_ID, scene.base_flange), (FLANGE_FRAME_ID, scene.camera_frame_id,
                                                                    scene.flange_camera)]
    transforms = []
    for parent, child, pose in pairs:
        if pose is None:
            continue
        p = pose_json(pose)
        transforms.append({"timestamp": stamp(scene.timestamp), "parent_frame_id": parent, "child_frame_id": child,
                           "translation": p["position"], "rotation": p["orientation"]})
    return {"transforms": transforms}


def drift(scene: Scene) -> dict[str, Any]:
    """``cellcal.Drift``: the drift values of a monitored camera (SI units), for Foxglove's Plot panel."""
    return {"timestamp": stamp(scene.timestamp), "frame_id": scene.camera_frame_id, **dict(scene.drift or {})}


def scene_messages(scene: Scene) -> dict[str, dict[str, Any]]:
    """Every Foxglove message of a scene by topic (:data:`~.schema.SCENE_CHANNELS`, plus drift when set).

    ``/tf`` only when a transform is known (a monitored camera has none: its scene is drawn in its own frame).
    """
    out = {TOPIC_TF: frame_transforms(scene), TOPIC_POINTS: point_cloud(scene), TOPIC_PLANE: scene_update(scene)}
    if not out[TOPIC_TF]["transforms"]:
        del out[TOPIC_TF]
    if scene.drift is not None:
        out[TOPIC_DRIFT] = drift(scene)
    if scene.track is not None:
        out[TOPIC_TRACK] = {"timestamp": stamp(scene.timestamp), "frame_id": scene.camera_frame_id, **scene.track}
    return out
