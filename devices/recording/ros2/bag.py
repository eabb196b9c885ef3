"""Write scenes to a ROS 2 bag: a rosbag2 directory (metadata.yaml + one MCAP file of CDR messages).

Written with ``rosbags`` (format version 9, the one ROS 2 Jazzy writes and reads), in a
temporary directory beside the destination that is renamed into place on close (ADR 0020).
"""

from __future__ import annotations

import contextlib
import errno
import shutil
import tempfile
from pathlib import Path
from types import TracebackType
from typing import Any, Self

from cellcal.devices.errors import CellcalError, MissingDependencyError, RecordingWriteError
from cellcal.devices.pose import Pose

from ..codec import seconds_to_ns
from ..scene import FLANGE_FRAME_ID, Scene
from .messages import Ros2Messages

#: rosbag2 metadata version written (ROS 2 Jazzy and later read it).
BAG_VERSION = 9
#: Topics and their message types.
TOPICS: dict[str, str] = {
    "/tf_static": "tf2_msgs/msg/TFMessage",
    "/tf": "tf2_msgs/msg/TFMessage",
    "/camera/camera_info": "sensor_msgs/msg/CameraInfo",
    "/camera/depth": "sensor_msgs/msg/Image",
    "/camera/points": "sensor_msgs/msg/PointCloud2",
    "/cellcal/plane": "shape_msgs/msg/Plane",
    "/cellcal/plane_marker": "visualization_msgs/msg/Marker",
}
#: History depth of each topic's offered QoS (tf2's static broadcaster keeps 1, its listener 100).
_DEPTH = {"/tf_static": 1, "/tf": 100}


def _import_rosbag2() -> Any:
    try:
        import rosbags.rosbag2 as rosbag2
    except ImportError:
        raise MissingDependencyError("rosbags (needed to write ROS 2 bags)", "ros2") from None
    return rosbag2


