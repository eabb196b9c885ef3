"""Recording a session to MCAP and replaying it: exact results, file layout, divergence and bad files."""

from __future__ import annotations

import json
import re
import signal
import sys
import tomllib
from collections.abc import Iterator
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fault_cells import interrupt
from mcap.reader import make_reader
from mcap.writer import Writer

from cellcal.core.calibration.calibrator import Calibrator, build_devices
from cellcal.core.calibration.config import parse_config
from cellcal.core.calibration.replay import exact_part, record, replay_session
from cellcal.core.cli import main
from cellcal.devices import (
    BackendContext,
    CellcalError,
    ConfigError,
    DeviceTimeoutError,
    MissingDependencyError,
    Registry,
    VendorError,
    default_registry,
)
from cellcal.devices.errors import RecordingError, RecordingFileError, ReplayExhaustedError, ReplayMismatchError
from cellcal.devices.recording import (
    CHANNELS,
    RECORDING_FORMAT,
    SessionRecorder,
    decode_error,
    decode_frame,
    decode_pose,
    encode_error,
    encode_frame,
    encode_pose,
    read_recording,
)
from cellcal.drivers.replay import ReplayArm, ReplayCamera
from cellcal.sims.arm import SimArm
from cellcal.sims.camera import SimCamera

SIM_DOC: dict[str, Any] = tomllib.loads(resources.files("cellcal.configs").joinpath("sim.toml").read_text())
N_POSES = len(SIM_DOC["plan"]["heights_m"])


def _with_replay(registry: Registry) -> Registry:
    """``registry`` with the replay backends (registered at run time unless the entry points provide them)."""
    for kind, cls in (("camera", ReplayCamera), ("arm", ReplayArm)):
        if "replay" not in registry.names(kind):  # type: ignore[arg-type]
            registry.register(kind, "replay", cls)  # type: ignore[arg-type]
    return registry


@pytest.fixture
def registry() -> Registry:
    return _with_replay(Registry())


@pytest.fixture
def cli_registry() -> Iterator[None]:
    """The process-wide registry knows ``replay`` for the CLI; restored afterwards."""
    reg = default_registry()
    added = [kind for kind in ("camera", "arm") if "replay" not in reg.names(kind)]  # type: ignore[arg-type]
    _with_replay(reg)
    yield
    for kind in added:
        reg.unregister(kind, "replay")  # type: ignore[arg-type]


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, Any], dict[str, int]]:
    """One recorded sim calibration: (file, in-memory result, messages written per topic)."""
    path = tmp_path_factory.mktemp("rec") / "session.mcap"
    document, recorder = record(parse_config(SIM_DOC, "<sim.toml>"), path)
    return path, document, dict(recorder.message_counts)


def run_replay(path: Path, registry: Registry, doc: dict[str, Any] | None = None, **kw: Any) -> dict[str, Any]:
    """Calibrate from a recording; ``doc`` replaces the recorded configuration (to change the plan)."""
    config, camera, arm = replay_session(path, registry, **kw)
    if doc is not None:
        config = parse_config(doc, "<modified>")
    return Calibrator(config, camera, arm).run()


# ---------------------------------------------------------------------------- exactness
def test_replay_reproduces_the_recorded_calibration_exactly(session: Any, registry: Registry) -> None:
    path, original, _ = session
    replayed = run_replay(path, registry)
    n = sum(len(p["measurements"]) for p in original["poses"])
    assert n >= N_POSES * 4 * 3 and len(replayed["poses"]) == N_POSES  # perimeters x methods (+ full frame)
    assert exact_part(replayed) == exact_part(original)
    # every measured number, compared as floats (NaN == NaN), not through JSON
    for a, b in zip(original["poses"], replayed["poses"], strict=True):
        for ma, mb in zip(a["measurements"], b["measurements"], strict=True):
            assert ma.keys() == mb.keys()
            for key, va in ma.items():
                if isinstance(va, float):
                    assert np.array_equal(va, mb[key], equal_nan=True), key
                else:
                    assert va == mb[key], key
    assert replayed["summary"] == original["summary"]
    assert replayed["config"] == original["config"]  # the recorded configuration, not the replay one
    # and the result stored inside the recording is the same too
    stored = read_recording(path).result
    assert stored is not None and stored["ok"] and exact_part(stored["result"]) == exact_part(original)


