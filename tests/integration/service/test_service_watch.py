"""Tracking and monitoring inside the service (core/service/watch.py): one thing at a time per cell, the stop
bounded, the token, the XML-RPC methods and the options' refusals; monitoring on the packaged sim cell."""

from __future__ import annotations

import time
import xmlrpc.client
from pathlib import Path
from typing import Any

import httpx
import pytest
from conftest import WAIT_S, serving, sim_config

from cellcal.core.service import Service
from cellcal.core.service.errors import RequestError
from cellcal.core.service.watch import WatchOptions, watch_values
from cellcal.core.service.xmlrpc import XmlRpcMethods

TOKEN = "watch-test-token-0123456789"
CELL = "paper-sim"


def _fast_monitor(tmp_path: Path, settle_s: float = 0.0) -> Path:
    """sim.toml with a monitor that captures as fast as it can and measures its baseline over 5 frames."""
    path = sim_config(tmp_path, settle_s)
    path.write_text(path.read_text() + "\n[monitor]\nperiod_s = 0.0\nbaseline_frames = 5\n")
    return path


def _until(predicate: Any) -> None:
    deadline = time.monotonic() + WAIT_S
    while not predicate():
        assert time.monotonic() < deadline
        time.sleep(0.02)


def test_options_are_checked_in_one_line() -> None:
    assert WatchOptions.from_dict(None) == WatchOptions()
    assert WatchOptions.from_dict({"duration_s": 2, "max_frames": 3}).duration_s == 2.0
    for bad, words in [({"bogus": 1}, "unknown option 'bogus'"), ({"duration_s": -1.0}, "duration_s"),
                       ({"duration_s": float("nan")}, "duration_s"), ({"max_frames": True}, "max_frames"),
                       ({"max_frames": 0}, "max_frames"), ({"baseline": "x"}, "baseline"), ({"camera": 3}, "camera")]:
        with pytest.raises(RequestError, match=words):
            WatchOptions.from_dict(bad)


def test_monitoring_holds_the_cell_reports_its_frames_and_stops(tmp_path: Path) -> None:
    service = Service([_fast_monitor(tmp_path)], tmp_path / "out")
    assert watch_values(service.watches, CELL, "camera")["MonitorState"] == "idle"
    with serving(service) as base, httpx.Client(base_url=base, timeout=WAIT_S) as client:
        assert client.get(f"/cells/{CELL}/monitor").json()["state"] == "idle"
        assert client.delete(f"/cells/{CELL}/monitor").status_code == 409  # nothing to stop
        assert client.post(f"/cells/{CELL}/monitor", json={"bogus": 1}).status_code == 422
        assert client.post(f"/cells/{CELL}/monitor", json={"camera": "nope"}).status_code == 404
        started = client.post(f"/cells/{CELL}/monitor")  # no body: every camera, until stopped
        assert started.status_code == 202, started.text
        assert client.post(f"/cells/{CELL}/track").status_code == 409  # one session at a time
        busy = client.post(f"/cells/{CELL}/runs", json={"kind": "calibrate", "camera": "camera"})
        assert busy.status_code == 409 and "monitoring" in busy.json()["error"]
        _until(lambda: client.get(f"/cells/{CELL}/monitor").json()["cameras"]["camera"]["frames"] >= 10)
        running = client.get(f"/cells/{CELL}/monitor").json()
        assert running["state"] == "running" and running["cameras"]["camera"]["estimate"]["baseline"] is not None
        stopped = client.post(f"/cells/{CELL}/monitor/stop").json()
        assert stopped["state"] == "stopped" and stopped["error"] is None
        assert stopped["cameras"]["camera"]["drift_events"] == 0  # a still arm over a still table: no drift
        values = watch_values(service.watches, CELL, "camera")
        assert values["MonitorState"] == "stopped" and values["DriftEvents"] == 0
        run = client.post(f"/cells/{CELL}/runs", json={"kind": "calibrate", "camera": "camera",
                                                       "options": {"report": False}})
        assert run.status_code == 202, run.text  # the cell is free again
        refused = client.post(f"/cells/{CELL}/monitor")
        assert refused.status_code == 409 and "running calibrate run" in refused.json()["error"]
        _until(lambda: client.get(f"/runs/{run.json()['id']}").json()["state"] == "ok")
        # a baseline from the calibration just made: the arm's pose read (it does not move), the plane seen from it
        calibrated = client.post(f"/cells/{CELL}/monitor", json={"baseline": "calibration", "max_frames": 12})
        assert calibrated.status_code == 202, calibrated.text
        _until(lambda: client.get(f"/cells/{CELL}/monitor").json()["state"] in ("stopped", "failed"))
        done = client.get(f"/cells/{CELL}/monitor").json()
        assert done["state"] == "stopped" and done["cameras"]["camera"]["frames"] == 12, done["error"]


