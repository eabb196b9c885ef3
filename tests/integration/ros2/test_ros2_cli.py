"""``cellcal record --format ros2`` on the sim cell and ``cellcal export --ros2``, read back independently.

The bag is written with rosbags and read here with mcap + mcap-ros2-support; every value
is checked against the run's own result.json (arm poses, mount, plane, intrinsics) and
against a cellcal MCAP recording of the same (deterministic) sim session (depth values).
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from defusedxml import ElementTree

from cellcal.core.cli import main
from cellcal.devices.pose import Pose
from cellcal.devices.recording import decode_frame, read_recording

pytest.importorskip("rosbags")
decoder = pytest.importorskip("mcap_ros2.decoder")
from mcap.reader import make_reader  # noqa: E402

N_POSES = 3


def _messages(bag: Path) -> dict[str, list[tuple[int, Any]]]:
    """Per topic: (log time ns, decoded message), in log-time order."""
    (mcap_file,) = bag.glob("*.mcap")
    out: dict[str, list[tuple[int, Any]]] = {}
    with mcap_file.open("rb") as fh:
        reader = make_reader(fh, decoder_factories=[decoder.DecoderFactory()], validate_crcs=True)
        for _, channel, message, decoded in reader.iter_decoded_messages(log_time_order=True):
            out.setdefault(channel.topic, []).append((message.log_time, decoded))
    return out


def _pose(transform: Any) -> Pose:
    """The pose of a ``geometry_msgs/TransformStamped``."""
    from scipy.spatial.transform import Rotation

    t, q = transform.transform.translation, transform.transform.rotation
    return Pose(Rotation.from_quat([q.x, q.y, q.z, q.w]), np.array([t.x, t.y, t.z]))


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, Any], Path]:
    """One ``record --format ros2`` run (bag, its result.json) and one ``record`` run to MCAP."""
    tmp = tmp_path_factory.mktemp("ros2")
    assert main(["record", "--format", "ros2", "--out", str(tmp / "bag"), "--result", str(tmp / "res"),
                 "--quiet"]) == 0
    assert main(["record", "--out", str(tmp / "session.mcap"), "--quiet"]) == 0
    return tmp / "bag", json.loads((tmp / "res" / "result.json").read_text()), tmp / "session.mcap"


def test_bag_holds_every_pose_with_the_results_poses_mount_and_plane(session: Any) -> None:
    bag, result, _ = session
    msgs = _messages(bag)
    assert {t: len(m) for t, m in msgs.items()} == {
        "/tf_static": 1, "/tf": N_POSES, "/camera/camera_info": N_POSES, "/camera/depth": N_POSES,
        "/camera/points": N_POSES, "/cellcal/plane": N_POSES, "/cellcal/plane_marker": 2 * N_POSES}
    (mount_tf,) = msgs["/tf_static"][0][1].transforms
    assert (mount_tf.header.frame_id, mount_tf.child_frame_id) == ("flange", "camera")
    assert _pose(mount_tf).is_close(Pose.from_dict(result["mount"]), atol_m=1e-15, atol_rad=1e-12)
    for i, pose in enumerate(result["poses"]):
        (arm,) = msgs["/tf"][i][1].transforms
        assert (arm.header.frame_id, arm.child_frame_id) == ("base", "flange")
        reported = pose["reported_flange_pose"]
        t = arm.transform.translation
        assert [t.x, t.y, t.z] == reported["translation_m"]
        assert _pose(arm).is_close(Pose.from_dict(reported), atol_m=1e-15, atol_rad=1e-12)
        plane = pose["full_frame"]["plane_cam"]
        assert list(msgs["/cellcal/plane"][i][1].coef) == [*plane["normal"], plane["offset_m"]]
        info = msgs["/camera/camera_info"][i][1]
        intr = pose["camera_intrinsics"]
        assert (info.width, info.height, info.distortion_model) == (intr["width"], intr["height"], "plumb_bob")
        assert list(info.k) == [intr["fx"], 0.0, intr["cx"], 0.0, intr["fy"], intr["cy"], 0.0, 0.0, 1.0]
        assert list(info.d) == [intr["k1"], intr["k2"], intr["p1"], intr["p2"], intr["k3"]]
        # the point cloud's green points are the fit's inliers
        cloud = msgs["/camera/points"][i][1]
        colours = np.frombuffer(bytes(cloud.data), dtype="u1").reshape(-1, 16)[:, 12:15]
        green = int(np.count_nonzero(colours[:, 1] == 204))
        assert green == pose["full_frame"]["n_inliers"] and cloud.width == pose["full_frame"]["n_points"]
    # every message of a pose carries the same stamp, also its log time, rising from pose to pose
    stamps = [m[0] for m in msgs["/camera/depth"]]
    assert stamps == sorted(stamps) and len(set(stamps)) == N_POSES
    for topic in ("/tf", "/camera/camera_info", "/camera/points", "/cellcal/plane"):
        assert [m[0] for m in msgs[topic]] == stamps, topic


def test_bag_depth_is_the_sim_cameras_distance_image(session: Any) -> None:
    bag, _, recording = session
    captures = read_recording(recording).captures
    depth = _messages(bag)["/camera/depth"]
    assert len(captures) == len(depth) == N_POSES
    for capture, (_, img) in zip(captures, depth, strict=True):
        frame = decode_frame(capture["frame"])
        assert (img.encoding, img.width, img.height) == ("32FC1", frame.shape[1], frame.shape[0])
        assert bytes(img.data) == frame.distance.astype("<f4").tobytes()


def test_mcap_recording_gains_the_scene_channels_and_still_replays(session: Any, tmp_path: Path,
                                                                   capsys: pytest.CaptureFixture[str]) -> None:
    _, _, recording = session
    with recording.open("rb") as fh:
        reader = make_reader(fh, validate_crcs=True)
        summary = reader.get_summary()
        assert summary is not None
        schemas = {ch.topic: summary.schemas[ch.schema_id].name for ch in summary.channels.values()}
        assert {k: schemas[k] for k in ("/camera/points", "/cellcal/plane", "/tf")} == {
            "/camera/points": "foxglove.PointCloud", "/cellcal/plane": "foxglove.SceneUpdate",
            "/tf": "foxglove.FrameTransforms"}
        tf = [json.loads(m.data) for _, _, m in reader.iter_messages(topics=["/tf"])]
    frames = [(t["parent_frame_id"], t["child_frame_id"]) for t in tf[0]["transforms"]]
    assert len(tf) == N_POSES and frames == [("base", "flange"), ("flange", "camera")]
    assert main(["calibrate", "--replay", str(recording), "--out", str(tmp_path / "replay"), "--quiet"]) == 0
    assert "identical to the recorded result" in capsys.readouterr().out


def _launch_values(text: str) -> dict[str, float]:
    return {k: float(v) for k, v in re.findall(r'"--(x|y|z|qx|qy|qz|qw)", "([^"]+)"', text)}


def _urdf_origin(text: str) -> Pose:
    xml = text[text.index("<joint"):]
    joint = ElementTree.fromstring(xml)
    assert joint.get("type") == "fixed"
    assert (joint.find("parent").get("link"), joint.find("child").get("link")) == ("flange", "camera")
    origin = joint.find("origin")
    return Pose.from_xyz_rpy([float(v) for v in origin.get("xyz").split()],
                             [float(v) for v in origin.get("rpy").split()])


def test_export_prints_the_results_mount_as_launch_and_urdf(session: Any, tmp_path: Path,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    _, result, _ = session
    path = tmp_path / "result.json"
    path.write_text(json.dumps(result))
    assert main(["export", "--ros2", str(path)]) == 0
    out = capsys.readouterr().out
    mount = Pose.from_dict(result["mount"])
    values = _launch_values(out)
    assert [values[k] for k in "xyz"] == result["mount"]["translation_m"]
    # the stored quaternion (as scipy normalises it: within 1e-15)
    assert np.allclose([values[k] for k in ("qx", "qy", "qz", "qw")], result["mount"]["quaternion_xyzw"], atol=1e-15)
    assert '"--frame-id", "flange", "--child-frame-id", "camera"' in out
    assert "static_transform_publisher" in out and "def generate_launch_description" in out
    compile(out[:out.index("<!--")], "launch.py", "exec")  # the launch snippet is valid Python
    assert _urdf_origin(out).is_close(mount, atol_m=1e-15, atol_rad=1e-12)


def test_export_reads_a_hand_eye_file_in_the_mount_table_form(tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "handeye.json"
    path.write_text(json.dumps({"mount": {"translation_m": [0.012, -0.034, 0.081], "rpy_deg": [1.5, -2.0, 91.0]}}))
    assert main(["export", "--ros2", str(path), "--parent", "tool0", "--child", "tof_optical"]) == 0
    out = capsys.readouterr().out
    want = Pose.from_xyz_rpy([0.012, -0.034, 0.081], np.radians([1.5, -2.0, 91.0]))
    values = _launch_values(out)
    assert np.allclose([values[k] for k in "xyz"], want.translation, atol=1e-15)
    assert np.allclose([values[k] for k in ("qx", "qy", "qz", "qw")], want.rotation.as_quat(), atol=1e-15)
    assert '<parent link="tool0"/>' in out and '<child link="tof_optical"/>' in out
    origin = ElementTree.fromstring(out[out.index("<joint"):]).find("origin")
    assert np.allclose([float(v) for v in origin.get("rpy").split()], np.radians([1.5, -2.0, 91.0]), atol=1e-15)


@pytest.mark.parametrize(("content", "says"), [
    (None, "file not found"),
    ("{not json", "not a readable JSON file"),
    ("[1, 2]", "no 'mount' object"),
    ('{"mount": {"translation_m": [0, 0, 0]}}', "'mount'"),
    ('{"mount": {"translation_m": [0, 0], "rpy_deg": [0, 0, 0]}}', "mount.translation_m"),
    ('{"mount": {"translation_m": [0, 0, 0], "rpy_deg": [0, "a", 0]}}', "mount.rpy_deg"),
    ('{"mount": {"translation_m": [0, 0, 0], "quaternion_xyzw": [0, 0, 0, 2]}}', "not a unit quaternion"),
])
def test_export_of_a_bad_file_is_one_line_and_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                     content: str | None, says: str) -> None:
    path = tmp_path / "in.json"
    if content is not None:
        path.write_text(content)
    assert main(["export", "--ros2", str(path)]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    (line,) = captured.err.strip().splitlines()
    assert line.startswith("cellcal: error: ") and str(path) in line and says in line


def test_record_ros2_refuses_a_non_empty_directory(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "bag"
    out.mkdir()
    (out / "other").write_text("x")
    assert main(["record", "--format", "ros2", "--out", str(out), "--quiet"]) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert "exists" in line and str(out) in line
    assert [p.name for p in out.iterdir()] == ["other"]