def test_frames_poses_and_errors_round_trip_bit_exact() -> None:
    camera, arm = SimCamera(), SimArm()
    with camera, arm:
        frame = camera.capture(2.0)
        pose = arm.get_pose(2.0)
    back = decode_frame(json.loads(json.dumps(encode_frame(frame))))
    for name in ("distance", "xyz", "amplitude", "valid", "confidence"):
        a, b = getattr(frame, name), getattr(back, name)
        assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes(), name
    assert np.isnan(back.distance).any() or back.valid.all()
    assert (back.timestamp, back.sequence, back.intrinsics) == (frame.timestamp, frame.sequence, frame.intrinsics)
    rng = np.random.default_rng(1)
    for _ in range(200):  # scipy's from_quat renormalises and would change last bits ~25 % of the time
        p = type(pose).from_xyz_rotvec(rng.normal(size=3), rng.normal(size=3))
        q = decode_pose(json.loads(json.dumps(encode_pose(p))))
        assert q.rotation.as_quat().tobytes() == p.rotation.as_quat().tobytes()
        assert q.translation.tobytes() == p.translation.tobytes()
    err = decode_error(json.loads(json.dumps(encode_error(VendorError("xarm", 31, "Collision")))))
    assert isinstance(err, VendorError) and (err.code, err.vendor, str(err)) == (31, "xarm", "xarm error 31: Collision")


# ---------------------------------------------------------------------------- file layout
def test_mcap_file_has_the_documented_channels_schemas_and_counts(session: Any) -> None:
    path, _, written = session
    rec = read_recording(path)
    methods = [c["method"] for c in rec.arm_calls]
    assert methods.count("move_linear") == N_POSES
    assert methods.count("get_pose") >= 1 + 2 * N_POSES  # start; per pose: the safety check and the read-back
    expected = {"/cellcal/session": 1, "/cellcal/result": 1, "/camera/info": 1, "/camera/calibration": 1,
                "/camera/capture": N_POSES, "/camera/depth": N_POSES, "/arm/info": 1, "/arm/call": len(methods),
                "/arm/flange_pose": methods.count("get_pose")}
    assert written == expected
    with path.open("rb") as fh:
        reader = make_reader(fh, validate_crcs=True)
        header, summary = reader.get_header(), reader.get_summary()
        assert summary is not None and header.library.startswith("cellcal ")
        topics = {ch.topic: (ch.message_encoding, summary.schemas[ch.schema_id]) for ch in summary.channels.values()}
        assert set(topics) == set(CHANNELS)
        for topic, (encoding, schema) in topics.items():
            assert encoding == "json" and schema.encoding == "jsonschema" and schema.name == CHANNELS[topic]
            assert json.loads(schema.data)["title"] == CHANNELS[topic]
        counts = {summary.channels[cid].topic: n for cid, n in summary.statistics.channel_message_counts.items()}
        assert counts == expected
        assert summary.statistics.message_count == sum(expected.values())
        meta = list(reader.iter_metadata())
        assert meta[0].name == "cellcal" and meta[0].metadata["format"] == RECORDING_FORMAT
        depth = [json.loads(m.data) for _, _, m in reader.iter_messages(topics=["/camera/depth"])]
        captures = [json.loads(m.data) for _, _, m in reader.iter_messages(topics=["/camera/capture"])]
    # the Foxglove image is the frame's distance, byte for byte
    frame = decode_frame(captures[0]["frame"])
    import base64

    img = depth[0]
    assert (img["encoding"], img["width"], img["height"], img["step"]) == ("32FC1", 224, 172, 4 * 224)
    assert base64.b64decode(img["data"]) == frame.distance.astype("<f4").tobytes()
    assert img["frame_id"] == "camera" and img["timestamp"]["sec"] == int(frame.timestamp)
    assert rec.config_document == SIM_DOC
    assert rec.message_counts == expected
    print(f"\nsim session: {path.stat().st_size} bytes, {sum(expected.values())} messages")


# ---------------------------------------------------------------------------- divergence
def _write_toml(path: Path, doc: dict[str, Any]) -> None:
    """A flat TOML file of ``doc`` (tables of scalars and arrays; JSON literals are valid TOML there)."""
    lines = []
    for table, values in doc.items():
        lines.append(f"[{table}]")
        lines += [f"{k} = {json.dumps(v)}" for k, v in values.items()]
    path.write_text("\n".join(lines) + "\n")


