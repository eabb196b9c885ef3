"""The cell's other cameras captured at each pose of ``calibrate``: together or alone, failures, Ctrl-C (ADR 0061).

Runs configs/sim_multi.toml's plan (3 poses, the simulated arm 1000x faster than real time) with the
calibrator's companion hook, as ``cellcal calibrate`` does. No assertion on how long anything takes:
the order of the captures is read from their start and end times, which the code takes in sequence.
"""

from __future__ import annotations

import contextlib
import threading
import tomllib
from pathlib import Path
from typing import Any

import pytest
from fuzz_targets import dump_toml

from cellcal.core.calibration.build import build_cell
from cellcal.core.calibration.calibrator import Calibrator
from cellcal.core.calibration.cell_capture import OtherCameras
from cellcal.core.calibration.config import parse_config
from cellcal.core.cli import main
from cellcal.devices.errors import DeviceTimeoutError

MULTI = Path(__file__).resolve().parents[3] / "configs" / "sim_multi.toml"


def _document(modes: dict[str, str] | None = None) -> dict[str, Any]:
    """configs/sim_multi.toml with ``capture`` set per camera name."""
    document = tomllib.loads(MULTI.read_text(encoding="utf-8"))
    for entry in document["cameras"]:
        if modes and entry["name"] in modes:
            entry["capture"] = modes[entry["name"]]
    return document


def _run(document: dict[str, Any], hooks: dict[str, Any] | None = None,
         arm_calls: list[str] | None = None) -> tuple[dict[str, Any], OtherCameras]:
    """One calibrate run of the cell's plan with every other camera captured; (driven result, the others)."""
    config = parse_config(document, str(MULTI))
    cameras, arm = build_cell(config)
    driven = cameras.pop(config.camera_name)
    for name, hook in (hooks or {}).items():
        cameras[name].fault_hook = hook  # type: ignore[attr-defined]
    if arm_calls is not None:
        stop = arm.stop

        def spy(timeout: float | None = None) -> None:
            arm_calls.append("stop")
            stop(timeout)

        arm.stop = spy  # type: ignore[method-assign]
    others = OtherCameras(config, cameras)
    calibrator = Calibrator(config, driven, arm, observer=others, companion=others)
    with contextlib.ExitStack() as stack:
        others.connect(stack)
        document = calibrator.run()
    return document, others


def _capture_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name.startswith("cellcal capture")]


def test_together_cameras_start_before_the_driven_one_ends_and_alone_ones_after_them() -> None:
    driven, others = _run(_document({"side45": "alone"}))
    capture = {p["index"]: p["timings_s"]["capture"] for p in driven["poses"]}
    above, side = others.poses["above"], others.poses["side45"]
    assert [p["index"] for p in above] == [p["index"] for p in side] == sorted(capture)
    for a, s in zip(above, side, strict=True):
        assert a["capture"] == "together" and s["capture"] == "alone"
        # 'above' started with the driven camera: before its capture (timed from the settle) was over
        assert 0.0 <= a["started_s"] < capture[a["index"]] and a["started_s"] <= a["ended_s"] == a["after_s"]
        # 'side45' only once the together cameras (the driven one and 'above') were done
        assert s["started_s"] >= max(a["ended_s"], capture[s["index"]])
        assert isinstance(a["timestamp"], float) and isinstance(s["timestamp"], float)
        assert "full_frame" in a and "full_frame" in s
    assert others.capture_document()["together"] == ["wrist", "above"]
    assert others.capture_document()["alone"] == ["side45"]
    assert _capture_threads() == []


def test_every_camera_alone_captures_one_after_the_other() -> None:
    driven, others = _run(_document({"wrist": "alone", "above": "alone", "side45": "alone"}))
    capture = {p["index"]: p["timings_s"]["capture"] for p in driven["poses"]}
    for a, s in zip(others.poses["above"], others.poses["side45"], strict=True):
        assert a["started_s"] >= capture[a["index"]]  # after the driven camera
        assert s["started_s"] >= a["ended_s"]         # and after each other, in the configuration's order
    assert others.capture_document()["together"] == [] and not others.driven_together


def test_a_camera_that_times_out_at_one_pose_has_that_error_and_the_run_completes(tmp_path: Path) -> None:
    failed: list[int] = []

    def hook(event: str, n: int) -> None:
        if event == "capture" and n == 2 and not failed:  # once: a failed capture does not count itself
            failed.append(n)
            raise DeviceTimeoutError("camera backend 'sim': capture(timeout=2 s) timed out")

    driven, others = _run(_document(), {"above": hook})
    above = others.poses["above"]
    assert len(driven["poses"]) == len(above) == 3
    assert "full_frame" not in above[1] and "capture failed: camera backend 'sim': capture" in above[1]["error"]
    assert all("full_frame" in p for i, p in enumerate(above) if i != 1)
    assert all("full_frame" in p for p in others.poses["side45"])
    others.write(tmp_path, None, None)
    import json

    written = json.loads((tmp_path / "result-above.json").read_text(encoding="utf-8"))
    assert written["failed_poses"] == [1] and written["summary"]["plane_consistency"]["n_poses"] == 2
    assert written["capture"]["together"] == ["wrist", "above", "side45"]


def test_a_capture_that_overruns_its_guard_is_abandoned_at_its_deadline() -> None:
    document = _document()
    document["plan"]["capture_timeout_s"] = 0.2
    release = threading.Event()
    blocked: list[int] = []

    def hook(event: str, n: int) -> None:
        if event == "capture" and n == 2 and not blocked:  # the second capture only (it never counts itself)
            blocked.append(n)
            release.wait(10.0)  # a backend ignoring its timeout (released at the end of the test)

    config = parse_config(document, str(MULTI))
    cameras, arm = build_cell(config)
    driven = cameras.pop(config.camera_name)
    cameras["side45"].fault_hook = hook  # type: ignore[attr-defined]
    others = OtherCameras(config, cameras)
    others.guards["side45"].grace_s = 0.05   # allowance 0.25 s, the hook blocks 10 s
    try:
        with contextlib.ExitStack() as stack:
            others.connect(stack)
            Calibrator(config, driven, arm, observer=others, companion=others).run()
    finally:
        release.set()
    side = others.poses["side45"]
    assert "did not return within 0.25 s" in side[1]["error"] and "full_frame" in side[2]
    assert _capture_threads() == []  # our worker was joined; the backend's own call is the guard's


def test_ctrl_c_in_a_companion_capture_propagates_and_stops_the_arm() -> None:
    def hook(event: str, n: int) -> None:
        if event == "capture" and n == 2:
            raise KeyboardInterrupt

    calls: list[str] = []
    with pytest.raises(KeyboardInterrupt):
        _run(_document(), {"side45": hook}, arm_calls=calls)
    assert calls == ["stop"] and _capture_threads() == []


def test_a_capture_mode_that_does_not_exist_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = tmp_path / "cell.toml"
    config.write_text(dump_toml(_document({"above": "sometimes"})), encoding="utf-8")
    assert main(["calibrate", "--check", "--config", str(config)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cameras[1].capture" in err[0] and "'together'" in err[0], err
