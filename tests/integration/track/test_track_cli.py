"""``cellcal track`` on the simulated cell of ``configs/sim_track.toml``: the arm works on its own, a knock halfway.

Truths (from the config): the mount is (3, 45, 58) mm, rpy (0.6, -0.7, 90.4) deg, knocked at
45 s to roll 1.1 deg; the plane is z = 0. The run reads the arm and never commands it.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import pytest
from repo_paths import REPO_ROOT

from cellcal.core.calibration.config import load_config
from cellcal.core.cli import main

CONFIG = REPO_ROOT / "configs" / "sim_track.toml"
KNOCK_S = 45.0
TRUE_MOUNT_MM = (3.0, 45.0, 58.0)
TRUE_RPY_AFTER = (1.1, -0.7, 90.4)
EVENT = re.compile(r"^\[\[sim\.events\]\].*", re.S | re.M)


def _variant(tmp_path: Path, events: str) -> Path:
    """sim_track.toml with its [[sim.events]] replaced by ``events`` (TOML text)."""
    path = tmp_path / "cell.toml"
    path.write_text(EVENT.sub(events, CONFIG.read_text()))
    return path


def _run(tmp_path: Path, capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, dict[str, Any]]:
    out = tmp_path / "out"
    code = main(["track", "--out", str(out), *args])
    printed = capsys.readouterr().out
    return code, printed, json.loads((out / "track.json").read_text())


def _knock_run(out: Path, *config: str) -> tuple[int, str, dict[str, Any], list[dict[str, Any]]]:
    import contextlib
    import io

    buffer = io.StringIO()
    with contextlib.redirect_stdout(buffer):
        code = main(["track", "--out", str(out), *config])
    rows = [json.loads(line) for line in (out / "track.jsonl").read_text().splitlines()]
    return code, buffer.getvalue(), json.loads((out / "track.json").read_text()), rows


@pytest.fixture(scope="module")
def knocked(tmp_path_factory: pytest.TempPathFactory) -> tuple[int, str, dict[str, Any], list[dict[str, Any]]]:
    """The built-in run (no --config): 90 s of work, the knock at 45 s; the sims' systematic errors on (defaults)."""
    return _knock_run(tmp_path_factory.mktemp("knocked"))


@pytest.fixture(scope="module")
def knocked_ideal(tmp_path_factory: pytest.TempPathFactory) -> tuple[int, str, dict[str, Any], list[dict[str, Any]]]:
    """The same run with an ideal camera on an exact arm: the noise-level targets (issue #32) are its figures."""
    out = tmp_path_factory.mktemp("knocked_ideal")
    config = out / "ideal.toml"
    config.write_text(CONFIG.read_text() + "\n[sim.systematic]\nenabled = false\n\n[sim.arm_errors]\nenabled = false\n")
    return _knock_run(out, "--config", str(config), "--duration", "90")


def test_the_knock_is_detected_within_a_second_of_frames_and_told_mount(knocked: Any) -> None:
    code, printed, doc, _rows = knocked
    assert code == 0
    (event,) = doc["events"]
    assert event["kind"] == "mount" and event["resolved_at_s"] is not None
    assert event["started_at_s"] >= KNOCK_S and event["detected_at_s"] - event["started_at_s"] <= 1.0
    assert abs(event["size"]["rotation_deg"] - 0.5) < 0.02           # a 0.5 deg knock
    assert event["size"]["translation_m"] < 1e-3                      # about the bracket: no shift
    assert f"t={event['detected_at_s']:.1f} s: change detected (mount or plane: cannot tell yet)" in printed
    # the first size comes from the few frames after the knock (0.4-0.5 deg), refined as the work shows more
    assert re.search(r"the mount moved: 0\.[45]\d\d deg", printed), printed
    assert "(its size is refined as the work shows more)" in printed


def test_the_knock_run_with_the_sims_errors_is_covered_by_its_intervals(knocked: Any) -> None:
    """The mount's intervals carry the camera's systematic allowance and the arm's accuracy (ADR 0055): they cover.

    The plane's offset is not covered: the sim arm's smooth pose-dependent error, amplified along the direction
    the work barely shows (the mount's z with the plane's offset: 3 mm), is beyond the arm's common part.
    """
    _code, _printed, doc, _rows = knocked
    iv = doc["intervals"]
    for i in range(3):
        lo, hi = iv["mount_translation_m"][i]
        assert lo <= TRUE_MOUNT_MM[i] / 1e3 <= hi
        lo, hi = iv["mount_rpy_deg"][i]
        assert lo <= TRUE_RPY_AFTER[i] <= hi
    assert 2e-3 < iv["mount_translation_m"][2][1] - iv["mount_translation_m"][2][0] < 30e-3  # wider than noise


