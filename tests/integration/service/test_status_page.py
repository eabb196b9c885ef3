"""The service's status page: ``/v1/status``, the reports served only from inside the output directory, and the
page itself in a real headless browser (Debian's chromium driven by playwright, as the reports' test does)
against a running ``cellcal serve`` on the sim cell: a run started over HTTP shows its progress and its end
without a reload, and the console stays clean.
"""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import httpx
import pytest
from conftest import WAIT_S, serving, sim_config

from cellcal.core.service import Service
from tests.support.browser import chromium_page, require_browser

RUN = {"kind": "calibrate", "camera": "camera", "options": {"report": True}}


def wait_for(client: httpx.Client, run_id: str) -> dict[str, Any]:
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline:
        run: dict[str, Any] = client.get(f"/runs/{run_id}").json()
        if run["state"] in ("ok", "failed", "cancelled"):
            return run
        time.sleep(0.05)
    raise AssertionError(f"run {run_id} did not end")


def test_status_and_reports_only_from_inside_the_output_directory(make_service: Any, tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")  # the calibrate report draws with it
    service: Service = make_service()
    with serving(service) as base, httpx.Client(base_url=base, timeout=WAIT_S) as client:
        root = client.get(base.removesuffix("/v1") + "/")
        assert root.status_code == 200 and root.headers["content-type"].startswith("text/html")
        assert "<title>cellcal service</title>" in root.text
        assert "http://" not in root.text and "https://" not in root.text  # nothing from another origin
        before = client.get("/status").json()
        assert before["status"] == "ok" and before["cells"][0]["run"] is None
        assert before["cells"][0]["cameras"][0]["calibration"] is None
        run = wait_for(client, client.post("/cells/paper-sim/runs", json=RUN).json()["id"])
        assert run["state"] == "ok", run["error"]
        status = client.get("/status").json()
        cell = status["cells"][0]
        assert cell["run"]["id"] == run["id"] and cell["run"]["report_url"] == f"/v1/runs/{run['id']}/report"
        camera = cell["cameras"][0]
        assert camera["calibration"]["kind"] == "calibrate" and camera["calibration"]["values"]["Calibrated"]
        assert camera["reports"] == ["/v1/cells/paper-sim/cameras/camera/reports/report.html"]
        page = Path(run["report_file"])
        served = client.get(f"/runs/{run['id']}/report")
        assert served.status_code == 200 and served.content == page.read_bytes()
        camera_report = base.removesuffix("/v1") + camera["reports"][0]
        assert client.get(camera_report).content == page.read_bytes()

        refused = ["/cells/paper-sim/cameras/camera/reports/..%2F..%2F..%2Fsecret.html",
                   "/cells/paper-sim/cameras/camera/reports/result.json",
                   "/cells/paper-sim/cameras/..%2F..%2F..%2F/reports/report.html",
                   "/cells/paper-sim/cameras/camera/reports/%2Fetc%2Fpasswd", "/runs/..%2F..%2Fsecret/report"]
        secret = tmp_path / "secret.html"
        secret.write_text("<p>outside the output directory</p>")
        for path in refused:
            answer = client.get(path)
            assert answer.status_code == 404 and "secret" not in answer.text and list(answer.json()) == ["error"]
        page.unlink()
        page.symlink_to(secret)  # a link out of the output directory is not followed
        assert client.get(f"/runs/{run['id']}/report").status_code == 404
        assert client.get(camera_report).status_code == 404
        assert client.get("/status").json()["cells"][0]["cameras"][0]["reports"] == []
        service.run(run["id"]).report_file = secret  # nor a run whose report lies elsewhere
        assert client.get(f"/runs/{run['id']}/report").status_code == 404


def _serve(*args: str) -> subprocess.Popen[str]:
    clean = {k: v for k, v in os.environ.items() if k != "CELLCAL_SERVE_TOKEN"}
    return subprocess.Popen([sys.executable, "-m", "cellcal.core.cli", "serve", *args], stdin=subprocess.DEVNULL,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=clean)


def _opcua_state(endpoint: str) -> str:
    from asyncua import Client, ua

    from cellcal.core.service.opcua_nodes import NAMESPACE

    async def read() -> str:
        async with Client(endpoint, timeout=30) as client:
            ns = await client.get_namespace_index(NAMESPACE)
            return str(await client.get_node(ua.NodeId("paper-sim.RunState", ns)).read_value())

    return asyncio.run(read())


#: Kept in the page: every run state and progress text the status page showed, as it changed.
OBSERVE = """() => {
  window.__seen = []; window.__marker = 'not reloaded';
  const note = () => {
    const state = document.querySelector('#cell-paper-sim .run-state');
    const progress = document.querySelector('#cell-paper-sim .run-progress');
    window.__seen.push([state ? state.textContent : null, progress ? progress.textContent : null]);
  };
  new MutationObserver(note).observe(document.getElementById('cells'),
                                     {subtree: true, childList: true, characterData: true});
}"""


def test_the_status_page_follows_a_run_in_headless_chromium(tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    pytest.importorskip("asyncua")
    require_browser()  # before the service starts: skipped, saying which, without chromium or playwright
    config = sim_config(tmp_path, settle_s=0.3)  # poses a few tenths of a second apart: each one a DOM change
    proc = _serve("--config", str(config), "--port", "0", "--opcua-port", "0", "--out", str(tmp_path / "out"))
    messages: list[str] = []
    requests: list[str] = []
    try:
        assert proc.stdout is not None
        opcua_line, http_line = proc.stdout.readline(), proc.stdout.readline()
        assert "OPC UA on opc.tcp://127.0.0.1:" in opcua_line and "read-only; security None" in opcua_line
        assert "listening on http://127.0.0.1:" in http_line, http_line
        base = http_line.split("listening on ")[1].split()[0].removesuffix("/v1/")
        with chromium_page(messages, requests) as page:
            page.goto(base + "/", wait_until="load", timeout=60_000)
            page.wait_for_function("() => document.getElementById('connection').textContent === 'live'",
                                   timeout=60_000)
            assert page.inner_text("#cell-paper-sim .run") == "No run yet."
            page.evaluate(OBSERVE)
            with httpx.Client(base_url=base + "/v1", timeout=WAIT_S) as client:
                run_id = client.post("/cells/paper-sim/runs", json=RUN).json()["id"]
                final = wait_for(client, run_id)
            page.wait_for_function("() => document.querySelector('#cell-paper-sim .run-report') !== null",
                                   timeout=60_000)
            seen = page.evaluate("() => window.__seen")
            marker = page.evaluate("() => window.__marker")
            shown = page.inner_text("#cell-paper-sim .run-state"), page.inner_text("#cell-paper-sim .run-progress")
            report = page.evaluate("() => fetch(document.querySelector('#cell-paper-sim .run-report').href)"
                                   ".then(r => r.status)")
            events = page.inner_text("#events")
            height = page.inner_text("#cell-paper-sim .plane-height")
        opcua_state = _opcua_state(opcua_line.split("OPC UA on ")[1].split()[0])
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=WAIT_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    total = final["progress"]["poses_total"]
    assert final["state"] == "ok" and total >= 3
    progress = [p for _, p in seen if p is not None]
    assert any(p == f"{k} / {total}" for p in progress for k in range(1, total)), seen  # mid-run, shown live
    assert shown == ("ok", f"{total} / {total}") and marker == "not reloaded"
    assert report == 200 and "run.progress" in events and " ± " in height
    assert not [m for m in messages if m.startswith(("error", "pageerror"))], messages
    assert all(url.startswith((base, "data:")) for url in requests), requests  # nothing from another origin
    assert opcua_state == "ok"
    assert proc.returncode == 130 and "Traceback" not in err
