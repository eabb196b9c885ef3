"""``cellcal serve`` as a command: security by default, and Ctrl-C mid-run (the run cancelled, exit 130)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
from conftest import WAIT_S, sim_config

TOKEN = "cli-test-token-0123456789"


def serve(*args: str, env: dict[str, str] | None = None) -> subprocess.Popen[str]:
    clean = {k: v for k, v in os.environ.items() if k != "CELLCAL_SERVE_TOKEN"}
    return subprocess.Popen([sys.executable, "-m", "cellcal.core.cli", "serve", *args], stdin=subprocess.DEVNULL,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env={**clean, **(env or {})})


def test_a_non_loopback_bind_without_a_token_is_refused(tmp_path: Path) -> None:
    done = serve("--host", "0.0.0.0", "--port", "0", "--out", str(tmp_path))
    _, err = done.communicate(timeout=WAIT_S)
    assert done.returncode == 2
    assert err.strip().count("\n") == 0 and "not loopback" in err and "CELLCAL_SERVE_TOKEN" in err
    short = tmp_path / "token"
    short.write_text("short\n")
    done = serve("--host", "0.0.0.0", "--port", "0", "--token-file", str(short), "--out", str(tmp_path))
    _, err = done.communicate(timeout=WAIT_S)
    assert done.returncode == 2 and "at least 16 characters" in err and err.strip().count("\n") == 0
    assert not (tmp_path / "paper-sim").exists()  # nothing ran


def test_ctrl_c_cancels_the_run_stops_the_arm_and_exits_130(tmp_path: Path) -> None:
    token_file = tmp_path / "token"
    token_file.write_text(TOKEN + "\n")
    config = sim_config(tmp_path, settle_s=0.5)
    proc = serve("--config", str(config), "--port", "0", "--token-file", str(token_file), "--out", str(tmp_path / "o"))
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        assert "listening on http://127.0.0.1:" in line, line
        base = line.split("listening on ")[1].split()[0].rstrip("/")
        with httpx.Client(base_url=base, timeout=WAIT_S) as client:
            run = {"kind": "calibrate", "camera": "camera", "options": {"report": False}}
            assert client.post("/cells/paper-sim/runs", json=run).status_code == 401
            started = client.post("/cells/paper-sim/runs", json=run, headers={"Authorization": f"Bearer {TOKEN}"})
            assert started.status_code == 202, started.text
            deadline = time.monotonic() + WAIT_S
            while client.get(f"/runs/{started.json()['id']}").json()["progress"]["poses_done"] < 1:
                assert time.monotonic() < deadline
                time.sleep(0.05)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=WAIT_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 130, err
    assert "cancelled at" in err and "the arm was told to stop" in err and "Traceback" not in err
    camera_dir = tmp_path / "o" / "paper-sim" / "camera"
    assert (camera_dir / "result.json.journal.jsonl").exists() and not (camera_dir / "result.json").exists()