def _qos(topic: str) -> list[Any]:
    """The offered QoS of a topic: reliable, keep-last; /tf_static transient-local (late joiners get it)."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    durable = QosDurability.TRANSIENT_LOCAL if topic == "/tf_static" else QosDurability.VOLATILE
    zero = QosTime(0, 0)  # 0 s: the middleware's default (no deadline, infinite lifespan)
    return [Qos(QosHistory.KEEP_LAST, _DEPTH.get(topic, 10), QosReliability.RELIABLE, durable, zero, zero,
                QosLiveliness.AUTOMATIC, zero, False)]


class Ros2BagWriter:
    """Writes scenes to a new rosbag2 directory; use as a context manager.

    Per scene: ``/tf`` (base -> flange, when the arm's pose is known), ``/camera/camera_info``,
    ``/camera/depth`` (32FC1, metres), ``/camera/points`` (PointCloud2, inliers green,
    outliers red) and, with a fitted plane, ``/cellcal/plane`` and two ``/cellcal/plane_marker``
    markers (patch and normal). ``/tf_static`` carries flange -> camera (the mount) once,
    at the first scene's time. Every message is stamped with its frame's time, and the bag's
    log times are those stamps.

    Args:
        path: The bag directory to create; it must not exist, or be an empty directory.
        compress: zstd-compress the MCAP chunks (``ros2 bag`` reads either).
        keep_on_error: When leaving the ``with`` block on a :class:`CellcalError`, finish the
            bag with what was written instead of discarding it. An interrupted run
            (KeyboardInterrupt) always keeps its bag.

    Raises:
        MissingDependencyError: If ``rosbags`` (extra ``ros2``) is not installed.
        RecordingWriteError: If ``path`` is not empty or cannot be created.
    """

    def __init__(self, path: str | Path, *, compress: bool = True, keep_on_error: bool = False) -> None:
        rosbag2 = _import_rosbag2()
        self.path = Path(path)
        self.keep_on_error = keep_on_error
        if self.path.exists() and not (self.path.is_dir() and not any(self.path.iterdir())):
            raise RecordingWriteError(f"{self.path} exists; a ROS 2 bag is written to a new (or empty) directory",
                                      errno=errno.EEXIST)
        self.messages = Ros2Messages()
        self.message_counts: dict[str, int] = dict.fromkeys(TOPICS, 0)
        self._static_done = False
        #: Whether the bag was finished and moved to :attr:`path`.
        self.finished = False
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._tmp: Path | None = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.", suffix=".tmp",
                                                           dir=self.path.parent))
        except OSError as exc:
            raise RecordingWriteError(f"cannot write {self.path}: {exc.strerror or exc}", errno=exc.errno) from None
        self._writer = rosbag2.Writer(self._tmp / self.path.name, version=BAG_VERSION,
                                      storage_plugin=rosbag2.StoragePlugin.MCAP)
        if compress:
            self._writer.set_compression(rosbag2.CompressionMode.STORAGE, rosbag2.CompressionFormat.ZSTD)
        try:
            self._writer.open()
            store = self.messages.store
            self._connections = {topic: self._writer.add_connection(topic, msgtype, typestore=store,
                                                                    offered_qos_profiles=_qos(topic))
                                 for topic, msgtype in TOPICS.items()}
        except BaseException:
            self.abort()
            raise

    def write(self, topic: str, message: Any, seconds: float) -> None:
        """Serialise ``message`` to CDR and write it on ``topic`` at ``seconds`` (log time).

        Raises:
            RecordingWriteError: If the bag is closed or the write fails.
        """
        if self._tmp is None:
            raise RecordingWriteError(f"the ROS 2 bag {self.path} is closed; nothing more can be written")
        data = self.messages.store.serialize_cdr(message, TOPICS[topic])
        try:
            self._writer.write(self._connections[topic], seconds_to_ns(seconds), data)
        except OSError as exc:
            raise RecordingWriteError(f"cannot write {self.path}: {exc.strerror or exc}", errno=exc.errno) from None
        self.message_counts[topic] += 1

    def write_scene(self, scene: Scene) -> None:
        """Write every message of one scene (see the class)."""
        m, t, cam = self.messages, scene.timestamp, scene.camera_frame_id
        if not self._static_done and scene.flange_camera is not None:
            self.write_static([(FLANGE_FRAME_ID, cam, scene.flange_camera)], t)
        dynamic = m.scene_transforms(scene)
        if dynamic:
            self.write("/tf", m.tf(dynamic, t), t)
        self.write("/camera/camera_info", m.camera_info(scene.frame.intrinsics, t, cam), t)
        self.write("/camera/depth", m.depth_image(scene.frame, cam), t)
        self.write("/camera/points", m.point_cloud(scene), t)
        if scene.has_plane:
            self.write("/cellcal/plane", m.plane(scene), t)
            for marker in m.plane_markers(scene):
                self.write("/cellcal/plane_marker", marker, t)

    def write_static(self, transforms: list[tuple[str, str, Pose]], seconds: float) -> None:
        """Write the static transforms (one ``/tf_static`` message; later calls add none)."""
        if not self._static_done:
            self.write("/tf_static", self.messages.tf(transforms, seconds), seconds)
            self._static_done = True

    # ------------------------------------------------------------ finishing
    def close(self) -> Path:
        """Finish the bag (MCAP summary, metadata.yaml) and move it to :attr:`path`. Idempotent.

        Raises:
            RecordingWriteError: If finishing or moving fails (the temporary directory is removed).
        """
        tmp = self._tmp
        if tmp is None:
            return self.path
        try:
            self._writer.close()
            if self.path.is_dir():
                self.path.rmdir()  # empty (checked at the start); rename cannot replace it on every OS
            (tmp / self.path.name).rename(self.path)
        except OSError as exc:
            self.abort()
            raise RecordingWriteError(f"cannot write {self.path}: {exc.strerror or exc}", errno=exc.errno) from None
        self._tmp = None
        self.finished = True
        shutil.rmtree(tmp, ignore_errors=True)
        return self.path

    def abort(self) -> None:
        """Discard the bag: remove the temporary directory. Idempotent."""
        tmp, self._tmp = self._tmp, None
        if tmp is not None:
            with contextlib.suppress(Exception):
                self._writer.abort()
            shutil.rmtree(tmp, ignore_errors=True)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        keep = isinstance(exc, KeyboardInterrupt) or (self.keep_on_error and isinstance(exc, CellcalError))
        if exc is None or keep:  # an interrupted run keeps what it recorded
            self.close()
        else:
            self.abort()
