"""Issue #41's end-to-end test: one real ``cellcal serve`` on the sim cell, driven over every face with its own client.

The cell is ``configs/sim_track.toml`` (what ``cellcal track`` tracks by default: the arm works on its
own, the camera is knocked 0.5 deg about its bracket's x axis) with the knock moved from 45 s to
:data:`KNOCK_S` of simulated time, so that tracking (which runs the sim as fast as it computes) meets it
within seconds. Over HTTP (httpx): calibrate -> result -> pixel_to_base; over XML-RPC
(xmlrpc.client): the plane and pixel_to_base equal to HTTP's; tracking started over HTTP, the knock's
``track.change`` read from the server-sent events, and its ``drift.mount`` counted in ``/metrics``;
over OPC UA (asyncua): the camera's ``TrackState``, ``DriftEvents`` and ``LastDrift``; the status page
in headless chromium shows the knock as it comes. A run asked while the cell tracks is a 409, the
stop answers ``stopped`` with ``track.json`` written, and Ctrl-C ends the service with 130.
"""

from __future__ import annotations

import asyncio
import json
import math
import re
import signal
import threading
import time
import xmlrpc.client
from pathlib import Path
from typing import Any

import httpx
import pytest
from conftest import WAIT_S
from repo_paths import REPO_ROOT
from scipy.spatial.transform import Rotation
from test_serve_cli import serve
from test_status_page import wait_for

from tests.support.browser import chromium_page, require_browser

CELL, CAMERA = "track-sim", "camera"
#: When the sim's camera is knocked, s of simulated time (sim_track.toml: 45 s).
KNOCK_S = 8.0
#: T_base_flange of the sim's first work pose (sim_track.toml): where the pixel is seen from.
FLANGE_T_M = [0.3824, 0.0515, 0.5023]
FLANGE_RPY_DEG = [180.0, 10.0, 7.66]


def _config(tmp_path: Path) -> Path:
    text = (REPO_ROOT / "configs" / "sim_track.toml").read_text()
    knocked = text.replace("at_s = 45.0", f"at_s = {KNOCK_S}")
    assert knocked != text and f'name = "{CELL}"' in text
    path = tmp_path / "track.toml"
    path.write_text(knocked)
    return path


def _faces(proc: Any) -> dict[str, str]:
    """The faces' addresses from the service's first three lines (OPC UA, XML-RPC, HTTP, in any order)."""
    assert proc.stdout is not None
    lines = [proc.stdout.readline() for _ in range(3)]
    found = {}
    for line in lines:
        if "OPC UA on " in line:
            found["opcua"] = line.split("OPC UA on ")[1].split()[0]
        elif "XML-RPC on " in line:
            found["xmlrpc"] = line.split("XML-RPC on ")[1].split()[0]
        elif "listening on " in line:
            found["http"] = line.split("listening on ")[1].split()[0].removesuffix("/").removesuffix("/v1")
    assert set(found) == {"opcua", "xmlrpc", "http"}, lines
    return found


class EventReader:
    """Reads ``/v1/events`` in a thread until a ``track.change`` came (or the stream ends); keeps what it read."""

    def __init__(self, url: str) -> None:
        self.url = url
        self.events: list[tuple[str, dict[str, Any]]] = []
        self.knock = threading.Event()
        self.open = threading.Event()
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self) -> None:
        kind = ""
        with httpx.Client(timeout=httpx.Timeout(WAIT_S, read=WAIT_S)) as client, \
                client.stream("GET", self.url) as answer:
            self.open.set()
            for line in answer.iter_lines():
                if line.startswith("event: "):
                    kind = line.removeprefix("event: ")
                elif line.startswith("data: "):
                    self.events.append((kind, json.loads(line.removeprefix("data: "))["data"]))
                    if kind == "track.change":
                        self.knock.set()
                        return


def _opcua_values(endpoint: str, names: list[str]) -> dict[str, Any]:
    from asyncua import Client, ua

    from cellcal.core.service.opcua_nodes import NAMESPACE

    async def read() -> dict[str, Any]:
        async with Client(endpoint, timeout=30) as client:
            ns = await client.get_namespace_index(NAMESPACE)
            return {n: await client.get_node(ua.NodeId(f"{CELL}/{CAMERA}.{n}", ns)).read_value() for n in names}

    return asyncio.run(read())


def _calibrate_and_map(client: httpx.Client, rpc: xmlrpc.client.ServerProxy) -> None:
    """HTTP: calibrate -> result -> pixel_to_base; XML-RPC: the same plane and point."""
    started = client.post(f"/cells/{CELL}/runs", json={"kind": "calibrate", "camera": CAMERA,
                                                       "options": {"report": False}})
    assert started.status_code == 202, started.text
    run = wait_for(client, started.json()["id"])
    assert run["state"] == "ok", run["error"]
    result = client.get(f"/runs/{run['id']}/result").json()
    assert result["run"]["id"] == run["id"] and result["result"]["schema"].startswith("cellcal.calibration/")
    calibration = client.get(f"/cells/{CELL}/cameras/{CAMERA}/calibration").json()
    size = calibration["intrinsics"]
    pixel = [size["width"] / 2.0, size["height"] / 2.0]  # the image's middle, px
    quaternion = Rotation.from_euler("xyz", FLANGE_RPY_DEG, degrees=True).as_quat().tolist()
    mapped = client.post(f"/cells/{CELL}/cameras/{CAMERA}/pixel_to_base",
                         json={"pixels": pixel, "flange_pose": {"translation_m": FLANGE_T_M,
                                                                "quaternion_xyzw": quaternion}})
    assert mapped.status_code == 200, mapped.text
    point, sigma = mapped.json()["points_m"][0], mapped.json()["sigma_m"][0]
    plane = calibration["plane_base"]
    # the point is on the calibrated plane (n . p + offset = 0, to rounding) and its sigma is a few mm
    assert abs(sum(n * p for n, p in zip(plane["normal"], point, strict=True)) + plane["offset_m"]) < 1e-9
    assert all(0.0 < s < 0.05 for s in sigma), sigma

    by_rpc = rpc.plane(CAMERA)
    assert by_rpc["normal"] == pytest.approx(plane["normal"], abs=1e-15)
    assert by_rpc["offset_m"] == pytest.approx(plane["offset_m"], abs=1e-15)
    rotvec = Rotation.from_quat(quaternion).as_rotvec().tolist()
    values = rpc.pixel_to_base(CAMERA, pixel[0], pixel[1], [*FLANGE_T_M, *rotvec])
    # the same point through a rotation vector instead of a quaternion: equal to rounding (1e-12 m)
    assert values[:3] == pytest.approx(point, abs=1e-12) and values[3:] == pytest.approx(sigma, rel=1e-9)