def test_a_calibration_baseline_without_a_calibration_fails_in_one_line(tmp_path: Path) -> None:
    service = Service([_fast_monitor(tmp_path)], tmp_path / "out")
    try:
        activity = service.watches.start(CELL, "monitor", {"baseline": "calibration"})
        assert activity.done.wait(WAIT_S)
        assert activity.state == "failed" and "has no calibration yet" in (activity.error or "")
        assert "\n" not in (activity.error or "") and service.cell(CELL).watch is None  # the cell freed
    finally:
        service.close()


def test_the_token_guards_start_and_stop_over_http_and_xml_rpc(tmp_path: Path) -> None:
    service = Service([_fast_monitor(tmp_path)], tmp_path / "out")
    auth = {"Authorization": f"Bearer {TOKEN}"}
    with serving(service, token=TOKEN) as base, httpx.Client(base_url=base, timeout=WAIT_S) as client:
        assert client.post(f"/cells/{CELL}/track").status_code == 401
        assert client.post(f"/cells/{CELL}/monitor", headers=auth).status_code == 202
        assert client.delete(f"/cells/{CELL}/monitor").status_code == 401
        assert client.post(f"/cells/{CELL}/monitor/stop").status_code == 401
        assert client.get(f"/cells/{CELL}/monitor").status_code == 200  # reading needs none
        assert client.delete(f"/cells/{CELL}/monitor", headers=auth).json()["state"] == "stopped"
    rpc = XmlRpcMethods(Service([_fast_monitor(tmp_path)], tmp_path / "out2"), TOKEN)
    try:
        with pytest.raises(xmlrpc.client.Fault) as refused:
            rpc.call("monitor_start", ())
        assert refused.value.faultCode == 401
        with pytest.raises(xmlrpc.client.Fault) as unknown:
            rpc.call("monitor_state", ("no-such-cell",))
        assert unknown.value.faultCode == 404
        assert rpc.call("monitor_state", ())["state"] == "idle"
        started = rpc.call("monitor_start", (TOKEN, "", {"max_frames": 1000}))
        assert started["state"] in ("starting", "running") and started["cameras"] == ["camera"]
        stopped = rpc.call("monitor_stop", (TOKEN, CELL))
        assert stopped["state"] == "stopped" and stopped["error"] == "" and stopped["id"] == started["id"]
        with pytest.raises(xmlrpc.client.Fault) as again:
            rpc.call("monitor_stop", (TOKEN,))
        assert again.value.faultCode == 409
        xmlrpc.client.dumps((stopped,), methodresponse=True)  # no nil anywhere: a UR program can read it
    finally:
        rpc.service.close()


def test_tracking_is_stopped_before_its_next_frame_and_its_files_written(tmp_path: Path) -> None:
    from repo_paths import REPO_ROOT

    service = Service([REPO_ROOT / "configs" / "sim_track.toml"], tmp_path / "out")
    try:
        activity = service.watches.start("track-sim", "track")  # until stopped
        _until(lambda: activity.to_dict()["cameras"]["camera"]["frames"] >= 5)
        ended = service.watches.stop("track-sim", "track")
        assert ended["state"] == "stopped" and ended["error"] is None
        written = tmp_path / "out" / "track-sim" / "camera" / "track.json"
        assert ended["files"]["camera"][0] == str(written) and written.is_file()
        assert service.cell("track-sim").watch is None
    finally:
        service.close()
