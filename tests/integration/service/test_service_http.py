"""``cellcal serve``'s HTTP face on the simulated cell, over a real socket (uvicorn on 127.0.0.1:0) with httpx.

calibrate -> progress -> result -> calibration -> pixel_to_base (PlaneMap's point; the sigma a Monte
Carlo of the calibration's covariance gives); cancel mid-run (the sim arm's stop seen, no move after
it, the earlier result intact); 409 for a second run; a client that leaves mid-run leaves the run going.
"""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np
from conftest import WAIT_S, Arms, serving
from scipy.spatial.transform import Rotation

from cellcal.core.geometry.planemap import PlaneMap
from cellcal.core.geometry.planes import Plane, tangent_basis
from cellcal.core.geometry.relative import perturb
from cellcal.core.service import Service
from cellcal.devices.pose import Pose

CELL = "/cells/paper-sim"
CAMERA = f"{CELL}/cameras/camera"
FAST = {"kind": "calibrate", "camera": "camera", "options": {"report": False}}


def wait_for(client: httpx.Client, run_id: str, done: Any = None) -> dict[str, Any]:
    """Poll the run until ``done(run)`` (default: it has ended); the run."""
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline:
        run: dict[str, Any] = client.get(f"/runs/{run_id}").json()
        if (done(run) if done is not None else run["state"] in ("ok", "failed", "cancelled")):
            return run
        time.sleep(0.05)
    raise AssertionError(f"run {run_id} did not get there: {run}")


def follow_events(base: str, into: list[dict[str, Any]], stop: threading.Event) -> threading.Thread:
    """Read the server-sent events into ``into`` until ``stop`` is set."""
    def read() -> None:
        with httpx.Client(timeout=WAIT_S) as client, client.stream("GET", f"{base}/events") as stream:
            for line in stream.iter_lines():
                if line.startswith("data: "):
                    into.append(json.loads(line[6:]))
                if stop.is_set():
                    return

    thread = threading.Thread(target=read, daemon=True)
    thread.start()
    return thread


def monte_carlo_sigma(calibration: dict[str, Any], flange: Pose, pixel: np.ndarray, document: dict[str, Any],
                      draws: int = 4000) -> np.ndarray:
    """1-sigma of the point at ``pixel`` over draws of the 9 parameters from the calibration's covariance."""
    cov = np.asarray(calibration["covariance"])
    plane = Plane(np.asarray(calibration["plane_base"]["normal"]), calibration["plane_base"]["offset_m"])
    anchor = np.asarray(calibration["plane_base"]["anchor_m"])
    mount = Pose.from_dict(calibration["mount"])
    intrinsics = PlaneMap.from_document(document, pose_index=0).intrinsics
    axes = tangent_basis(np.array(plane.normal))
    thetas = np.random.default_rng(11).multivariate_normal(np.zeros(9), cov, size=draws, method="eigh")
    points = []
    for theta in thetas:
        normal = Rotation.from_rotvec(axes @ theta[6:8]).apply(np.array(plane.normal))
        moved = Plane.from_point_normal(anchor + theta[8] * np.array(plane.normal), normal)
        camera = flange @ perturb(mount, theta[:6])
        points.append(PlaneMap.from_base_plane(intrinsics, moved, camera).pixel_to_base(pixel[None])[0])
    return np.std(np.array(points), axis=0, ddof=1)


def test_calibrate_progress_result_and_pixel_to_base_over_a_real_socket(make_service: Any) -> None:
    service: Service = make_service()
    events: list[dict[str, Any]] = []
    stop = threading.Event()
    with serving(service) as base, httpx.Client(base_url=base, timeout=WAIT_S) as client:
        assert client.get("/health").json()["status"] == "ok"
        assert client.get(f"{CELL}/cameras").json() == [{"name": "camera", "on": "flange", "backend": "sim"}]
        assert client.get(f"{CAMERA}/calibration").status_code == 404  # nothing calibrated yet
        reader = follow_events(base, events, stop)
        while service.bus.subscribers == 0:
            time.sleep(0.01)
        started = client.post(f"{CELL}/runs", json=FAST)
        assert started.status_code == 202, started.text
        run = wait_for(client, started.json()["id"])
        assert run["state"] == "ok" and run["progress"] == {"poses_done": 3, "poses_total": 3}
        result = client.get(f"/runs/{run['id']}/result").json()["result"]
        assert result["schema"].startswith("cellcal.calibration/") and len(result["poses"]) == 3
        calibration = client.get(f"{CAMERA}/calibration").json()
        assert calibration["kind"] == "calibrate" and calibration["file"] == run["result_file"]
        assert calibration["plane_base"]["height_sigma_m"] > 0
        # pixel_to_base at the first pose's flange: the consensus plane seen from there, as PlaneMap maps it
        flange = Pose.from_dict(result["poses"][0]["reported_flange_pose"])
        pixels = np.array([[111.5, 85.5], [20.25, 30.75], [200.0, 150.0]])
        answer = client.post(f"{CAMERA}/pixel_to_base", json={"pixels": pixels.tolist(),
                                                                "flange_pose": flange.to_dict()})
        assert answer.status_code == 200, answer.text
        stop.set()
        service.bus.publish("test.end")  # wakes the reader so it sees stop
        reader.join(WAIT_S)
    document = json.loads(Path(run["result_file"]).read_text())
    want = PlaneMap.from_document(document, camera_in_base=flange @ Pose.from_dict(document["mount"]))
    points, sigma = np.array(answer.json()["points_m"]), np.array(answer.json()["sigma_m"])
    assert np.max(np.abs(points - want.pixel_to_base(pixels))) < 1e-9  # the same point to a nanometre
    assert np.all(sigma > 0)
    mc = monte_carlo_sigma(calibration, flange, pixels[1], document)
    assert np.all(np.abs(sigma[1] / mc - 1.0) < 0.10), (sigma[1], mc)  # first order holds to 10 % (4000 draws: ~2 %)
    # the progress was published pose by pose, then the end
    progress = [e["data"]["progress"]["poses_done"] for e in events if e["type"] in ("run.state", "run.progress")]
    assert progress[-1] == 3 and sorted(set(progress)) == [0, 1, 2, 3]
    assert [e["data"]["state"] for e in events if e["type"] == "run.state"] == ["running", "ok"]
    assert any(e["type"] == "calibration.changed" for e in events)


