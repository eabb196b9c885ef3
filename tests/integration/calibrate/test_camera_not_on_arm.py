"""A camera that is not on the arm that moves is named by calibrate, handeye and track (ADR 0045).

The simulated cells are the packaged ones with ``[sim] camera_on_arm = false`` (the camera
stays where the arm's first pose put it); the last test is the reported case: cellcal's own
O3R driver against the standalone O3R emulator, whose scene does not follow the arm.
"""

from __future__ import annotations

import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from emulator_cli import first_line, stop
from repo_paths import REPO_ROOT

from cellcal.core.calibration.calibrator import Calibrator, build_devices
from cellcal.core.calibration.config import load_config
from cellcal.core.cli import main

CONFIGS = REPO_ROOT / "configs"
#: The end of every message: what is wrong and what to check.
CAUSE = ("the camera is not on the arm that moves (check the rig, [camera]/[arm], or that the emulator's scene "
         "follows the arm)")
GATE = re.compile(r"^cellcal: error: quality gate 'view_follows_arm' failed: (\S+) vs threshold 0\.1; "
                  r"the camera's view did not change while the arm moved (\S+) m and turned (\S+) deg between ")


def off_arm(tmp_path: Path, name: str) -> Path:
    """The packaged ``name`` with its camera taken off the arm."""
    text = (CONFIGS / name).read_text()
    text = text.replace("\n[sim]\n", "\n[sim]\ncamera_on_arm = false\n") if "\n[sim]\n" in text \
        else text + "\n[sim]\ncamera_on_arm = false\n"
    path = tmp_path / name
    path.write_text(text)
    return path


def refused(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[str, float, float]:
    """Run ``cellcal argv`` in-process; it must exit 1 with the one-line message: the line, travel (m), turn (deg)."""
    assert main(list(argv)) == 1
    err = capsys.readouterr().err.strip().splitlines()
    line = err[-1]
    match = GATE.match(line)
    assert match, line
    assert line.endswith(CAUSE), line
    assert float(match.group(1)) < 0.01                   # the view changed by < 1 % of what the arm predicts
    return line, float(match.group(2)), float(match.group(3))


def test_calibrate_stops_at_the_second_pose_and_leaves_no_journal(tmp_path: Path,
                                                                   capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    line, travel, turn = refused(capsys, "calibrate", "--config", str(off_arm(tmp_path, "sim.toml")),
                                 "--out", str(out), "--quiet", "--no-report")
    assert "between poses 1 and 2 " in line
    assert (travel, turn) == (0.130, 0.0)                 # H1 0.46 m -> H2 0.59 m along the optical axis
    assert "on the arm: 130.1 mm, 0.00 deg" in line       # 0.13 m along an axis 80 deg from the plane
    assert not (out / "result.json").exists()
    assert list(out.glob("*.journal.jsonl")) == []        # nothing to resume on a corrected rig
    assert "--resume" not in line


def test_handeye_stops_at_the_first_pose_that_tilts_the_tool(tmp_path: Path,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    """Poses 2-4 roll the tool about its own axis, and the plane this camera shows (from straight above) lies
    within the mount's tolerance of that axis: a camera on the arm might see no change. Pose 5 tilts the tool."""
    out = tmp_path / "out"
    line, travel, turn = refused(capsys, "handeye", "--config", str(off_arm(tmp_path, "sim_handeye.toml")),
                                 "--out", str(out), "--quiet", "--no-report")
    assert "between poses 1 and 5 " in line
    assert travel == pytest.approx(0.133, abs=0.0015) and turn == pytest.approx(15.0, abs=0.15)
    assert not (out / "handeye.json").exists()


def test_track_stops_once_the_work_has_moved_the_arm(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    line, _, turn = refused(capsys, "track", "--config", str(off_arm(tmp_path, "sim_track.toml")),
                            "--out", str(out), "--duration", "30", "--quiet")
    times = re.search(r"between frames at (\S+) s and (\S+) s ", line)
    assert times, line
    # the work's first tilt of the tool decides (its first moves turn the tool about its own axis)
    assert float(times.group(1)) < 1.0 and 5.0 < float(times.group(2)) < 30.0
    assert turn == pytest.approx(15.0, abs=0.15)
    assert not (out / "track.json").exists()              # a failed run writes no result


def test_the_packaged_cell_sees_the_change_its_arm_predicts() -> None:
    config = load_config(CONFIGS / "sim.toml")
    calibrator = Calibrator(config, *build_devices(config))
    calibrator.run()
    decided = calibrator.view_check.decided if calibrator.view_check is not None else None
    assert decided is not None and (decided.first, decided.second) == ("1", "2")
    assert decided.least_sigmas > 1000                    # 0.13 m along an axis 10 deg from the normal
    assert decided.measured_sigmas == pytest.approx(decided.predicted_sigmas, rel=0.01)
    assert 1.0 < decided.fraction < 2.0                   # the least change is 0.82 of the predicted one


def test_the_o3r_driver_against_the_standalone_emulator_is_refused(tmp_path: Path,
                                                                    capsys: pytest.CaptureFixture[str]) -> None:
    """The user's case: the standalone emulator renders from the sim arm's first pose whatever the arm does.

    The plan is ``ur_o3r.toml``'s (no full-frame method: the plane is fitted for the check alone).
    """
    proc = subprocess.Popen([sys.executable, "-m", "cellcal.sims.o3r", "--xmlrpc-port", "0", "--pcic-port", "0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        ready = first_line(proc, 60.0)
        port = re.search(r"xmlrpc=127\.0\.0\.1:(\d+)", ready)
        assert port, ready
        text = (CONFIGS / "ur_o3r.toml").read_text()
        text = text.replace('host = "192.168.0.69"', 'host = "127.0.0.1"').replace(
            "xmlrpc_port = 80", f"xmlrpc_port = {port.group(1)}")
        arm = text[text.index("[arm]"):text.index("# Hand-eye")]
        config = tmp_path / "cell.toml"
        config.write_text(text.replace(arm, '[arm]\nbackend = "sim"\ntime_scale = 0.001\n\n'))
        assert "full_frame" not in load_config(config).plan.methods
        line, travel, _ = refused(capsys, "calibrate", "--config", str(config), "--out", str(tmp_path / "out"),
                                  "--quiet", "--no-report")
        assert "between poses 1 and 2 " in line and travel == 0.130
    finally:
        stop(proc, signal.SIGTERM)