def _doc(**plan: Any) -> dict[str, Any]:
    doc = json.loads(json.dumps(SIM_DOC))
    doc["plan"].update(plan)
    return doc


def test_replay_with_another_plan_is_a_clear_error(session: Any, registry: Registry) -> None:
    path = session[0]
    with pytest.raises(ReplayMismatchError, match=r"move 1 goes to xyz=.*but the recorded session moved to"):
        run_replay(path, registry, _doc(heights_m=[0.5, 0.59, 0.61]))
    with pytest.raises(ReplayMismatchError, match=r"move 1 at speed 0.25 m/s, but the recorded session used 0.3"):
        run_replay(path, registry, _doc(speed_m_s=0.25))
    n_calls = len(read_recording(path).arm_calls)
    with pytest.raises(ReplayExhaustedError, match=rf"arm call {n_calls + 1} \(\w+\).*ends after {n_calls} arm calls"):
        run_replay(path, registry, _doc(heights_m=[0.46, 0.59, 0.61, 0.5]))
    with pytest.raises(ReplayMismatchError, match="capture 2 was recorded after move 2, but is asked for after move 1"):
        run_replay(path, registry, _doc(frames_per_pose=2))
    # without a replay arm to follow, the camera just runs out of frames
    camera = registry.create_camera({"backend": "replay", "file": str(path)}, BackendContext(section="camera"))
    with camera:
        for _ in range(N_POSES):
            camera.capture(1.0)
        with pytest.raises(ReplayExhaustedError, match=f"capture {N_POSES + 1} asked for, but the recording "
                                                        f"holds only {N_POSES} captures"):
            camera.capture(1.0)


def test_strict_order_and_lenient_queries(session: Any, registry: Registry) -> None:
    path = session[0]
    calls = read_recording(path).arm_calls
    move = next(i for i, c in enumerate(calls) if c["method"] == "move_linear")
    first_target = decode_pose(calls[move]["args"]["target"])
    recorded_after_move = decode_pose(next(c["result"] for c in calls[move:] if c["method"] == "get_pose"))
    section = {"backend": "replay", "file": str(path)}
    strict = registry.create_arm(section, BackendContext(section="arm"))
    with strict, pytest.raises(ReplayMismatchError, match=f"arm call 1 is move_linear, but the recorded "
                                                          f"session called {calls[0]['method']} there"):
        strict.move_linear(first_target, speed=0.3, acceleration=1.5)
    lenient = registry.create_arm({**section, "strict": False}, BackendContext(section="arm"))
    with lenient:
        first = lenient.get_pose()
        assert lenient.get_pose().translation.tobytes() == first.translation.tobytes()  # asked twice: same answer
        lenient.stop()  # not recorded: a no-op in lenient mode
        lenient.move_linear(first_target, speed=0.3, acceleration=1.5)
        assert lenient.get_pose().translation.tobytes() == recorded_after_move.translation.tobytes()
        with pytest.raises(ReplayMismatchError, match="the recording holds no joint_positions call"):
            lenient.joint_positions()


# ---------------------------------------------------------------------------- bad files
@pytest.mark.parametrize("keep", [0, 8, 100, 0.5, -9, -1])
def test_truncated_recording_is_a_one_line_error(session: Any, tmp_path: Path, keep: float) -> None:
    data = session[0].read_bytes()
    n = int(len(data) * keep) if isinstance(keep, float) else (keep if keep >= 0 else len(data) + keep)
    bad = tmp_path / "cut.mcap"
    bad.write_bytes(data[:n])
    with pytest.raises(RecordingFileError) as info:
        read_recording(bad)
    msg = str(info.value)
    assert "\n" not in msg and msg.startswith(f"{bad}: not a")
    assert ("truncated or corrupt" in msg) if n >= 8 else ("not an MCAP file" in msg)


