"""ROS 2 messages of a :class:`~cellcal.devices.recording.scene.Scene`, built with ``rosbags`` types (ADR 0020).

Types are those of the ROS 2 Jazzy type store (``rosbags.typesys``): ``tf2_msgs/msg/TFMessage``,
``sensor_msgs/msg/{CameraInfo,Image,PointCloud2}``, ``shape_msgs/msg/Plane`` and
``visualization_msgs/msg/Marker``; they are serialised to CDR by the same type store.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from cellcal.devices.errors import MissingDependencyError
from cellcal.devices.pose import Pose
from cellcal.devices.types import Frame, Intrinsics

from ..codec import seconds_to_ns
from ..scene import (
    BASE_FRAME_ID,
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

#: Name of the ``rosbags`` type store the messages use (ROS 2 Jazzy).
TYPE_STORE = "ROS2_JAZZY"
#: ``sensor_msgs/msg/PointField`` data type FLOAT32.
FLOAT32 = 7
#: Marker ids of the plane patch and its normal arrow.
PLANE_MARKER_ID, NORMAL_MARKER_ID = 0, 1


def typestore() -> Any:
    """The ``rosbags`` type store of ROS 2 Jazzy.

    Raises:
        MissingDependencyError: If ``rosbags`` (extra ``ros2``) is not installed.
    """
    try:
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise MissingDependencyError("rosbags (needed to write ROS 2 bags)", "ros2") from None
    return get_typestore(getattr(Stores, TYPE_STORE))


class Ros2Messages:
    """Builds the ROS 2 messages of scenes with one type store.

    Args:
        store: A ``rosbags`` type store (default: :func:`typestore`).
    """

    def __init__(self, store: Any | None = None) -> None:
        self.store = store if store is not None else typestore()
        self.t = self.store.types

    # ------------------------------------------------------------ building blocks
    def header(self, seconds: float, frame_id: str) -> Any:
        """``std_msgs/Header`` at a time in seconds."""
        ns = seconds_to_ns(seconds)
        stamp = self.t["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
        return self.t["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)

    def geometry_pose(self, pose: Pose) -> Any:
        """``geometry_msgs/Pose`` of a pose (metres, quaternion x, y, z, w)."""
        x, y, z = (float(v) for v in pose.translation)
        qx, qy, qz, qw = (float(v) for v in pose.rotation.as_quat())
        return self.t["geometry_msgs/msg/Pose"](position=self.t["geometry_msgs/msg/Point"](x=x, y=y, z=z),
                                                orientation=self.quaternion(qx, qy, qz, qw))

    def quaternion(self, x: float, y: float, z: float, w: float) -> Any:
        """``geometry_msgs/Quaternion``."""
        return self.t["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w)

    def colour(self, rgba: tuple[float, float, float, float]) -> Any:
        """``std_msgs/ColorRGBA`` (0..1)."""
        r, g, b, a = rgba
        return self.t["std_msgs/msg/ColorRGBA"](r=r, g=g, b=b, a=a)

    # ------------------------------------------------------------ messages
    def tf(self, transforms: list[tuple[str, str, Pose]], seconds: float) -> Any:
        """``tf2_msgs/TFMessage`` of ``(parent, child, T_parent_child)`` transforms at one time."""
        items = []
        for parent, child, pose in transforms:
            x, y, z = (float(v) for v in pose.translation)
            qx, qy, qz, qw = (float(v) for v in pose.rotation.as_quat())
            tr = self.t["geometry_msgs/msg/Transform"](translation=self.t["geometry_msgs/msg/Vector3"](x=x, y=y, z=z),
                                                      rotation=self.quaternion(qx, qy, qz, qw))
            items.append(self.t["geometry_msgs/msg/TransformStamped"](header=self.header(seconds, parent),
                                                                      child_frame_id=child, transform=tr))
        return self.t["tf2_msgs/msg/TFMessage"](transforms=items)

    def camera_info(self, intr: Intrinsics, seconds: float, frame_id: str) -> Any:
        """``sensor_msgs/CameraInfo``: plumb_bob (k1, k2, p1, p2, k3), rational_polynomial when k4..k6 are used."""
        rational = any(getattr(intr, k) != 0.0 for k in ("k4", "k5", "k6"))
        d = [intr.k1, intr.k2, intr.p1, intr.p2, intr.k3] + ([intr.k4, intr.k5, intr.k6] if rational else [])
        k = intr.camera_matrix.astype(np.float64)
        # P = [K | 0]: a monocular camera, no rectification
        p = np.hstack([k, np.zeros((3, 1))])
        roi = self.t["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        return self.t["sensor_msgs/msg/CameraInfo"](
            header=self.header(seconds, frame_id), height=intr.height, width=intr.width,
            distortion_model="rational_polynomial" if rational else "plumb_bob",
            d=np.asarray(d, dtype=np.float64), k=k.ravel(), r=np.eye(3).ravel(), p=p.ravel(),
            binning_x=0, binning_y=0, roi=roi)

    def depth_image(self, frame: Frame, frame_id: str) -> Any:
        """``sensor_msgs/Image`` of the distance image: ``32FC1``, metres, little-endian, NaN where invalid."""
        h, w = frame.shape
        data = np.ascontiguousarray(frame.distance, dtype="<f4").view(np.uint8).ravel()
        return self.t["sensor_msgs/msg/Image"](header=self.header(frame.timestamp, frame_id), height=h, width=w,
                                               encoding="32FC1", is_bigendian=0, step=4 * w, data=data)

    def point_cloud(self, scene: Scene) -> Any:
        """``sensor_msgs/PointCloud2`` of the valid points: x, y, z (float32, m) and packed ``rgb``.

        ``rgb`` colours inliers green and outliers red (the PCL/RViz packing: B, G, R, A bytes).
        """
        data, n = packed_points(scene)
        field = self.t["sensor_msgs/msg/PointField"]
        offsets = (("x", POINT_OFFSETS["x"]), ("y", POINT_OFFSETS["y"]), ("z", POINT_OFFSETS["z"]),
                   ("rgb", POINT_OFFSETS["bgra"]))
        fields = [field(name=name, offset=off, datatype=FLOAT32, count=1) for name, off in offsets]
        return self.t["sensor_msgs/msg/PointCloud2"](
            header=self.header(scene.timestamp, scene.camera_frame_id), height=1, width=n, fields=fields,
            is_bigendian=False, point_step=POINT_STRIDE, row_step=POINT_STRIDE * n,
            data=np.frombuffer(data, dtype=np.uint8), is_dense=True)

    def plane(self, scene: Scene) -> Any:
        """``shape_msgs/Plane`` ``[a, b, c, d]`` with ``a x + b y + c z + d = 0`` in the camera frame (m)."""
        assert scene.plane_normal is not None and scene.plane_offset_m is not None
        n = np.asarray(scene.plane_normal, dtype=np.float64)
        return self.t["shape_msgs/msg/Plane"](coef=np.array([*n, float(scene.plane_offset_m)], dtype=np.float64))

    def plane_markers(self, scene: Scene) -> list[Any]:
        """Two ``visualization_msgs/Marker``: the plane as a thin CUBE over the inliers, its normal as an ARROW."""
        patch, size_x, size_y = plane_patch(scene)
        marker, vec = self.t["visualization_msgs/msg/Marker"], self.t["geometry_msgs/msg/Vector3"]
        arrow_len = NORMAL_ARROW_FRACTION * max(size_x, size_y)
        common = {"header": self.header(scene.timestamp, scene.camera_frame_id), "ns": "cellcal/plane",
                  "action": 0, "lifetime": self.t["builtin_interfaces/msg/Duration"](sec=0, nanosec=0),
                  "frame_locked": False, "points": [], "colors": [], "texture_resource": "",
                  "texture": self.t["sensor_msgs/msg/CompressedImage"](
                      header=self.header(0.0, ""), format="", data=np.zeros(0, dtype=np.uint8)),
                  "uv_coordinates": [], "text": "", "mesh_resource": "",
                  "mesh_file": self.t["visualization_msgs/msg/MeshFile"](filename="", data=np.zeros(0, dtype=np.uint8)),
                  "mesh_use_embedded_materials": False}
        cube = marker(**common, id=PLANE_MARKER_ID, type=1, pose=self.geometry_pose(patch),
                      scale=vec(x=size_x, y=size_y, z=PLANE_THICKNESS_M), color=self.colour(PLANE_RGBA))
        # ARROW with a pose: scale.x is its length, y and z the shaft's width and height
        arrow = marker(**common, id=NORMAL_MARKER_ID, type=0, pose=self.geometry_pose(normal_arrow(scene, patch)),
                       scale=vec(x=arrow_len, y=arrow_len / NORMAL_ARROW_SHAFT_RATIO,
                                 z=arrow_len / NORMAL_ARROW_SHAFT_RATIO), color=self.colour(NORMAL_RGBA))
        return [cube, arrow]

    def scene_transforms(self, scene: Scene) -> list[tuple[str, str, Pose]]:
        """The dynamic transform of a scene: base -> flange, when the arm's pose is known."""
        return [] if scene.base_flange is None else [(BASE_FRAME_ID, FLANGE_FRAME_ID, scene.base_flange)]