def test_after_the_knock_the_mount_is_the_new_truth_within_its_intervals(knocked_ideal: Any) -> None:
    _code, _printed, doc, _rows = knocked_ideal
    mount, iv = doc["mount"], doc["intervals"]
    assert doc["schema"] == "cellcal.track/1" and not doc["change_unresolved"] and doc["unseen"] == []
    assert all(doc["observable"].values()) and iv["confidence"] == 0.95 and iv["withheld"] is None
    z = iv["z"]
    for i in range(3):
        assert abs(mount["translation_m"][i] * 1e3 - TRUE_MOUNT_MM[i]) < 1.0          # target 1 mm
        assert abs(mount["rpy_deg"][i] - TRUE_RPY_AFTER[i]) < 0.05                     # target 0.05 deg
        # one run: each error within 3 sigma of its own interval (the 95 % coverage itself is measured over
        # many runs in benchmarks/track_estimator.py), the intervals as narrow as the targets
        lo, hi = iv["mount_translation_m"][i]
        sigma = (hi - lo) / (2 * z)
        assert sigma == pytest.approx(mount["translation_sigma_m"][i], rel=1e-9) and hi - lo < 1e-3
        assert abs(mount["translation_m"][i] - TRUE_MOUNT_MM[i] / 1e3) < 4 * sigma
        lo, hi = iv["mount_rpy_deg"][i]
        sigma = (hi - lo) / (2 * z)
        assert sigma == pytest.approx(mount["rpy_sigma_deg"][i], rel=1e-9) and hi - lo < 0.05
        assert abs(mount["rpy_deg"][i] - TRUE_RPY_AFTER[i]) < 4 * sigma
    assert abs(doc["plane"]["offset_m"]) < 5e-4 and doc["plane"]["normal"][2] > 0.99999
    assert iv["noise_model"]["verdict"] in ("consistent", "scaled")


def test_frames_while_the_arm_moves_fast_are_skipped_and_counted(knocked: Any) -> None:
    _code, printed, doc, rows = knocked
    c = doc["counters"]
    assert c["frames"] == len(rows) == 901                       # 90 s at 10 fps, the first frame at 0
    assert c["accepted"] + c.get("held out", 0) + c["skipped: arm moving too fast"] \
        + c["skipped: arm turning too fast"] == c["frames"]
    assert c["skipped: arm moving too fast"] > 50 and c["accepted"] > 300
    skipped = [r for r in rows if r["note"] and r["note"].startswith("skipped")]
    assert len(skipped) == c["skipped: arm moving too fast"] + c["skipped: arm turning too fast"]
    assert all(set(r) == {"t_s", "index", "accepted", "note"} for r in skipped)
    used = [r for r in rows if r["accepted"]]
    assert all(len(r["residual"]) == 3 and r["chi2"] >= 0 for r in used)
    assert f"frames: 901, used {c['accepted']}, held out {c.get('held out', 0)}" in printed
    assert "the arm is read, never moved" in printed


