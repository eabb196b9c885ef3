"""``--viz-wait`` and ``--viz-linger`` (ADR 0035): a viewer that joins late still sees the plane.

Each test runs ``cellcal`` as a user does (a subprocess) and connects a real Foxglove
WebSocket client (tests/support/foxglove_client.py) once the command says it is
waiting or lingering; Ctrl-C is a real SIGINT.
"""

from __future__ import annotations

import contextlib
import json
import logging
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("foxglove")
pytest.importorskip("websockets")
from foxglove_client import FoxgloveClient
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from cellcal.core.calibration.config import load_config, plan_flange_poses
from cellcal.core.cli import main
from cellcal.core.liveview import LiveView
from tests.support.ports import free_port, port_free

SCENE_TOPICS = {"/camera/points", "/cellcal/plane", "/tf"}
#: Longest wait for a line the command prints, s (a bound, not a timing assertion).
LINE_TIMEOUT_S = 120.0


@contextlib.contextmanager
def _cellcal(*args: str) -> Iterator[subprocess.Popen[str]]:
    """``cellcal ARGS`` as a child process, killed on the way out if it still runs."""
    proc = subprocess.Popen([sys.executable, "-m", "cellcal.core.cli", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def _read_until(proc: subprocess.Popen[str], text: str) -> list[str]:
    """The stderr lines up to and including the first one containing ``text``."""
    assert proc.stderr is not None
    lines: list[str] = []
    deadline = time.monotonic() + LINE_TIMEOUT_S
    while time.monotonic() < deadline:
        line = proc.stderr.readline()
        if not line:
            break
        lines.append(line)
        if text in line:
            return lines
    raise AssertionError(f"no line with {text!r} on stderr: {lines}")


def _finish(proc: subprocess.Popen[str], interrupt: bool = False) -> tuple[str, str]:
    if interrupt:
        proc.send_signal(signal.SIGINT)
    return proc.communicate(timeout=LINE_TIMEOUT_S)


def _on_plane(update: dict[str, Any], plane: dict[str, Any]) -> bool:
    """Whether the plane message's patch lies on ``plane`` (result.json's ``plane_cam``)."""
    (entity,) = update["entities"]
    c = entity["cubes"][0]["pose"]["position"]
    return abs(np.array(plane["normal"]) @ [c["x"], c["y"], c["z"]] + plane["offset_m"]) < 1e-9


def _refused(url: str, subprotocols: list[str]) -> bool:
    """Whether the server refuses a WebSocket handshake offering only ``subprotocols`` with HTTP 400."""
    try:
        with connect(url, subprotocols=subprotocols, open_timeout=10):  # type: ignore[arg-type]
            return False
    except InvalidStatus as exc:
        return exc.response.status_code == 400


def test_with_viz_wait_a_viewer_joining_a_second_after_start_sees_every_pose_and_a_refused_client_stays_silent(
        tmp_path: Path) -> None:
    n_poses = len(plan_flange_poses(load_config(None)))
    port = free_port()
    with _cellcal("calibrate", "--viz-port", str(port), "--viz-wait", "60", "--out", str(tmp_path), "--quiet") as proc:
        head = _read_until(proc, "waiting up to 60 s for a viewer")
        time.sleep(1.0)  # the viewer joins a second after the start
        url = f"ws://127.0.0.1:{port}"
        # a client offering another protocol only is refused (HTTP 400) ...
        assert _refused(url, ["other.v1"])
        # ... and a viewer offering only the protocol's original name (Lichtblick, an older Foxglove) is admitted
        with FoxgloveClient(url, subprotocols=("foxglove.websocket.v1",)) as client:
            assert client.ws.subprotocol == "foxglove.websocket.v1"
            client.wait_for_channels(SCENE_TOPICS)
            client.subscribe_all()
            seen = client.collect(SCENE_TOPICS, count=n_poses, timeout_s=LINE_TIMEOUT_S)
        out, err = _finish(proc)
    assert proc.returncode == 0, err
    document = json.loads((tmp_path / "result.json").read_text())
    planes = [pose["full_frame"]["plane_cam"] for pose in document["poses"]]
    assert len(planes) == n_poses
    assert all(_on_plane(update, plane) for (_, update), plane in zip(seen.messages["/cellcal/plane"], planes,
                                                                        strict=True))
    # ... and the refusal is no line of the run's output: only the live view's own lines are on stderr
    lines = (''.join(head) + err).splitlines()
    assert lines == [f"live view: ws://127.0.0.1:{port} (in Foxglove: Open connection, Foxglove WebSocket, this URL)",
                     "live view: waiting up to 60 s for a viewer to subscribe (Ctrl-C to stop)",
                     "live view: a viewer subscribed; starting"], lines
    assert out.splitlines() == [f"result written to {tmp_path / 'result.json'}"]
    assert port_free(port)


def test_during_viz_linger_a_viewer_joining_after_the_run_sees_the_last_plane_and_ctrl_c_is_130(
        tmp_path: Path) -> None:
    port = free_port()
    with _cellcal("calibrate", "--viz-port", str(port), "--viz-linger", "600", "--out", str(tmp_path),
                  "--quiet") as proc:
        _read_until(proc, "serving the last scene for 600 s more (Ctrl-C to stop)")
        document = json.loads((tmp_path / "result.json").read_text())  # written before the linger
        with FoxgloveClient(f"ws://127.0.0.1:{port}") as client:
            client.wait_for_channels(SCENE_TOPICS)
            client.subscribe_all()
            seen = client.collect(SCENE_TOPICS, timeout_s=LINE_TIMEOUT_S)
        out, err = _finish(proc, interrupt=True)
    assert proc.returncode == 130, err
    assert err.splitlines() == ["cellcal: interrupted"]
    assert out.splitlines() == [f"result written to {tmp_path / 'result.json'}"]
    _, update = seen.messages["/cellcal/plane"][-1]
    assert _on_plane(update, document["poses"][-1]["full_frame"]["plane_cam"])
    assert json.loads((tmp_path / "result.json").read_text()) == document and port_free(port)


@pytest.mark.parametrize("command", [["calibrate", "--quiet"], ["monitor", "--frames", "5", "--quiet"]])
def test_ctrl_c_while_waiting_for_a_viewer_is_130_and_starts_nothing(command: list[str], tmp_path: Path) -> None:
    port = free_port()
    with _cellcal(*command, "--out" if command[0] == "calibrate" else "--save-baseline",
                  str(tmp_path / "out"), "--viz-port", str(port), "--viz-wait") as proc:
        _read_until(proc, "waiting up to 60 s for a viewer to subscribe (Ctrl-C to stop)")
        out, err = _finish(proc, interrupt=True)
    assert proc.returncode == 130, err
    assert err.splitlines() == ["cellcal: interrupted"] and out == ""
    assert not (tmp_path / "out").exists() and port_free(port)


def test_monitor_lingers_with_its_last_frame_after_a_scripted_run(tmp_path: Path) -> None:
    port = free_port()
    with _cellcal("monitor", "--frames", "3", "--quiet", "--viz-port", str(port), "--viz-linger", "600") as proc:
        _read_until(proc, "serving the last scene for 600 s more")
        with FoxgloveClient(f"ws://127.0.0.1:{port}") as client:
            client.wait_for_channels({*SCENE_TOPICS, "/cellcal/drift"})
            client.subscribe_all()
            seen = client.collect({"/cellcal/drift", "/cellcal/plane"}, timeout_s=LINE_TIMEOUT_S)
        out, err = _finish(proc, interrupt=True)
    assert proc.returncode == 130, err
    assert "monitor finished" in out and err.splitlines() == ["cellcal: interrupted"]
    _, drift = seen.messages["/cellcal/drift"][-1]
    assert drift["label"] == "sim" and drift["phase"] == "baseline"


def test_a_linger_that_runs_out_keeps_the_runs_exit_status(tmp_path: Path) -> None:
    port = free_port()
    assert main(["calibrate", "--viz-port", str(port), "--viz-linger", "0.1", "--out", str(tmp_path),
                 "--quiet"]) == 0
    assert (tmp_path / "result.json").is_file() and port_free(port)


def test_both_names_of_the_protocol_are_admitted_and_a_refused_handshake_is_logged_without_printing_it(
        caplog: pytest.LogCaptureFixture, capfd: pytest.CaptureFixture[str]) -> None:
    """``foxglove.sdk.v1`` and ``foxglove.websocket.v1`` alone are each admitted; neither is refused (ADR 0035)."""
    caplog.set_level(logging.INFO, logger="cellcal.liveview")
    with LiveView(0) as view:
        for name in ("foxglove.sdk.v1", "foxglove.websocket.v1"):
            with connect(view.url, subprotocols=[name], open_timeout=10) as ws:  # type: ignore[list-item]
                assert ws.subprotocol == name
                assert json.loads(ws.recv(timeout=10))["op"] == "serverInfo"
        assert _refused(view.url, ["other.v1"])
        deadline = time.monotonic() + LINE_TIMEOUT_S  # the SDK logs from its own thread
        while not (ours := [r for r in caplog.records
                            if r.name == "cellcal.liveview" and "handshake failed" in r.getMessage()]):
            assert time.monotonic() < deadline, caplog.records
            time.sleep(0.01)
    (record,) = ours
    assert record.levelno == logging.INFO
    assert "foxglove.sdk.v1" in record.getMessage()
    assert capfd.readouterr() == ("", "")


@pytest.mark.parametrize("option", [["--viz-wait"], ["--viz-linger", "5"]])
def test_wait_or_linger_without_a_port_is_one_line_and_exit_2(option: list[str], tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["calibrate", *option, "--out", str(tmp_path / "out")]) == 2
    assert capsys.readouterr().err.strip() == f"cellcal: error: {option[0]} needs --viz-port"
    assert not (tmp_path / "out").exists()


def _several_cameras_scene(command: list[str], names: list[str], tf_messages: int) -> Any:
    """Run ``cellcal COMMAND --viz-port N --viz-linger 600``, then read the lingering scene of a cell's cameras: one
    message on each camera's own topics (none on the one camera's shared ones) and ``tf_messages`` on ``/tf``."""
    topics = {f"/cameras/{name}/{kind}" for name in names for kind in ("points", "plane")}
    port = free_port()
    with _cellcal(*command, "--viz-port", str(port), "--viz-linger", "600") as proc:
        _read_until(proc, "serving the last scene for")
        with FoxgloveClient(f"ws://127.0.0.1:{port}") as client:
            client.wait_for_channels({*topics, "/tf"})
            assert not {"/camera/points", "/cellcal/plane"} & set(client.seen.channels)
            client.subscribe_all()
            client.collect(topics, timeout_s=LINE_TIMEOUT_S)
            seen = client.collect({"/tf"}, count=tf_messages, timeout_s=LINE_TIMEOUT_S)
        _finish(proc, interrupt=True)
    return seen


def test_monitor_of_several_cameras_puts_each_on_its_own_topics_and_a_fixed_one_under_the_base() -> None:
    """``monitor --viz-port`` on configs/sim_multi.toml: each camera's cloud and plane on its own topics (a viewer
    keeps one message per topic), the fixed cameras' frames under ``base`` at their configured poses (ADR 0061)."""
    from repo_paths import REPO_ROOT
    from scipy.spatial.transform import Rotation

    from cellcal.core.calibration.config import load_every_camera
    from cellcal.devices.pose import Pose

    multi = REPO_ROOT / "configs" / "sim_multi.toml"
    poses = {c.camera_name: c.camera_entry.pose_base for c in load_every_camera(multi)}
    labels = [f"sim_multi.{name}" for name in poses]
    # the fixed cameras' scenes carry their frames (the monitor reads no arm: none for the wrist's)
    seen = _several_cameras_scene(["monitor", "--config", str(multi), "--frames", "2", "--quiet"], labels, 2)
    fixed = {t["child_frame_id"]: t for _, m in seen.messages["/tf"] for t in m["transforms"]
             if t["parent_frame_id"] == "base" and t["child_frame_id"].startswith("camera_")}
    for name, pose in poses.items():
        if pose is None:
            continue  # on the flange
        t = fixed[f"camera_sim_multi.{name}"]
        q, p = t["rotation"], t["translation"]
        got = Pose(Rotation.from_quat([q["x"], q["y"], q["z"], q["w"]]), np.array([p["x"], p["y"], p["z"]]))
        assert got.is_close(pose, atol_m=1e-9, atol_rad=1e-9)
    assert len(fixed) == sum(p is not None for p in poses.values()) == 2


def test_calibrate_of_several_cameras_draws_every_camera_in_one_scene(tmp_path: Path) -> None:
    """``calibrate --viz-port`` on configs/sim_multi.toml: the driven camera and the others captured at each pose
    on their own topics, the driven one under the flange, the fixed ones under base at their poses."""
    from repo_paths import REPO_ROOT

    multi = REPO_ROOT / "configs" / "sim_multi.toml"
    names = ["wrist", "above", "side45"]
    seen = _several_cameras_scene(["calibrate", "--config", str(multi), "--out", str(tmp_path / "out"), "--quiet"],
                                  names, 3)
    parents = {t["child_frame_id"]: t["parent_frame_id"] for _, m in seen.messages["/tf"] for t in m["transforms"]}
    assert parents["camera_wrist"] == "flange" and parents["flange"] == "base"
    assert parents["camera_above"] == "base" and parents["camera_side45"] == "base"
    for name in names:
        (_, cloud), *_ = seen.messages[f"/cameras/{name}/points"]
        assert cloud["frame_id"] == f"camera_{name}"
    assert (tmp_path / "out" / "result-above.json").is_file()