def test_cancel_mid_run_stops_the_arm_moves_no_more_and_keeps_the_earlier_result(make_service: Any,
                                                                                  arms: Arms) -> None:
    service: Service = make_service(settle_s=0.5)
    with serving(service) as base, httpx.Client(base_url=base, timeout=WAIT_S) as client:
        first = wait_for(client, client.post(f"{CELL}/runs", json=FAST).json()["id"])
        assert first["state"] == "ok"
        before = Path(first["result_file"]).read_bytes()
        run_id = client.post(f"{CELL}/runs", json=FAST).json()["id"]
        wait_for(client, run_id, lambda r: r["progress"]["poses_done"] >= 1)
        second = client.post(f"{CELL}/runs", json=FAST)  # one run at a time per cell
        assert second.status_code == 409 and list(second.json()) == ["error"]
        assert "one run at a time" in second.json()["error"]
        cancelled = client.post(f"/runs/{run_id}/cancel")
        assert cancelled.status_code == 202 and cancelled.json()["cancel_requested"] is True
        run = wait_for(client, run_id)
        assert run["state"] == "cancelled" and "arm was told to stop" in run["error"]
        arm = arms.built[-1]
        assert arm.stops >= 1  # the calibrator's Ctrl-C path told the arm to stop
        assert arm.moves_started == run["progress"]["poses_done"] < 3  # no move after the cancel was seen
        assert Path(first["result_file"]).read_bytes() == before  # the earlier result untouched, still served
        assert client.get(f"{CAMERA}/calibration").json()["file"] == first["result_file"]
        assert client.post(f"/runs/{run_id}/cancel").status_code == 409  # it has ended
        assert client.get(f"/runs/{run_id}/result").status_code == 409
        assert client.get("/health").json()["cells"] == {"paper-sim": None}  # the cell is free again


def test_a_second_process_on_the_same_output_is_refused(make_service: Any, tmp_path: Path) -> None:
    service: Service = make_service(settle_s=0.5)
    other = Service([tmp_path / "sim.toml"], tmp_path / "out")  # as a second `cellcal serve` on the same --out
    with serving(service) as base, httpx.Client(base_url=base, timeout=WAIT_S) as client:
        run_id = client.post(f"{CELL}/runs", json=FAST).json()["id"]
        try:
            refused = other.start_run("paper-sim", "calibrate", "camera", {"report": False})
        except Exception as exc:
            refused = exc
        assert type(refused).__name__ == "BusyError" and "in use by another cellcal run" in str(refused)
        client.post(f"/runs/{run_id}/cancel")
        assert wait_for(client, run_id)["state"] == "cancelled"


def test_a_client_that_leaves_mid_run_leaves_the_run_going(make_service: Any) -> None:
    service: Service = make_service(settle_s=0.3)
    with serving(service) as base, httpx.Client(base_url=base, timeout=WAIT_S) as client:
        leaving = httpx.Client(base_url=base, timeout=WAIT_S)
        run_id = leaving.post(f"{CELL}/runs", json=FAST).json()["id"]
        with leaving.stream("GET", "/events") as stream:  # reads a little of the stream, then hangs up
            next(stream.iter_lines())
        leaving.close()
        run = wait_for(client, run_id)
        assert run["state"] == "ok" and run["progress"]["poses_done"] == 3
        deadline = time.monotonic() + WAIT_S
        while service.bus.subscribers and time.monotonic() < deadline:
            time.sleep(0.05)
        assert service.bus.subscribers == 0  # the stream of the client that left was closed
