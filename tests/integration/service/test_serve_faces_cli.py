"""``cellcal serve`` as a command with its history beside the output, ``/metrics`` and ``--xmlrpc-port``."""

from __future__ import annotations

import signal
import sqlite3
import time
import xmlrpc.client
from pathlib import Path

import httpx
import pytest
from conftest import WAIT_S, sim_config
from test_serve_cli import serve


def test_the_history_is_beside_the_output_and_xml_rpc_and_metrics_are_served(tmp_path: Path) -> None:
    out = tmp_path / "o"
    proc = serve("--config", str(sim_config(tmp_path)), "--port", "0", "--xmlrpc-port", "0", "--out", str(out))
    try:
        assert proc.stdout is not None
        lines = [proc.stdout.readline(), proc.stdout.readline()]
        rpc = next(line for line in lines if "XML-RPC on http://127.0.0.1:" in line)
        http = next(line for line in lines if "listening on http://127.0.0.1:" in line)
        url = rpc.split("XML-RPC on ")[1].split()[0]
        assert url.endswith("/RPC2") and f'rpc_factory("xmlrpc", "{url}")' in rpc
        base = http.split("listening on ")[1].split()[0].rstrip("/")
        proxy = xmlrpc.client.ServerProxy(url)
        with pytest.raises(xmlrpc.client.Fault) as none:
            proxy.run_state("no-such-run")
        assert none.value.faultCode == 404
        run_id = proxy.start_run("calibrate", "camera", {"report": False})  # loopback without a token: none taken
        metrics = httpx.get(base.removesuffix("/v1") + "/metrics", timeout=WAIT_S)
        assert metrics.status_code == 200 and 'cellcal_service_info{cell="paper-sim"' in metrics.text
        with httpx.Client(base_url=base, timeout=WAIT_S) as client:
            deadline = time.monotonic() + WAIT_S
            while proxy.run_state(run_id)["state"] != "ok":
                assert time.monotonic() < deadline
                time.sleep(0.05)
            runs = client.get("/history/runs").json()["items"]
        assert [(r["camera"], r["status"]) for r in runs] == [("paper-sim/camera", "ok")]
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=WAIT_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 130 and "Traceback" not in err
    with sqlite3.connect(out / "cellcal-history.sqlite") as db:  # the default store, beside the output
        assert db.execute("SELECT status FROM runs").fetchall() == [("ok",)]


def test_an_unusable_history_is_refused_in_one_line(tmp_path: Path) -> None:
    junk = tmp_path / "junk.sqlite"
    junk.write_bytes(b"this is not a database" * 100)
    done = serve("--port", "0", "--out", str(tmp_path / "o"), "--history", f"sqlite:///{junk}")
    _, err = done.communicate(timeout=WAIT_S)
    assert done.returncode == 2 and err.strip().count("\n") == 0 and "not a usable SQLite database" in err
