"""The ROS 2 bag writer (rosbags), read back with another library (mcap + mcap-ros2-support) and checked
against the scene it was written from: stamps, frame ids, poses, intrinsics, depth, points, plane."""

from __future__ import annotations

import dataclasses
import errno
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from tof_frames import ToFSetup, make_frame

from cellcal.devices.errors import CellcalError, RecordingWriteError
from cellcal.devices.pose import Pose
from cellcal.devices.recording.scene import Scene, plane_patch
from cellcal.devices.types import Intrinsics

pytest.importorskip("rosbags")
mcap_ros2_decoder = pytest.importorskip("mcap_ros2.decoder")
from mcap.reader import make_reader  # noqa: E402
from ruamel.yaml import YAML  # noqa: E402  (installed with rosbags)

from cellcal.devices.recording.ros2 import BAG_VERSION, TOPICS, Ros2BagWriter  # noqa: E402

T0 = 1_790_000_000.123456789  # seconds since the epoch
BASE_FLANGE = Pose.from_xyz_rpy([0.31, -0.12, 0.47], [3.05, 0.12, -0.4])
MOUNT = Pose.from_xyz_rpy([0.0, 0.04, 0.06], [0.0, 0.0, np.pi / 2])


def _scenes(n: int = 2) -> list[Scene]:
    """``n`` frames of a tilted plane, a distorted lens, a random inlier mask with about 10 % outliers."""
    setup = ToFSetup()
    frame = make_frame(setup, 3)
    intr = dataclasses.replace(frame.intrinsics, k1=-0.12, k2=0.03, p1=1e-4, p2=-2e-4, k3=0.004)
    rng = np.random.default_rng(7)
    out = []
    for i in range(n):
        f = dataclasses.replace(make_frame(setup, 10 + i), intrinsics=intr, timestamp=T0 + 0.5 * i)
        # the plane through the frame's valid points (least squares: the smallest singular vector)
        pts = f.xyz[f.valid].astype(np.float64)
        centroid = pts.mean(axis=0)
        normal = np.linalg.svd(pts - centroid, full_matrices=False)[2][-1]
        normal = -normal if normal[2] > 0 else normal  # toward the camera
        mask = f.valid & (rng.random(f.shape) > 0.1)
        arm = BASE_FLANGE @ Pose.from_xyz_rpy([0.01 * i, 0, 0], [0, 0, 0.05 * i])
        out.append(Scene(f, base_flange=arm, flange_camera=MOUNT, plane_normal=normal,
                         plane_offset_m=float(-normal @ centroid), inlier_mask=mask))
    return out


def _write(path: Path, scenes: list[Scene]) -> dict[str, int]:
    with Ros2BagWriter(path) as bag:
        for scene in scenes:
            bag.write_scene(scene)
    return bag.message_counts


def _read(path: Path) -> tuple[Any, dict[str, list[tuple[Any, Any, Any]]]]:
    """The MCAP file's header and summary, and per topic (schema, MCAP message, decoded ROS message)."""
    mcap_files = sorted(path.glob("*.mcap"))
    assert len(mcap_files) == 1
    out: dict[str, list[tuple[Any, Any, Any]]] = {}
    with mcap_files[0].open("rb") as fh:
        reader = make_reader(fh, decoder_factories=[mcap_ros2_decoder.DecoderFactory()], validate_crcs=True)
        info = (reader.get_header(), reader.get_summary())
        for schema, channel, message, decoded in reader.iter_decoded_messages(log_time_order=True):
            out.setdefault(channel.topic, []).append((schema, message, decoded))
    return info, out


def _ns(seconds: float) -> int:
    return round(seconds * 1e9)


def _stamp_ns(header: Any) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


@pytest.fixture(scope="module")
def bag(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[Scene], dict[str, int]]:
    path = tmp_path_factory.mktemp("ros2") / "session_bag"
    scenes = _scenes()
    return path, scenes, _write(path, scenes)