def _page(base: str, during: Any) -> tuple[str, str, list[str]]:
    """Open the status page in headless chromium, run ``during()``, wait until the page shows the knock."""
    messages: list[str] = []
    with chromium_page(messages) as page:
        page.goto(base + "/", wait_until="load", timeout=60_000)
        page.wait_for_function("() => document.getElementById('connection').textContent === 'live'",
                               timeout=60_000)
        assert page.inner_text(f"#track-{CELL}") == "Tracking: none yet."
        during()
        page.wait_for_function(f"() => {{ const c = document.querySelector('#track-{CELL} .last-drift'); "
                               "return c !== null && c.textContent.includes('change detected'); }",
                               timeout=60_000)
        shown = page.inner_text(f"#track-{CELL} .last-drift")
        events = page.inner_text("#events")
    return shown, events, messages


def test_calibrate_map_track_a_knock_and_count_it_over_every_face(tmp_path: Path) -> None:
    pytest.importorskip("asyncua")
    require_browser()  # before the service starts: skipped, saying which, without chromium or playwright
    began = time.monotonic()
    proc = serve("--config", str(_config(tmp_path)), "--port", "0", "--opcua-port", "0", "--xmlrpc-port", "0",
                 "--out", str(tmp_path / "out"))
    try:
        faces = _faces(proc)
        base, rpc = faces["http"], xmlrpc.client.ServerProxy(faces["xmlrpc"])
        with httpx.Client(base_url=base + "/v1", timeout=WAIT_S) as client:
            _calibrate_and_map(client, rpc)
            assert rpc.track_state()["state"] == "idle"
            reader = EventReader(base + "/v1/events")
            assert reader.open.wait(WAIT_S)
            track: dict[str, Any] = {}

            def start_tracking() -> None:
                answer = client.post(f"/cells/{CELL}/track", json={"duration_s": 600.0})
                assert answer.status_code == 202, answer.text
                track.update(answer.json())
                busy = client.post(f"/cells/{CELL}/runs", json={"kind": "calibrate", "camera": CAMERA})
                assert busy.status_code == 409 and "tracking" in busy.json()["error"]

            shown, page_events, messages = _page(base, start_tracking)
            assert reader.knock.wait(WAIT_S), reader.events  # the knock over SSE, within WAIT_S at most
            kind, change = reader.events[-1]
            assert kind == "track.change" and change["camera"] == CAMERA and change["stage"] == "detected"
            assert KNOCK_S <= change["event"]["detected_at_s"] <= KNOCK_S + 5.0  # seen within 5 s of frames
            state = rpc.track_state(CELL)
            assert state["state"] == "running" and state["drift_events"] >= 1 and state["id"] == track["id"]
            metrics = httpx.get(base + "/metrics", timeout=WAIT_S).text
            counted = re.search(rf'^cellcal_drift_events_total\{{camera="{CAMERA}",cell="{CELL}",kind="mount"\}} '
                                r"(\S+)$", metrics, re.M)
            assert counted is not None and float(counted[1]) == 1.0, metrics
            opcua = _opcua_values(faces["opcua"], ["TrackState", "DriftEvents", "LastDrift", "TrackFrames"])
            stopped = client.delete(f"/cells/{CELL}/track")
            assert stopped.status_code == 200, stopped.text
            ended = stopped.json()
            assert client.get(f"/cells/{CELL}/track").json()["state"] == "stopped"
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=WAIT_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    took = time.monotonic() - began
    # the knock told apart as the mount's: 0.5 deg about the bracket (within 0.1 deg: the first frames' fit)
    (knock,) = ended["cameras"][CAMERA]["changes"]
    assert knock["kind"] == "mount" and abs(knock["size"]["rotation_deg"] - 0.5) < 0.1
    assert ended["state"] == "stopped" and ended["error"] is None and ended["cameras"][CAMERA]["drift_events"] == 1
    estimate = ended["cameras"][CAMERA]["estimate"]
    assert estimate["schema"] == "cellcal.track/1" and math.isfinite(estimate["mount"]["rpy_deg"][0])
    assert json.loads(Path(ended["files"][CAMERA][0]).read_text())["events"][0]["kind"] == "mount"
    assert opcua["TrackState"] == "running" and opcua["DriftEvents"] >= 1 and opcua["TrackFrames"] > 0
    assert "change detected" in opcua["LastDrift"] and "change detected" in shown
    assert "track.change" in page_events and "drift.mount" in page_events
    assert not [m for m in messages if m.startswith(("error", "pageerror"))], messages
    assert proc.returncode == 130 and "Traceback" not in err, err
    print(f"end to end: {took:.1f} s")