def test_corrupt_and_foreign_files(session: Any, tmp_path: Path) -> None:
    data = bytearray(session[0].read_bytes())
    data[len(data) // 2] ^= 0xFF  # inside a compressed chunk: CRC or decompression fails
    bad = tmp_path / "flip.mcap"
    bad.write_bytes(bytes(data))
    with pytest.raises(RecordingFileError, match="truncated or corrupt"):
        read_recording(bad)
    toml = tmp_path / "cell.toml"
    toml.write_text("[cell]\n")
    with pytest.raises(RecordingFileError, match=r"cell\.toml: not an MCAP file"):
        read_recording(toml)
    foreign = tmp_path / "other.mcap"
    with foreign.open("wb") as fh:  # a valid MCAP file written by someone else
        w = Writer(fh)
        w.start()
        ch = w.register_channel("/x", "json", w.register_schema("x", "jsonschema", b"{}"))
        w.add_message(ch, log_time=1, data=b"{}", publish_time=1)
        w.finish()
    with pytest.raises(RecordingFileError, match="no /cellcal/session message: not a cellcal recording"):
        read_recording(foreign)


def test_missing_file(tmp_path: Path, registry: Registry) -> None:
    with pytest.raises(RecordingFileError, match=r"nope\.mcap: recording not found"):
        read_recording(tmp_path / "nope.mcap")
    # relative paths in a replay config resolve from the config file's directory
    ctx = BackendContext(source=str(tmp_path / "cell.toml"), section="camera")
    with pytest.raises(ConfigError, match=re.escape(f"{tmp_path}/nope.mcap: recording not found")):
        registry.create_camera({"backend": "replay", "file": "nope.mcap"}, ctx)
    with pytest.raises(ConfigError, match=r"key 'camera\.file': missing required value"):
        registry.create_camera({"backend": "replay"}, ctx)


def test_missing_mcap_is_a_missing_dependency(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    for name in ("mcap", "mcap.reader", "mcap.writer"):
        monkeypatch.setitem(sys.modules, name, None)
    with pytest.raises(MissingDependencyError, match=r"pip install 'cellcal\[record\]'"):
        SessionRecorder(tmp_path / "x.mcap")
    with pytest.raises(MissingDependencyError, match="mcap"):
        read_recording(tmp_path / "x.mcap")


# ---------------------------------------------------------------------------- failures while recording
def _arm_fault_at_move(camera: Any, arm: Any, move: int) -> None:
    sim = arm.inner

    def hook(what: str, n: int) -> None:
        if what == "move" and n == move:
            sim.set_error(31)

    sim.fault_hook = hook


def test_recorder_leaves_no_file_when_the_session_fails(tmp_path: Path) -> None:
    out = tmp_path / "rec" / "s.mcap"
    with pytest.raises(RuntimeError), SessionRecorder(out, config_document=SIM_DOC):
        raise RuntimeError("boom")
    assert list(out.parent.iterdir()) == []
    # a failing calibration: nothing under the final name, no temp file, an earlier recording untouched
    out.write_bytes(b"earlier recording")
    config = parse_config(SIM_DOC, "<sim>")
    camera, arm = build_devices(config)
    _arm_fault_at_move(camera, arm, 2)
    with pytest.raises(VendorError, match="31"), SessionRecorder(out, config_document=SIM_DOC) as rec:
        Calibrator(config, rec.camera(camera), type(arm)(rec.arm(arm.inner), arm.limits)).run()
    assert [p.name for p in out.parent.iterdir()] == ["s.mcap"] and out.read_bytes() == b"earlier recording"
    with pytest.raises(RecordingError, match="is closed"):
        rec.log_result({})
    # a destination that cannot be written: a one-line error and nothing left
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(RecordingError, match="cannot write"):
        SessionRecorder(blocker / "s.mcap")


def test_a_kept_failed_run_replays_to_the_same_error(tmp_path: Path, registry: Registry) -> None:
    out = tmp_path / "failed.mcap"
    config = parse_config(SIM_DOC, "<sim>")
    camera, arm = build_devices(config)
    _arm_fault_at_move(camera, arm, 2)
    with pytest.raises(VendorError) as original, \
            SessionRecorder(out, config_document=SIM_DOC, keep_on_error=True) as rec:
        Calibrator(config, rec.camera(camera), type(arm)(rec.arm(arm.inner), arm.limits)).run()
    stored = read_recording(out)
    assert stored.result is not None and not stored.result["ok"]
    assert stored.result["error"]["type"] == "VendorError" and [c["method"] for c in stored.arm_calls][-1] == "stop"
    with pytest.raises(VendorError) as replayed:
        run_replay(out, registry)
    assert (replayed.value.code, str(replayed.value)) == (original.value.code, str(original.value))


def test_recorded_capture_errors_replay_as_the_same_type(tmp_path: Path, registry: Registry) -> None:
    camera = SimCamera()
    calls: list[str] = []

    def hook(what: str, n: int) -> None:
        calls.append(what)
        if calls.count("capture") == 2 and what == "capture":
            raise DeviceTimeoutError("sim camera: no frame within 1 s")

    camera.fault_hook = hook
    path = tmp_path / "cam.mcap"
    with SessionRecorder(path) as rec, rec.camera(camera) as cam, rec.arm(SimArm()) as _arm:
        first = cam.capture(1.0)
        with pytest.raises(DeviceTimeoutError):
            cam.capture(1.0)
        third = cam.capture(1.0)
    replay = registry.create_camera({"backend": "replay", "file": str(path)}, BackendContext(section="camera"))
    with replay:
        assert replay.capture(1.0).distance.tobytes() == first.distance.tobytes()
        with pytest.raises(DeviceTimeoutError, match="no frame within 1 s"):
            replay.capture(1.0)
        assert replay.capture(1.0).sequence == third.sequence
        with pytest.raises(ReplayExhaustedError):
            replay.capture(1.0)


# ---------------------------------------------------------------------------- device contract
def _sim(kind: str) -> Any:
    ctx = BackendContext(source="<sim.toml>", section=kind, document=SIM_DOC, shared={}, seed=3)
    cls = SimCamera if kind == "camera" else SimArm
    return cls.from_config({**SIM_DOC[kind], "backend": "sim"}, ctx)


def _kit_rule(kit: Any, kind: str, rule: str, tmp_path: Path, registry: Registry) -> None:
    """Run one kit rule on recording wrappers around the sim, then on the replay of exactly those sessions."""
    check = kit.check_camera if kind == "camera" else kit.check_arm
    recorders: list[SessionRecorder] = []

    def recording() -> Any:
        rec = SessionRecorder(tmp_path / f"{rule}-{len(recorders)}.mcap")
        recorders.append(rec)
        return rec.camera(_sim(kind)) if kind == "camera" else rec.arm(_sim(kind))

    # the sim camera, with no plan, sees the table straight below it, 0.44 m away
    options = kit.CameraOptions(scene_plane=kit.ScenePlane((0.0, 0.0, 1.0), 0.44)) if kind == "camera" else None
    report = check(recording, options, only=[rule], raise_on_failure=False)
    for bad in report.failures:  # the only two rules a wrapper breaks, for the expected reason:
        if rule.endswith(".factory"):  # it is not a config-built backend class (no backend_name, no Config)
            assert "backend_name must be" in bad.detail or "Config must be" in bad.detail, bad.message
        else:  # the recorder's file, owned by the test, is open
            assert rule.endswith(".releases-resources") and ".mcap." in bad.detail, bad.message
    for rec in recorders:
        rec.close()
    made: list[int] = []

    def replay() -> Any:
        made.append(len(made))
        path = tmp_path / f"{rule}-{made[-1]}.mcap"
        return registry.create(kind, {"backend": "replay", "file": str(path)},  # type: ignore[arg-type]
                               BackendContext(section=kind))

    check(replay, options, only=[rule])
    assert len(made) == len(recorders), rule  # one replayed device per recorded one


@pytest.mark.parametrize("kind", ["camera", "arm"])
def test_recording_and_replay_backends_pass_the_conformance_kit(kind: str, tmp_path: Path,
                                                                registry: Registry) -> None:
    kit = pytest.importorskip("cellcal.testing")
    rules = kit.CAMERA_RULES if kind == "camera" else kit.ARM_RULES
    assert len(rules) >= 10
    for rule in rules:
        _kit_rule(kit, kind, rule, tmp_path, registry)


# ---------------------------------------------------------------------------- CLI
def test_cli_record_then_calibrate_replay(tmp_path: Path, cli_registry: None,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "s.mcap"
    assert main(["record", "--out", str(out), "--result", str(tmp_path / "orig"), "--quiet"]) == 0
    assert f"recording written to {out}" in capsys.readouterr().out
    assert main(["calibrate", "--replay", str(out), "--out", str(tmp_path / "again"), "--quiet"]) == 0
    n = sum(len(p["measurements"]) for p in json.loads((tmp_path / "orig" / "result.json").read_text())["poses"])
    assert f"replay: identical to the recorded result (3 poses, {n} measurements, summary)" in capsys.readouterr().out
    a = json.loads((tmp_path / "orig" / "result.json").read_text())
    b = json.loads((tmp_path / "again" / "result.json").read_text())
    assert exact_part(a) == exact_part(b) and a["summary"] == b["summary"]
    assert main(["calibrate", "--replay", str(out), "--config", "x.toml"]) == 2
    assert "drop --config" in capsys.readouterr().err
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(out.read_bytes()[:1000])
    assert main(["calibrate", "--replay", str(cut), "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "cut.mcap: not a readable MCAP recording" in err
    assert main(["calibrate", "--replay", str(tmp_path / "none.mcap")]) == 2
    assert "none.mcap: recording not found" in capsys.readouterr().err


def test_replay_entry_points_when_declared() -> None:
    names = {(e.kind, e.name): e.target for e in Registry().entries()}
    if ("camera", "replay") not in names:
        pytest.skip("pyproject.toml does not declare the replay entry points yet")
    assert names[("camera", "replay")] == "cellcal.drivers.replay.camera:ReplayCamera"
    assert names[("arm", "replay")] == "cellcal.drivers.replay.arm:ReplayArm"
    assert Registry().get("camera", "replay") is ReplayCamera and Registry().get("arm", "replay") is ReplayArm


def test_replay_config_reanalyses_a_recording_with_other_methods(session: Any, tmp_path: Path,
                                                                 cli_registry: None) -> None:
    """A hand-written config: replay backends (file relative to it), same plan, other perimeters and methods."""
    path, original, _ = session
    (tmp_path / "s.mcap").write_bytes(path.read_bytes())
    doc = json.loads(json.dumps(SIM_DOC))
    doc["camera"] = {"backend": "replay", "file": "s.mcap"}
    doc["arm"] = {"backend": "replay", "file": "s.mcap"}
    doc["plan"].update(perimeters_px=[30], methods=["plane_fit"])
    _write_toml(tmp_path / "replay.toml", doc)
    assert main(["calibrate", "--config", str(tmp_path / "replay.toml"), "--out", str(tmp_path / "o"), "--quiet"]) == 0
    result = json.loads((tmp_path / "o" / "result.json").read_text())
    rows = [m for p in result["poses"] for m in p["measurements"] if m["method"] == "plane_fit"]
    want = [m for p in original["poses"] for m in p["measurements"]
            if m["method"] == "plane_fit" and m["perimeter_px"] == 30]
    assert len(rows) == N_POSES and [r["angle_deg"] for r in rows] == [w["angle_deg"] for w in want]


def test_random_byte_flips_are_caught_or_harmless(session: Any, tmp_path: Path) -> None:
    """Any single flipped byte: a one-line RecordingFileError, or (outside the data) the same content."""
    data = session[0].read_bytes()
    good = read_recording(session[0])
    rng = np.random.default_rng(9)
    outcomes = {"error": 0, "same": 0}
    for pos in rng.integers(0, len(data), size=40):
        bad = bytearray(data)
        bad[pos] ^= 1 << int(rng.integers(0, 8))
        path = tmp_path / "flip.mcap"
        path.write_bytes(bytes(bad))
        try:
            rec = read_recording(path)
        except RecordingFileError as exc:
            assert "\n" not in str(exc)
            outcomes["error"] += 1
            continue
        assert (rec.session, rec.captures, rec.arm_calls, rec.result) == \
            (good.session, good.captures, good.arm_calls, good.result), f"flip at byte {pos} changed the content"
        outcomes["same"] += 1
    assert outcomes["error"] > 0
    print(f"\n40 single-bit flips: {outcomes}")


def test_cli_record_of_a_rejected_plan_is_discarded_unless_kept(tmp_path: Path,
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    doc = json.loads(json.dumps(SIM_DOC))
    doc["safety"]["max_speed_m_s"] = 0.1  # below the plan's 0.3 m/s: rejected before the first move
    _write_toml(tmp_path / "cell.toml", doc)
    out = tmp_path / "rec" / "s.mcap"
    args = ["record", "--config", str(tmp_path / "cell.toml"), "--out", str(out), "--quiet"]
    assert main(args) == 1 and "speed 0.3 m/s exceeds max 0.1 m/s" in capsys.readouterr().err
    assert not out.parent.exists()  # no recording, no temp file, no lock file: nothing (not even its directory)
    assert main([*args, "--keep-failed"]) == 1
    assert f"recording of the failed run written to {out}" in capsys.readouterr().err
    kept = read_recording(out)
    assert kept.result is not None and not kept.result["ok"] and kept.result["error"]["type"] == "SafetyError"
    assert [p.name for p in out.parent.iterdir()] == ["s.mcap"]


# ---------------------------------------------------------------------------- Ctrl-C while recording
INTERRUPTED = {"type": "KeyboardInterrupt", "message": "interrupted (Ctrl-C)", "attrs": {}}


@pytest.mark.parametrize("keep_failed", [False, True])
def test_an_interrupted_recording_is_finished_with_what_was_recorded(tmp_path: Path, registry: Registry,
                                                                     keep_failed: bool) -> None:
    """Ctrl-C (a real SIGINT) while the last pose's frame is taken: a valid file, with the capture it cut short."""
    config = parse_config(SIM_DOC, "<sim.toml>")
    out = tmp_path / "s.mcap"
    out.write_bytes(b"an earlier recording")
    camera, arm = build_devices(config)
    camera.fault_hook = lambda what, n: interrupt() if (what, n) == ("capture", N_POSES) else None
    with pytest.raises(KeyboardInterrupt), \
            SessionRecorder(out, config_document=SIM_DOC, keep_on_error=keep_failed) as rec:
        Calibrator(config, rec.camera(camera), type(arm)(rec.arm(arm.inner), arm.limits)).run()
    assert rec.finished and rec.finish_error is None
    stored = read_recording(out)  # summary, chunk indexes, CRCs: all checked
    assert stored.result == {"ok": False, "result": None, "error": INTERRUPTED}
    assert [c["error"] for c in stored.captures] == [None] * (N_POSES - 1) + [INTERRUPTED]
    assert [c["method"] for c in stored.arm_calls][-1] == "stop"
    assert [p.name for p in tmp_path.iterdir()] == ["s.mcap"]
    # the replay re-runs the recorded part and stops where the session was interrupted
    with pytest.raises(CellcalError, match="KeyboardInterrupt: interrupted"):
        run_replay(out, registry)


@pytest.mark.parametrize("at_message", [1, 2, 5, 9])
def test_ctrl_c_inside_the_mcap_writer_waits_for_the_message_to_be_written(tmp_path: Path,
                                                                            at_message: int) -> None:
    """A SIGINT that arrives half-way through a write is delivered right after it, never inside it."""
    out = tmp_path / "s.mcap"
    rec = SessionRecorder(out, config_document=SIM_DOC)
    real_add = rec._writer.add_message
    calls = {"n": 0, "written": 0}

    def add_message(**kwargs: Any) -> None:
        calls["n"] += 1
        if calls["n"] == at_message:
            interrupt_now()  # the handler runs at the next bytecode: inside this write unless held back
        real_add(**kwargs)
        calls["written"] += 1

    rec._writer.add_message = add_message  # type: ignore[method-assign]
    with pytest.raises(KeyboardInterrupt), rec:
        for i in range(12):
            rec.log("/arm/flange_pose", {"timestamp": {"sec": i, "nsec": 0}, "frame_id": "base",
                                         "pose": {"position": {"x": 0, "y": 0, "z": 0},
                                                  "orientation": {"x": 0, "y": 0, "z": 0, "w": 1}}})
    assert calls["written"] == calls["n"]  # every write that started, finished
    stored = read_recording(out)
    assert stored.message_counts["/arm/flange_pose"] == at_message  # the one it arrived in, and no later one
    assert stored.result == {"ok": False, "result": None, "error": INTERRUPTED}


def interrupt_now() -> None:
    """SIGINT to this process, returning (Python raises KeyboardInterrupt at its next check)."""
    signal.raise_signal(signal.SIGINT)
