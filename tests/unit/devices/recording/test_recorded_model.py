"""Recordings carry the camera's measurement model; replays state it and their frames carry it.

A format-1 recording (written before the model existed) still replays, as ``unknown``; a
malformed model in a recording (a user-supplied file) is refused in one line naming it.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from cellcal.devices import BackendContext, Camera3D, DeviceInfo, Frame, Intrinsics
from cellcal.devices.errors import RecordingError, RecordingFileError
from cellcal.devices.measurement import UNKNOWN_MODEL, MeasurementModel
from cellcal.devices.recording.codec import decode_frame, decode_model, encode_frame, encode_model

mcap_reader = pytest.importorskip("mcap.reader")
mcap_writer = pytest.importorskip("mcap.writer")

from cellcal.devices.recording import RECORDING_FORMAT, SessionRecorder, read_recording  # noqa: E402
from cellcal.drivers.replay import ReplayCamera  # noqa: E402

#: An OAK-D-like stereo model as a device states it: 75 mm baseline, 440 px, 3 fractional bits.
OAK_MODEL = MeasurementModel(kind="stereo", baseline_m=0.075, focal_px=440.0, subpixel_bits=3, source="device",
                             settings={"median": "KERNEL_7x7", "left_right_check": True})


class StereoToy(Camera3D):
    """16 x 12 px camera 0.7 m from a wall, stating ``model`` (the recorded camera)."""

    backend_name = "stereo-toy"
    model: MeasurementModel = OAK_MODEL

    @dataclass(frozen=True)
    class Config:
        wall_m: float = 0.7

    def __init__(self, config: Any = None, context: BackendContext | None = None) -> None:
        super().__init__()
        self._seq = 0

    def _connect(self, timeout: float) -> None:
        pass

    def _close(self) -> None:
        pass

    def _info(self) -> DeviceInfo:
        return DeviceInfo(backend="stereo-toy", vendor="Toy", model="S1")

    def _intrinsics(self) -> Intrinsics:
        return Intrinsics(16, 12, 440.0 * 16 / 640, 440.0 * 16 / 640, 7.5, 5.5)

    def _measurement_model(self) -> MeasurementModel:
        return self.model

    def _capture(self, timeout: float) -> Frame:
        intr = self._intrinsics()
        v, u = np.mgrid[0:intr.height, 0:intr.width].astype(np.float64)
        xyz = np.dstack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones_like(u)]) * 0.7
        self._seq += 1
        return Frame(np.linalg.norm(xyz, axis=2).astype(np.float32), xyz.astype(np.float32),
                     np.ones(intr.shape, np.float32), np.ones(intr.shape, bool), intr, 1.7e9 + self._seq, self._seq)


def record(path: Path, camera: Camera3D, captures: int = 2) -> Path:
    with SessionRecorder(path) as rec:
        cam = rec.camera(camera)
        with cam:
            for _ in range(captures):
                cam.capture(1.0)
    return path


def rewrite(src: Path, dst: Path, edit: Callable[[str, dict[str, Any]], dict[str, Any]]) -> Path:
    """Copy a recording message by message through ``edit(topic, payload)`` (schemas and channels kept)."""
    with src.open("rb") as fh_in, dst.open("wb") as fh_out:
        reader = mcap_reader.make_reader(fh_in)
        writer = mcap_writer.Writer(fh_out)
        writer.start()
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            if schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(channel.topic, channel.message_encoding,
                                                               schemas[schema.id])
            payload = edit(channel.topic, json.loads(message.data))
            writer.add_message(channels[channel.id], log_time=message.log_time, data=json.dumps(payload).encode(),
                               publish_time=message.publish_time, sequence=message.sequence)
        writer.finish()
    return dst


def as_format_1(topic: str, payload: dict[str, Any]) -> dict[str, Any]:
    """A message as cellcal wrote it before the model existed: no model anywhere, format 1."""
    payload = dict(payload)
    if topic == "/cellcal/session":
        payload["format"] = "cellcal.recording/1"
    payload.pop("measurement_model", None)
    if isinstance(payload.get("frame"), dict):
        payload["frame"] = {k: v for k, v in payload["frame"].items() if k != "measurement"}
    return payload


# ---------------------------------------------------------------- codec
def test_a_frame_round_trips_with_its_model() -> None:
    frame = StereoToy()._capture(1.0)
    stamped = Frame(**{**frame.__dict__, "measurement": OAK_MODEL})
    doc = encode_frame(stamped)
    assert doc["measurement"] == {"kind": "stereo", "baseline_m": 0.075, "focal_px": 440.0, "subpixel_bits": 3,
                                  "distance_exponent": 1.5, "multipath_m": 0.0, "range_step_m": 0.0,
                                  "source": "device", "settings": {"median": "KERNEL_7x7",
                                                                   "left_right_check": True}}
    back = decode_frame(json.loads(json.dumps(doc)))
    assert back.measurement == OAK_MODEL and back.measurement.settings == OAK_MODEL.settings
    assert back.measurement.fb_px_m == pytest.approx(33.0)
    # a frame with no model records no key, and decodes as unknown
    plain = encode_frame(frame)
    assert "measurement" not in plain and decode_frame(plain).measurement is UNKNOWN_MODEL


@pytest.mark.parametrize(("change", "key", "why"), [
    ({"baseline_m": 0.0}, "frame.measurement.baseline_m", "> 0"),
    ({"subpixel_bits": -1}, "frame.measurement.subpixel_bits", ">= 0"),
    ({"baseline": 0.075}, "frame.measurement.baseline", "unknown"),
    ({"kind": "lidar"}, "frame.measurement.kind", "lidar"),
])
def test_a_malformed_recorded_model_is_one_line_naming_the_key(change: dict[str, Any], key: str, why: str) -> None:
    doc = encode_frame(Frame(**{**StereoToy()._capture(1.0).__dict__, "measurement": OAK_MODEL}))
    doc["measurement"] = {**doc["measurement"], **change}
    with pytest.raises(RecordingError) as err:
        decode_frame(doc)
    message = str(err.value)
    assert "\n" not in message and f"'{key}'" in message and why in message
    with pytest.raises(RecordingError, match=r"frame\.measurement is a list, not an object"):
        decode_model([1], "frame.measurement")


def test_a_recorded_model_without_a_source_is_marked_as_from_the_recording() -> None:
    data = {k: v for k, v in encode_model(OAK_MODEL).items() if k != "source"}
    assert decode_model(data, "frame.measurement").source == "recording"
    assert decode_model(encode_model(OAK_MODEL), "frame.measurement").source == "device"
    assert decode_model(None, "frame.measurement") is UNKNOWN_MODEL


# ---------------------------------------------------------------- a session, recorded and replayed
def test_the_recording_holds_the_model_and_the_replay_states_it(tmp_path: Path) -> None:
    path = record(tmp_path / "s.mcap", StereoToy())
    recording = read_recording(path)
    assert recording.format == RECORDING_FORMAT == "cellcal.recording/2"
    (info,) = recording.camera_infos
    assert info["measurement_model"]["baseline_m"] == 0.075 and info["measurement_model"]["source"] == "device"
    assert all(c["frame"]["measurement"]["subpixel_bits"] == 3 for c in recording.captures)
    replay = ReplayCamera.from_config({"file": str(path)})
    assert replay.measurement_model == OAK_MODEL            # before connect too: it is in the file
    with replay:
        frames = [replay.capture(1.0) for _ in range(2)]
    assert all(f.measurement == OAK_MODEL for f in frames)
    assert frames[0].measurement.depth_step_m(0.7) == pytest.approx(0.49 / 33.0 / 8.0)


def test_the_config_override_is_what_is_recorded(tmp_path: Path) -> None:
    cam = StereoToy.from_config({"model": {"kind": "stereo", "baseline_m": 0.05, "focal_px": 400.0}})
    path = record(tmp_path / "s.mcap", cam, captures=1)
    with ReplayCamera.from_config({"file": str(path)}) as replay:
        frame = replay.capture(1.0)
        assert replay.measurement_model.source == "config" and replay.measurement_model.fb_px_m == pytest.approx(20.0)
    assert frame.measurement == replay.measurement_model and frame.measurement.subpixel_bits == 0


def test_a_format_1_recording_replays_as_unknown(tmp_path: Path) -> None:
    old = rewrite(record(tmp_path / "new.mcap", StereoToy()), tmp_path / "old.mcap", as_format_1)
    recording = read_recording(old)
    assert recording.format == "cellcal.recording/1"
    assert "measurement_model" not in recording.camera_infos[0]
    with ReplayCamera.from_config({"file": str(old)}) as replay:
        frame = replay.capture(1.0)
        assert replay.measurement_model is UNKNOWN_MODEL
    assert frame.measurement is UNKNOWN_MODEL and frame.valid.all()


def test_a_format_this_cellcal_does_not_know_is_refused(tmp_path: Path) -> None:
    def future(topic: str, payload: dict[str, Any]) -> dict[str, Any]:
        return {**payload, "format": "cellcal.recording/3"} if topic == "/cellcal/session" else payload

    bad = rewrite(record(tmp_path / "new.mcap", StereoToy(), captures=1), tmp_path / "future.mcap", future)
    with pytest.raises(RecordingFileError, match=r"'cellcal.recording/3' is not supported \(this cellcal reads "
                                                 r"'cellcal.recording/1', 'cellcal.recording/2'\)"):
        read_recording(bad)


def test_a_malformed_model_in_a_recording_is_refused_naming_file_and_key(tmp_path: Path) -> None:
    def zero_baseline(topic: str, payload: dict[str, Any]) -> dict[str, Any]:
        if topic == "/camera/info":
            return {**payload, "measurement_model": {**payload["measurement_model"], "baseline_m": 0}}
        return payload

    bad = rewrite(record(tmp_path / "new.mcap", StereoToy(), captures=1), tmp_path / "bad.mcap", zero_baseline)
    with pytest.raises(RecordingFileError) as err:
        ReplayCamera.from_config({"file": str(bad)})
    message = str(err.value)
    assert "\n" not in message and message.startswith(str(bad))
    assert "'camera_info.measurement_model.baseline_m'" in message and "> 0" in message

    def bad_frame(topic: str, payload: dict[str, Any]) -> dict[str, Any]:
        if topic == "/camera/capture":
            frame = payload["frame"]
            return {**payload, "frame": {**frame, "measurement": {**frame["measurement"], "subpixel_bits": -2}}}
        return payload

    bad = rewrite(record(tmp_path / "new2.mcap", StereoToy(), captures=1), tmp_path / "bad2.mcap", bad_frame)
    with ReplayCamera.from_config({"file": str(bad)}) as replay, pytest.raises(RecordingFileError) as err:
        replay.capture(1.0)
    assert "\n" not in str(err.value) and "'frame.measurement.subpixel_bits'" in str(err.value)
