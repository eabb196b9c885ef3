"""The live view (``--viz-port``): a real Foxglove WebSocket client against the foxglove-sdk server.

The client (tests/support/foxglove_client.py, on the ``websockets`` package) learns the
advertised channels, subscribes, and checks what arrives against the calibration's own
result: the arm's poses, the fit's inliers, the plane.
"""

from __future__ import annotations

import base64
import math
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

pytest.importorskip("foxglove")
pytest.importorskip("websockets")
from foxglove_client import FoxgloveClient

from cellcal.core.calibration.calibrator import Calibrator, build_devices
from cellcal.core.calibration.config import load_config
from cellcal.core.cli import main
from cellcal.core.liveview import LiveView
from cellcal.devices.pose import Pose
from tests.support.ports import free_port, port_free

SCENE_TOPICS = {"/camera/points", "/cellcal/plane", "/tf"}
SCHEMAS = {"/camera/points": "foxglove.PointCloud", "/cellcal/plane": "foxglove.SceneUpdate",
           "/tf": "foxglove.FrameTransforms", "/cellcal/drift": "cellcal.Drift"}


def _pose(p: dict[str, Any]) -> Pose:
    t, q = p["translation"], p["rotation"]
    return Pose(Rotation.from_quat([q["x"], q["y"], q["z"], q["w"]]), np.array([t["x"], t["y"], t["z"]]))


def test_a_calibration_streams_points_plane_and_frames_to_a_websocket_client() -> None:
    config = load_config(None)
    camera, arm = build_devices(config)
    with LiveView(0) as view:
        assert view.url == f"ws://127.0.0.1:{view.port}"
        with FoxgloveClient(view.url) as client:
            client.wait_for_channels(SCENE_TOPICS)
            assert client.seen.server_name == "cellcal"
            assert {t: (c["schemaName"], c["encoding"]) for t, c in client.seen.channels.items()} == {
                t: (SCHEMAS[t], "json") for t in SCENE_TOPICS}
            client.subscribe_all()
            deadline = time.monotonic() + 60
            while view.subscriptions < len(client.seen.channels):  # the server registers each subscription
                assert time.monotonic() < deadline, view.subscriptions
                time.sleep(0.01)
            document = Calibrator(config, camera, arm, observer=view.observe_pose(config.mount.pose())).run()
            n = len(document["poses"])
            seen = client.collect(SCENE_TOPICS, count=n)
    assert {t: len(seen.messages[t]) for t in SCENE_TOPICS} == dict.fromkeys(SCENE_TOPICS, n)
    assert view.message_counts == dict.fromkeys(SCENE_TOPICS, n)
    mount = config.mount.pose()
    for pose, (_, tf), (_, cloud), (log_time, update) in zip(
            document["poses"], seen.messages["/tf"], seen.messages["/camera/points"], seen.messages["/cellcal/plane"],
            strict=True):
        # frames: base -> flange is the arm's reported pose, flange -> camera the mount
        (base, flange) = tf["transforms"]
        assert (base["parent_frame_id"], base["child_frame_id"]) == ("base", "flange")
        assert (flange["parent_frame_id"], flange["child_frame_id"]) == ("flange", "camera")
        assert _pose(base).is_close(Pose.from_dict(pose["reported_flange_pose"]), atol_m=1e-15, atol_rad=1e-12)
        assert _pose(flange).is_close(mount, atol_m=1e-15, atol_rad=1e-12)
        # points: every valid point, the fit's inliers green
        assert cloud["frame_id"] == "camera" and cloud["point_stride"] == 16
        data = np.frombuffer(base64.b64decode(cloud["data"]), dtype="u1").reshape(-1, 16)
        assert len(data) == pose["full_frame"]["n_points"]
        assert int(np.count_nonzero(data[:, 13] == 204)) == pose["full_frame"]["n_inliers"]  # G of green
        assert {f["name"] for f in cloud["fields"]} == {"x", "y", "z", "red", "green", "blue", "alpha"}
        # plane: the patch lies on the fitted plane, its arrow along the normal
        (entity,) = update["entities"]
        plane = pose["full_frame"]["plane_cam"]
        normal, offset = np.array(plane["normal"]), plane["offset_m"]
        centre = entity["cubes"][0]["pose"]["position"]
        assert abs(normal @ [centre["x"], centre["y"], centre["z"]] + offset) < 1e-9
        o = entity["arrows"][0]["pose"]["orientation"]
        assert Rotation.from_quat([o["x"], o["y"], o["z"], o["w"]]).apply([1, 0, 0]) @ normal > 1 - 1e-12
        stamp = entity["timestamp"]
        assert log_time == stamp["sec"] * 10**9 + stamp["nsec"]


