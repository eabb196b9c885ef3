"""``cellcal track --viz-port``: a Foxglove client sees each used frame's cloud, plane, frames and the tracked mount."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("foxglove")
pytest.importorskip("websockets")
from fault_cells import CellcalProcess
from foxglove_client import FoxgloveClient

from tests.support.ports import free_port, port_free

TOPICS = {"/camera/points", "/cellcal/plane", "/tf", "/cellcal/track"}


def test_track_streams_the_mount_and_each_frames_outcome(tmp_path: Path) -> None:
    port = free_port()
    with CellcalProcess(["track", "--viz-port", str(port), "--viz-wait", "30", "--duration", "100000", "--quiet",
                         "--out", str(tmp_path)]) as run:
        assert run.wait_for("\n", timeout_s=60)                # the server listens once its line is out
        line = run.stderr_so_far().splitlines()[0]
        assert f"live view: ws://127.0.0.1:{port}" in line, line
        with FoxgloveClient(f"ws://127.0.0.1:{port}") as client:
            client.wait_for_channels(TOPICS)
            assert client.seen.channels["/cellcal/track"]["schemaName"] == "cellcal.Track"
            client.subscribe_all()
            seen = client.collect(TOPICS, count=5, timeout_s=60)
        run.interrupt()
        code, _out, err = run.finish(30)
    messages = [m for _, m in seen.messages["/cellcal/track"]]
    assert all(m["outcome"] in ("accepted", "held out") and m["frame_id"] == "camera" for m in messages)
    assert all(abs(np.linalg.norm(m["mount_translation_m"]) - 0.0582) < 0.02 for m in messages)
    assert all(abs(m["mount_rpy_deg"][2] - 90.4) < 1.0 and m["change_open"] is False for m in messages)
    assert code == 130, err
    assert port_free(port) and (tmp_path / "track.json").exists()
