"""``cellcal serve``'s history over HTTP on the simulated cell: every run, the calibration it put into use, every
event; "the mount at time T"; runs a crash left running; a history that fails never fails a run."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import httpx
import pytest
from conftest import WAIT_S, Arms, serving, sim_config
from test_service_http import CAMERA, CELL, FAST, wait_for

from cellcal.core.calibration.outlock import OutputLock
from cellcal.core.service import HistoryStore, Service
from cellcal.core.service.recorder import ABANDONED, MAX_EVENT_DETAIL_BYTES

KEY = "paper-sim/camera"  # the camera's name in the store


def make(tmp_path: Path, arms: Arms, settle_s: float = 0.0, history: Any = None) -> Service:
    store = history if history is not None else HistoryStore.beside(tmp_path)
    return Service([sim_config(tmp_path, settle_s)], tmp_path / "out", build=arms, history=store)


def test_runs_their_calibrations_and_events_are_kept_and_the_mount_at_time_t_is_answered(tmp_path: Path,
                                                                                          arms: Arms) -> None:
    service = make(tmp_path, arms, settle_s=0.3)
    before = datetime.now(UTC) - timedelta(seconds=1)
    with serving(service) as base, httpx.Client(base_url=base, timeout=WAIT_S) as client:
        first = wait_for(client, client.post(f"{CELL}/runs", json=FAST).json()["id"])
        assert first["state"] == "ok"
        # the run's end shows only once its history is written: no wait needed here
        runs = client.get("/history/runs").json()
        assert [r["status"] for r in runs["items"]] == ["ok"] and runs["next_cursor"] is None
        record = client.get(f"/history/runs/{runs['items'][0]['id']}").json()
        assert record["camera"] == KEY and record["kind"] == "calibrate" and record["reason"] is None
        assert record["result"] == client.get(f"/runs/{first['id']}/result").json()["result"]  # the whole document
        current = client.get(f"{CAMERA}/calibration").json()
        now = datetime.now(UTC).isoformat()
        at = client.get(f"{CAMERA}/calibration", params={"at": now}).json()
        assert at["mount"]["run_id"] == record["id"] and at["plane"]["run_id"] == record["id"]
        assert at["plane"]["value"]["normal"] == current["plane_base"]["normal"]  # bit for bit
        assert at["plane"]["value"]["offset_m"] == current["plane_base"]["offset_m"]
        assert at["mount"]["value"]["translation_m"] == current["mount"]["translation_m"]
        assert at["mount"]["value"]["estimated"] is False and at["mount"]["covariance"] is None  # configured mount
        assert len(at["plane"]["covariance"]) == 3  # tilts and height
        early = client.get(f"{CAMERA}/calibration", params={"at": before.isoformat()})
        assert early.status_code == 404 and "had no calibration in use" in early.json()["error"]
        naive = client.get(f"{CAMERA}/calibration", params={"at": "2024-05-01T10:00:00"})
        assert naive.status_code == 422 and "no timezone" in naive.json()["error"]
        # a cancelled run is kept with its reason, and puts nothing into use
        run_id = client.post(f"{CELL}/runs", json=FAST).json()["id"]
        wait_for(client, run_id, lambda r: r["progress"]["poses_done"] >= 1)
        client.post(f"/runs/{run_id}/cancel")
        assert wait_for(client, run_id)["state"] == "cancelled"
        cancelled = client.get("/history/runs", params={"status": "cancelled", "camera": "camera"}).json()["items"]
        assert len(cancelled) == 1 and "arm was told to stop" in cancelled[0]["reason"]
        assert client.get(f"{CAMERA}/calibration", params={"at": datetime.now(UTC).isoformat()}).json()[
            "mount"]["run_id"] == record["id"]
        page = client.get("/history/runs", params={"limit": 1}).json()  # newest first, a page at a time
        assert page["items"][0]["status"] == "cancelled" and page["next_cursor"]
        rest = client.get("/history/runs", params={"limit": 1, "cursor": page["next_cursor"]}).json()
        assert rest["items"][0]["id"] == record["id"] and rest["next_cursor"] is None
        assert client.get("/history/runs", params={"limit": 501}).status_code == 422
        assert client.get("/history/runs", params={"cell": "paper-sim"}).status_code == 422  # needs the camera
        assert client.get("/history/runs/999").status_code == 404
        # every event published, oldest first, in the window asked
        assert service.recorder.flush()
        events = client.get("/history/events", params={"since": before.isoformat()}).json()["items"]
        kinds = [e["kind"] for e in events]
        assert kinds[0] == "run.state" and kinds.count("calibration.changed") == 1
        assert "run.cancel_requested" in kinds and kinds.count("run.state") == 4
        assert {e["camera"] for e in events} == {KEY}
        assert [e["detail"]["state"] for e in events if e["kind"] == "run.state"] == ["running", "ok", "running",
                                                                                      "cancelled"]
        assert client.get("/history/events", params={"until": before.isoformat()}).json()["items"] == []
    # a restart sees the same calibration: it is not put into use twice
    again = make(tmp_path, arms)
    try:
        assert again.cells["paper-sim"].calibration("camera") is not None
        assert again.history is not None
        assert len(again.history.list_applied(camera=KEY).items) == 2  # the run's mount and plane only
    finally:
        again.close()


def test_runs_a_crash_left_running_are_marked_failed_only_for_a_cell_nobody_holds(tmp_path: Path,
                                                                                   arms: Arms) -> None:
    with HistoryStore.beside(tmp_path) as store:
        crashed = store.start_run("calibrate", KEY, "sim.toml")
        elsewhere = store.start_run("handeye", "another-cell/camera", "other.toml")  # another service's, alive
    held = OutputLock.for_directory(tmp_path / "out" / "paper-sim").acquire()  # a second process runs the cell
    try:
        service = make(tmp_path, arms, history=f"sqlite:///{tmp_path / 'cellcal-history.sqlite'}")
        assert service.history is not None and service.history.run(crashed).status == "running"  # type: ignore
        service.close()
    finally:
        held.release()
    service = make(tmp_path, arms)
    try:
        assert service.history is not None
        marked = service.history.run(crashed)
        assert marked is not None and marked.status == "failed" and marked.reason == ABANDONED
        assert service.history.run(elsewhere).status == "running"  # type: ignore[union-attr]
    finally:
        service.close()


def test_a_history_that_fails_never_fails_a_run(tmp_path: Path, arms: Arms) -> None:
    store = HistoryStore.beside(tmp_path)
    service = make(tmp_path, arms, history=store)
    store.close()  # every later write fails (as a lost database would)
    sub = service.bus.subscribe()
    with serving(service) as base, httpx.Client(base_url=base, timeout=WAIT_S) as client:
        run = wait_for(client, client.post(f"{CELL}/runs", json=FAST).json()["id"])
        assert run["state"] == "ok" and client.get(f"{CAMERA}/calibration").status_code == 200
        service.bus.publish("drift.plane", {"cell": "paper-sim", "camera": "camera", "detail": "x" * 100})
        metrics = httpx.get(base.removesuffix("/v1") + "/metrics").text
    failures = float(next(line for line in metrics.splitlines()
                          if line.startswith("cellcal_history_failures_total")).split()[-1])
    assert failures >= 4  # the run's start, the calibration seen, its events...
    seen = []
    while (event := sub.get(0.2)) is not None:
        seen.append(event)
    failed = [e for e in seen if e.type == "history.failed"]
    # published, one line each, but not once per failure (at most one per 10 s)
    assert 1 <= len(failed) < failures and all("\n" not in e.data["message"] for e in failed)
    assert "cannot record" in failed[0].data["message"]


def test_an_event_s_detail_is_bounded(tmp_path: Path, arms: Arms) -> None:
    service = make(tmp_path, arms)
    try:
        service.bus.publish("drift.mount", {"cell": "paper-sim", "camera": "camera", "rotation_deg": 0.5})
        service.bus.publish("note", {"cell": "paper-sim", "blob": "x" * (MAX_EVENT_DETAIL_BYTES + 1)})
        service.bus.publish("service.note", {"text": "no cell"})
        assert service.recorder.flush()
        assert service.history is not None
        events = service.history.events().items
        assert [(e.camera, e.kind) for e in events] == [(KEY, "drift.mount"), ("paper-sim", "note"),
                                                        ("service", "service.note")]
        assert events[0].detail["rotation_deg"] == 0.5
        assert events[1].detail == {"truncated": True, "bytes": pytest.approx(MAX_EVENT_DETAIL_BYTES + 30, abs=10),
                                    "keys": ["blob", "cell"]}
    finally:
        service.close()