def test_calibrate_with_viz_port_serves_during_the_run_and_frees_the_port(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    port = free_port()
    assert main(["calibrate", "--viz-port", str(port), "--out", str(tmp_path), "--quiet"]) == 0
    err = capsys.readouterr().err
    assert f"live view: ws://127.0.0.1:{port}" in err
    assert (tmp_path / "result.json").is_file() and port_free(port)


def test_a_closed_live_view_has_released_its_port_when_close_returns() -> None:
    """The SDK stops its server asynchronously; close() waits, so the next run can listen at once."""
    port = free_port()
    for _ in range(20):
        view = LiveView(port)
        assert view.port == port
        view.close()
        assert port_free(port)


def _cellcal(*args: str, env: dict[str, str] | None = None, **kw: Any) -> subprocess.Popen[str]:
    return subprocess.Popen([sys.executable, "-m", "cellcal.core.cli", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env, **kw)


def test_monitor_with_viz_port_streams_drift_values_and_points() -> None:
    port = free_port()
    proc = _cellcal("monitor", "--viz-port", str(port), "--duration", "60", "--quiet")
    try:
        assert proc.stderr is not None
        line = proc.stderr.readline()  # the server listens once this line is out
        assert f"live view: ws://127.0.0.1:{port}" in line, line
        with FoxgloveClient(f"ws://127.0.0.1:{port}") as client:
            client.wait_for_channels({*SCENE_TOPICS, "/cellcal/drift"})
            assert client.seen.channels["/cellcal/drift"]["schemaName"] == "cellcal.Drift"
            client.subscribe_all()
            seen = client.collect({"/cellcal/drift", "/camera/points", "/cellcal/plane"}, timeout_s=30)
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130, err
    _, drift = seen.messages["/cellcal/drift"][0]
    assert drift["label"] == "sim" and drift["phase"] in {"baseline", "ok", "drift"}
    assert 0.3 < drift["height_m"] < 1.0 and all(math.isfinite(drift[k]) for k in ("tilt_x_rad", "tilt_y_rad"))
    _, cloud = seen.messages["/camera/points"][0]
    assert cloud["frame_id"] == "camera" and len(base64.b64decode(cloud["data"])) > 16 * 10_000
    assert "monitor interrupted" in out and port_free(port)


def test_without_foxglove_sdk_viz_port_is_one_line_and_exit_2(tmp_path: Path) -> None:
    # a foxglove package that cannot be imported, first on the path
    (tmp_path / "foxglove").mkdir()
    (tmp_path / "foxglove" / "__init__.py").write_text("raise ImportError('no foxglove-sdk here')\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")])}
    for args in (["calibrate", "--out", str(tmp_path / "out")], ["monitor", "--frames", "1"]):
        proc = _cellcal(*args, "--viz-port", str(free_port()), env=env)
        _, err = proc.communicate(timeout=120)
        assert proc.returncode == 2, err
        (line,) = err.strip().splitlines()
        assert line == ("cellcal: error: --viz-port needs foxglove-sdk, which is not installed: "
                        "pip install 'cellcal[viz]'")
    assert not (tmp_path / "out").exists()


def test_a_port_in_use_is_one_line_and_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        assert main(["calibrate", "--viz-port", str(port), "--out", str(tmp_path), "--quiet"]) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line.startswith(f"cellcal: error: --viz-port {port}: cannot listen on 127.0.0.1:{port}")
    assert not (tmp_path / "result.json").exists()


@pytest.mark.parametrize("port", ["0", "65536", "http"])
def test_a_bad_port_number_is_a_usage_error(port: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main(["monitor", "--viz-port", port])
    assert info.value.code == 2 and "--viz-port" in capsys.readouterr().err