def test_without_a_change_nothing_is_detected(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, printed, doc = _run(tmp_path, capsys, "--config", str(_variant(tmp_path, "")), "--duration", "40")
    assert code == 0 and doc["events"] == [] and "change detected" not in printed
    truth_before = (0.6, -0.7, 90.4)
    for i in range(3):
        assert abs(doc["mount"]["rpy_deg"][i] - truth_before[i]) < 0.05


def test_a_table_shift_is_told_apart_from_a_mount_change(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    events = "[[sim.events]]\nat_s = 30.0\nplane_point_m = [0.0, 0.0, 0.005]\nplane_normal = [0.0, 0.0, 1.0]\n"
    code, printed, doc = _run(tmp_path, capsys, "--config", str(_variant(tmp_path, events)), "--duration", "70")
    (event,) = doc["events"]
    assert event["kind"] == "plane" and abs(event["size"]["plane_shift_m"] - 0.005) < 5e-4
    # n.x + offset = 0 at z = 5 mm, within the 2-3 mm the sim arm's smooth error puts on the plane's offset (the
    # direction the work barely shows; test_the_knock_run_with_the_sims_errors_is_covered_by_its_intervals)
    assert code == 0 and abs(doc["plane"]["offset_m"] + 0.005) < 4e-3
    # printed as the table's height above the base origin: + 5 mm, not the offset's -5
    found = re.search(r"^plane \(base frame\): normal \[.*\], ([+-]\d+\.\d{3}) mm above the base origin$", printed,
                      re.M)
    assert found is not None and abs(float(found[1]) - 5.0) < 4.0, printed


def test_a_change_left_open_at_the_end_is_exit_1(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    events = ("[[sim.events]]\nat_s = 29.0\nmount_translation_m = [0.003, 0.045, 0.058]\n"
              "mount_rpy_deg = [1.1, -0.7, 90.4]\n")
    code, printed, doc = _run(tmp_path, capsys, "--config", str(_variant(tmp_path, events)), "--duration", "31",
                              "--apply")
    assert code == 1 and doc["change_unresolved"]
    assert "a change is open: the frames after it have not shown every parameter again" in printed
    assert "not applied: a change was detected and the frames after it have not shown every parameter again" \
        in printed
    assert not (tmp_path / "out" / "calibration.json").exists()


def test_apply_writes_a_versioned_file_the_mount_can_be_read_from(tmp_path: Path,
                                                                   capsys: pytest.CaptureFixture[str]) -> None:
    config = _variant(tmp_path, "")
    for version in (1, 2):
        code, printed, doc = _run(tmp_path, capsys, "--config", str(config), "--duration", "35", "--apply")
        path = tmp_path / "out" / "calibration.json"
        assert code == 0 and f"applied: {path} (version {version})" in printed
        applied = json.loads(path.read_text())
        assert applied["schema"] == "cellcal.track-calibration/1" and applied["version"] == version
        assert applied["mount"] == doc["mount"] and applied["plane"] == doc["plane"]
    old = json.loads((tmp_path / "out" / "history" / "calibration.v1.json").read_text())
    assert old["version"] == 1
    cell = tmp_path / "uses.toml"
    text = re.sub(r"translation_m = \[0\.0, 0\.04, 0\.06\]\nrpy_deg = \[0\.0, 0\.0, 90\.0\]",
                  f'from_handeye = "{path}"', config.read_text())
    cell.write_text(text)
    mount = load_config(cell).mount
    assert list(mount.translation_m) == pytest.approx(applied["mount"]["translation_m"], abs=1e-12)
    assert list(mount.rpy_deg) == pytest.approx(applied["mount"]["rpy_deg"], abs=1e-12)


def test_the_arm_is_read_and_never_commanded(tmp_path: Path) -> None:
    from cellcal.core.calibration.calibrator import build_devices
    from cellcal.core.track.run import ReadOnlyArm, TrackRun, device_clock
    from cellcal.devices.errors import SafetyError

    config = load_config(_variant(tmp_path, ""))
    camera, arm = build_devices(config)
    reader = ReadOnlyArm(arm)
    with camera, reader:
        outcome = TrackRun(config, camera, reader, out_dir=None, now=device_clock(camera)).run(max_frames=50)
        pose = reader.get_pose()
        for call in (lambda: reader.move_linear(pose, speed=0.01, acceleration=0.1), reader.stop,
                     reader.clear_errors):
            with pytest.raises(SafetyError, match="cellcal track reads the arm and never commands it"):
                call()
    assert arm.inner.moves_started == 0 and arm.inner.stops == 0 and outcome.counters["frames"] == 50


def test_a_replay_tracks_exactly_as_live(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("mcap")
    config = _variant(tmp_path, "")
    recording = tmp_path / "session.mcap"
    code, printed, live = _run(tmp_path, capsys, "--config", str(config), "--duration", "8", "--record",
                               str(recording))
    assert code == 0 and f"session recorded to {recording}" in printed
    rows_live = (tmp_path / "out" / "track.jsonl").read_text().splitlines()
    replay_out = tmp_path / "replay"
    assert main(["track", "--replay", str(recording), "--out", str(replay_out), "--duration", "8", "--quiet"]) == 0
    replayed = json.loads((replay_out / "track.json").read_text())
    for key in ("mount", "plane", "intervals", "observable", "events", "counters", "unseen"):
        assert replayed[key] == live[key], key
    rows_replay = (replay_out / "track.jsonl").read_text().splitlines()

    def strip(lines: list[str]) -> list[dict[str, Any]]:
        return [{k: v for k, v in json.loads(line).items() if k != "fit_ms"} for line in lines]

    assert strip(rows_replay) == strip(rows_live) and len(rows_live) == 81


def test_a_config_without_a_reference_plane_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = tmp_path / "cell.toml"
    config.write_text(re.sub(r"^\[reference\]\n(?:(?!\[).*\n)*", "", CONFIG.read_text(), flags=re.M))
    assert main(["track", "--config", str(config), "--duration", "1"]) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line.startswith(f"cellcal: error: {config}: key 'reference': ") and "a [reference] plane" in line


def test_ctrl_c_writes_both_files_whole_and_exits_130(tmp_path: Path) -> None:
    import time

    from fault_cells import CellcalProcess

    out = tmp_path / "out"
    partial = out / "track.jsonl.partial"
    with CellcalProcess(["track", "--duration", "100000", "--out", str(out), "--quiet"]) as run:
        deadline = time.monotonic() + 60.0
        while not (partial.exists() and partial.stat().st_size > 4096):     # a few flushes of rows, then Ctrl-C
            assert run.proc.poll() is None and time.monotonic() < deadline, run.stderr_so_far()
            time.sleep(0.05)
        run.interrupt()
        code, _stdout, err = run.finish(60.0)
    assert code == 130, err
    assert err == "" and not partial.exists()  # the summary goes to stdout: no line on stderr, so none run together
    doc = json.loads((out / "track.json").read_text())
    rows = [json.loads(line) for line in (out / "track.jsonl").read_text().splitlines()]
    assert doc["meta"]["interrupted"] is True and doc["counters"]["frames"] == len(rows) > 0


def test_ctrl_c_between_a_frames_count_and_its_row_still_leaves_them_equal(tmp_path: Path) -> None:
    import collections
    import signal

    from cellcal.core.calibration.calibrator import build_devices
    from cellcal.core.track.run import ReadOnlyArm, TrackRun, device_clock

    class InterruptAtThirdCount(collections.Counter[str]):
        """Ctrl-C arrives the moment the third frame is counted, before its row could be written."""

        def __setitem__(self, key: str, value: int) -> None:
            super().__setitem__(key, value)
            if key == "frames" and value == 3:
                signal.raise_signal(signal.SIGINT)

    config = load_config(_variant(tmp_path, ""))
    camera, arm = build_devices(config)
    out = tmp_path / "out"
    with camera, ReadOnlyArm(arm) as reader:
        session = TrackRun(config, camera, reader, out_dir=out, now=device_clock(camera))
        session.counters = InterruptAtThirdCount()
        outcome = session.run(max_frames=10)
    rows = (out / "track.jsonl").read_text().splitlines()
    assert outcome.interrupted and outcome.counters["frames"] == len(rows) == 3


def test_an_output_directory_that_cannot_be_written_is_one_line(tmp_path: Path,
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("")
    assert main(["track", "--duration", "1", "--out", str(blocker / "out")]) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line.startswith(f"cellcal: error: cannot write {blocker / 'out'}")


def test_a_device_failure_mid_run_leaves_the_earlier_files_as_they_were(tmp_path: Path,
                                                                        capsys: pytest.CaptureFixture[str]) -> None:
    from cellcal.core.calibration.calibrator import build_devices
    from cellcal.core.track.run import ReadOnlyArm, TrackRun, device_clock
    from cellcal.devices.errors import DeviceTimeoutError

    config_path = _variant(tmp_path, "")
    code, _printed, first = _run(tmp_path, capsys, "--config", str(config_path), "--duration", "5")
    out = tmp_path / "out"
    before = {name: (out / name).read_bytes() for name in ("track.json", "track.jsonl")}
    assert code == 0 and first["counters"]["frames"] == 51

    def fail_after_20(what: str, n: int) -> None:     # the camera stops answering at its 21st frame
        if what == "capture" and n > 20:
            raise DeviceTimeoutError("sim camera: no frame within 2 s")

    config = load_config(config_path)
    camera, arm = build_devices(config)
    camera.fault_hook = fail_after_20
    with camera, ReadOnlyArm(arm) as reader, pytest.raises(DeviceTimeoutError):
        TrackRun(config, camera, reader, out_dir=out, now=device_clock(camera)).run(duration_s=5.0)
    assert {name: (out / name).read_bytes() for name in before} == before      # the earlier pair, untouched
    partial = (out / "track.jsonl.partial").read_text().splitlines()
    assert len(partial) == 20                                                   # what the failed run saw
