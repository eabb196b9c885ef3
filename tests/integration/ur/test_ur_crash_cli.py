"""``cellcal calibrate`` on a UR cell whose ur_rtde dies mid-run: exit 1, one line, the journal kept.

The run is ``configs/ur_emulated.toml`` (the real ur driver through ur_rtde to the UR emulator);
after the first pose is in the journal, the driver's ur_rtde worker process gets SIGSEGV.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from importlib import resources
from pathlib import Path

import pytest

pytest.importorskip("rtde_control")  # the ur extra

CONFIG = Path(str(resources.files("cellcal.configs"))) / "ur_emulated.toml"
WORKER = b"cellcal.devices.isolation.worker"


def _workers_of(parent: int) -> list[int]:
    """Process ids of ur_rtde worker processes whose parent is ``parent`` (Linux /proc)."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            cmdline = (entry / "cmdline").read_bytes()
            ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            continue
        if ppid == parent and WORKER in cmdline:
            found.append(int(entry.name))
    return found


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs Linux /proc")
def test_a_segfault_in_ur_rtde_ends_calibrate_with_exit_1_one_line_and_the_journal_kept(tmp_path: Path) -> None:
    journal = tmp_path / "result.json.journal.jsonl"
    proc = subprocess.Popen([sys.executable, "-m", "cellcal.core.cli", "calibrate", "--config", str(CONFIG),
                             "--out", str(tmp_path), "--quiet", "--no-report"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120.0
        while time.monotonic() < deadline and proc.poll() is None:
            if journal.exists() and len(journal.read_text().splitlines()) >= 2:   # a header and one pose
                break
            time.sleep(0.05)
        workers = _workers_of(proc.pid)
        assert proc.poll() is None and len(workers) == 1, "the run ended before a pose was journalled"
        os.kill(workers[0], signal.SIGSEGV)
        out, err = proc.communicate(timeout=60.0)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 1, err
    assert out.strip() == "", out                              # --quiet: nothing but the error line
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith("cellcal: error: ") and "the ur_rtde worker process died during" in lines[0]
    assert "(SIGSEGV, a crash in native code)" in lines[0] and "the arm was told to stop" in lines[0]
    records = [json.loads(line) for line in journal.read_text().splitlines()]
    assert len(records) >= 2                                   # what was measured is still there
    assert not (tmp_path / "result.json").exists()             # and no result pretends the run finished