def test_metadata_yaml_is_a_rosbag2_version_9_description_of_the_mcap_file(bag: Any) -> None:
    path, _, counts = bag
    (header, summary), _ = _read(path)
    meta = YAML(typ="safe").load((path / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["version"] == BAG_VERSION == 9 and meta["storage_identifier"] == "mcap"
    assert meta["relative_file_paths"] == [f"{path.name}.mcap"] and (path / f"{path.name}.mcap").is_file()
    assert meta["starting_time"]["nanoseconds_since_epoch"] == _ns(T0)
    assert meta["duration"]["nanoseconds"] == _ns(T0 + 0.5) - _ns(T0)
    assert meta["message_count"] == sum(counts.values()) == summary.statistics.message_count
    topics = {t["topic_metadata"]["name"]: t for t in meta["topics_with_message_count"]}
    assert set(topics) == set(TOPICS)
    mcap_counts = {summary.channels[c].topic: n for c, n in summary.statistics.channel_message_counts.items()}
    for name, entry in topics.items():
        tm = entry["topic_metadata"]
        assert tm["type"] == TOPICS[name] and tm["serialization_format"] == "cdr"
        assert tm["type_description_hash"].startswith("RIHS01_") and len(tm["type_description_hash"]) == 71
        assert entry["message_count"] == counts[name] == mcap_counts.get(name, 0)
        (qos,) = tm["offered_qos_profiles"]
        assert qos["reliability"] == "reliable"
        assert qos["durability"] == ("transient_local" if name == "/tf_static" else "volatile")
    assert counts == {"/tf_static": 1, "/tf": 2, "/camera/camera_info": 2, "/camera/depth": 2, "/camera/points": 2,
                      "/cellcal/plane": 2, "/cellcal/plane_marker": 4}
    assert header.profile == "ros2"
    for channel in summary.channels.values():
        schema = summary.schemas[channel.schema_id]
        assert channel.message_encoding == "cdr" and schema.encoding == "ros2msg"
        assert schema.name == TOPICS[channel.topic]


def test_every_stamp_frame_id_and_log_time_is_the_frames(bag: Any) -> None:
    path, scenes, _ = bag
    _, msgs = _read(path)
    times = [_ns(s.timestamp) for s in scenes]
    for topic in ("/camera/camera_info", "/camera/depth", "/camera/points"):
        assert [_stamp_ns(d.header) for _, _, d in msgs[topic]] == times, topic
        assert [m.log_time for _, m, _ in msgs[topic]] == times, topic
        assert {d.header.frame_id for _, _, d in msgs[topic]} == {"camera"}, topic
    assert [_stamp_ns(d.header) for _, _, d in msgs["/cellcal/plane_marker"]] == [t for t in times for _ in (0, 1)]
    assert [m.log_time for _, m, _ in msgs["/cellcal/plane"]] == times


def test_transforms_are_the_arm_pose_and_the_mount(bag: Any) -> None:
    path, scenes, _ = bag
    _, msgs = _read(path)
    (static,) = msgs["/tf_static"]
    (mount,) = static[2].transforms
    assert (mount.header.frame_id, mount.child_frame_id, _stamp_ns(mount.header)) == ("flange", "camera", _ns(T0))
    t, q = mount.transform.translation, mount.transform.rotation
    assert [t.x, t.y, t.z] == MOUNT.translation.tolist()
    assert [q.x, q.y, q.z, q.w] == MOUNT.rotation.as_quat().tolist()
    for scene, (_, _, tf) in zip(scenes, msgs["/tf"], strict=True):
        (arm,) = tf.transforms
        assert (arm.header.frame_id, arm.child_frame_id, _stamp_ns(arm.header)) == ("base", "flange",
                                                                                      _ns(scene.timestamp))
        t, q = arm.transform.translation, arm.transform.rotation
        assert scene.base_flange is not None
        assert [t.x, t.y, t.z] == scene.base_flange.translation.tolist()
        assert [q.x, q.y, q.z, q.w] == scene.base_flange.rotation.as_quat().tolist()


def test_camera_info_is_the_lens_model_in_plumb_bob_form(bag: Any) -> None:
    path, scenes, _ = bag
    _, msgs = _read(path)
    intr: Intrinsics = scenes[0].frame.intrinsics
    info = msgs["/camera/camera_info"][0][2]
    assert (info.width, info.height, info.distortion_model) == (intr.width, intr.height, "plumb_bob")
    assert list(info.d) == [intr.k1, intr.k2, intr.p1, intr.p2, intr.k3]
    assert list(info.k) == [intr.fx, 0.0, intr.cx, 0.0, intr.fy, intr.cy, 0.0, 0.0, 1.0]
    assert list(info.r) == np.eye(3).ravel().tolist()
    assert list(info.p) == [intr.fx, 0.0, intr.cx, 0.0, 0.0, intr.fy, intr.cy, 0.0, 0.0, 0.0, 1.0, 0.0]


def test_depth_image_is_the_distance_in_metres_bit_for_bit(bag: Any) -> None:
    path, scenes, _ = bag
    _, msgs = _read(path)
    for scene, (_, _, img) in zip(scenes, msgs["/camera/depth"], strict=True):
        h, w = scene.frame.shape
        assert (img.encoding, img.height, img.width, img.step, img.is_bigendian) == ("32FC1", h, w, 4 * w, 0)
        depth = np.frombuffer(bytes(img.data), dtype="<f4").reshape(h, w)
        assert depth.tobytes() == scene.frame.distance.astype("<f4").tobytes()
        assert np.isnan(depth).sum() == np.isnan(scene.frame.distance).sum()
        assert 0.3 < float(np.nanmedian(depth)) < 3.0  # metres, not millimetres


def test_point_cloud_holds_the_valid_points_coloured_by_the_inlier_mask(bag: Any) -> None:
    path, scenes, _ = bag
    _, msgs = _read(path)
    for scene, (_, _, cloud) in zip(scenes, msgs["/camera/points"], strict=True):
        keep = scene.frame.valid & np.all(np.isfinite(scene.frame.xyz), axis=-1)
        names = [(f.name, f.offset, f.datatype, f.count) for f in cloud.fields]
        assert names == [("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1), ("rgb", 12, 7, 1)]
        assert (cloud.height, cloud.width, cloud.point_step) == (1, int(keep.sum()), 16)
        assert cloud.row_step == 16 * cloud.width and not cloud.is_bigendian
        rec = np.frombuffer(bytes(cloud.data), dtype=[("xyz", "<f4", (3,)), ("bgra", "u1", (4,))])
        assert rec["xyz"].tobytes() == scene.frame.xyz[keep].astype("<f4").tobytes()
        assert scene.inlier_mask is not None
        inlier = scene.inlier_mask[keep]
        assert 0.05 < 1 - inlier.mean() < 0.15  # the mask really has outliers
        # green (B, G, R = 51, 204, 26) for inliers, red (26, 38, 230) for outliers
        assert np.all(rec["bgra"][inlier] == [51, 204, 26, 255])
        assert np.all(rec["bgra"][~inlier] == [26, 38, 230, 255])


def test_plane_and_markers_are_the_fitted_plane(bag: Any) -> None:
    path, scenes, _ = bag
    _, msgs = _read(path)
    markers = [d for _, _, d in msgs["/cellcal/plane_marker"]]
    for i, (scene, (_, _, plane)) in enumerate(zip(scenes, msgs["/cellcal/plane"], strict=True)):
        assert scene.plane_normal is not None and scene.plane_offset_m is not None
        assert list(plane.coef) == [*scene.plane_normal.tolist(), scene.plane_offset_m]
        cube, arrow = markers[2 * i], markers[2 * i + 1]
        assert (cube.type, cube.id, arrow.type, arrow.id) == (1, 0, 0, 1)
        patch, size_x, size_y = plane_patch(scene)
        for marker in (cube, arrow):
            p = marker.pose.position
            centre = np.array([p.x, p.y, p.z])
            assert abs(scene.plane_normal @ centre + scene.plane_offset_m) < 1e-9  # on the plane
            assert np.allclose(centre, patch.translation, atol=1e-12)
        from scipy.spatial.transform import Rotation

        def axis(m: Any, k: int) -> np.ndarray:
            o = m.pose.orientation
            return Rotation.from_quat([o.x, o.y, o.z, o.w]).as_matrix()[:, k]

        assert axis(cube, 2) @ scene.plane_normal > 1 - 1e-12  # the cube's z is the normal
        assert axis(arrow, 0) @ scene.plane_normal > 1 - 1e-12  # the arrow points along it
        assert (cube.scale.x, cube.scale.y) == (size_x, size_y) and 0.2 < size_x < 5 and 0.2 < size_y < 5


def test_an_existing_bag_directory_is_refused_and_left_alone(tmp_path: Path) -> None:
    path = tmp_path / "bag"
    path.mkdir()
    (path / "keep.txt").write_text("mine")
    with pytest.raises(RecordingWriteError, match="exists") as info:
        Ros2BagWriter(path)
    assert info.value.errno == errno.EEXIST and info.value.bad_path
    assert sorted(p.name for p in path.iterdir()) == ["keep.txt"] and sorted(tmp_path.iterdir()) == [path]


def test_an_empty_directory_is_used_and_a_failed_run_leaves_nothing(tmp_path: Path) -> None:
    empty = tmp_path / "empty"
    empty.mkdir()
    counts = _write(empty, _scenes(1))
    assert counts["/camera/points"] == 1 and (empty / "metadata.yaml").is_file()
    failed = tmp_path / "failed"
    with pytest.raises(CellcalError), Ros2BagWriter(failed) as bag:
        bag.write_scene(_scenes(1)[0])
        raise CellcalError("device fault")
    assert not failed.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["empty"]


def test_an_interrupted_run_keeps_a_readable_bag(tmp_path: Path) -> None:
    path = tmp_path / "bag"
    scenes = _scenes(2)
    with pytest.raises(KeyboardInterrupt), Ros2BagWriter(path) as bag:
        bag.write_scene(scenes[0])
        raise KeyboardInterrupt
    assert bag.finished
    _, msgs = _read(path)
    assert len(msgs["/camera/depth"]) == 1 and len(msgs["/tf_static"]) == 1
