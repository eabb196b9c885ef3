"""Record a calibration session to one MCAP file, and re-run it from the file alone (ADR 0009).

Replay builds the recorded configuration with the ``replay`` camera and arm backends
(:mod:`cellcal.drivers.replay`, found through the registry like any backend);
:func:`compare_with_recording` says whether the result equals the recorded one exactly.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from cellcal.core.calibration.calibrator import Calibrator, PoseObserver, ProgressFactory, build_devices
from cellcal.core.calibration.config import CellConfig, parse_config
from cellcal.core.calibration.outlock import OutputLock
from cellcal.devices.camera import Camera3D
from cellcal.devices.errors import RecordingFileError
from cellcal.devices.jsonsafe import json_safe
from cellcal.devices.recording import SessionRecorder, read_recording
from cellcal.devices.registry import Registry
from cellcal.devices.safety import SafeArm

__all__ = ["REPLAY_BACKEND", "VOLATILE_KEYS", "VOLATILE_POSE_KEYS", "compare_with_recording", "exact_part",
           "record", "recorded_devices", "replay_session", "run_recorded"]

#: Backend name of the replay camera and arm.
REPLAY_BACKEND = "replay"
#: Keys of the result document (top level / per pose) a replay need not reproduce: timing and
#: provenance. Everything else — poses, measurements, summary and any key added later — must be equal.
VOLATILE_KEYS = ("cellcal_version", "created_utc", "config_source", "timings_s")
VOLATILE_POSE_KEYS = ("timings_s",)


def record(config: CellConfig, out: str | Path, *, config_text: str | None = None, keep_failed: bool = False,
           registry: Registry | None = None, progress: ProgressFactory | None = None
           ) -> tuple[dict[str, Any], SessionRecorder]:
    """Run the plan of ``config`` with its devices behind a recorder writing ``out``.

    The backend arm is recorded inside the safety wrapper, so the file holds exactly
    what the backend was asked and answered. ``out`` is locked for the run
    (:meth:`OutputLock.for_file`): a second recording to the same file is refused.

    Args:
        config: The validated configuration.
        out: The MCAP file to write.
        config_text: The configuration's TOML text, stored for humans (None: not stored).
        keep_failed: Keep the recording of a failed run (with the error logged).
        registry: Where to find the backends; default: the process-wide one.
        progress: Optional factory ``total -> tqdm-like`` for a progress bar.

    Returns:
        The result document and the (closed) recorder, for its message counts.

    Raises:
        CellcalError: As :meth:`Calibrator.run`; the recording is then discarded, or
            finished with the error logged when ``keep_failed``. OutputError if another
            run holds ``out``.
        KeyboardInterrupt: The recording is finished with what was recorded (see
            :class:`SessionRecorder`).
    """
    camera, safe_arm = build_devices(config, registry)
    with OutputLock.for_file(out):
        recorder = SessionRecorder(out, config_document=config.document, config_source=config.source,
                                   config_text=config_text, keep_on_error=keep_failed)
        with recorder:
            document = run_recorded(config, recorder, camera, safe_arm, progress=progress)
    return document, recorder


def recorded_devices(recorder: SessionRecorder, camera: Camera3D, safe_arm: SafeArm) -> tuple[Camera3D, SafeArm]:
    """``camera`` and ``safe_arm`` behind ``recorder``: the backend arm recorded inside the safety wrapper."""
    return recorder.camera(camera), SafeArm(recorder.arm(safe_arm.inner), safe_arm.limits)


def run_recorded(config: CellConfig, recorder: SessionRecorder, camera: Camera3D, safe_arm: SafeArm, *,
                 progress: ProgressFactory | None = None, observer: PoseObserver | None = None) -> dict[str, Any]:
    """Run the plan of ``config`` on ``camera`` and ``safe_arm`` (:func:`build_devices`) behind ``recorder``.

    The backend arm is recorded inside the safety wrapper; the result is logged. The
    caller owns ``recorder`` (its ``with`` block decides what becomes of the file when
    this raises).

    Raises:
        CellcalError, KeyboardInterrupt: As :meth:`Calibrator.run`.
    """
    camera, arm = recorded_devices(recorder, camera, safe_arm)
    document = Calibrator(config, camera, arm, progress=progress, observer=observer).run()
    recorder.log_result(document)
    return document


def replay_session(path: str | Path, registry: Registry | None = None, *, strict: bool = True
                   ) -> tuple[CellConfig, Camera3D, SafeArm]:
    """The recorded configuration of ``path`` with the ``replay`` camera and arm in place of its devices.

    Args:
        path: A recording written by ``cellcal record``.
        registry: Where to find the ``replay`` backends; default: the process-wide one.
        strict: Arm calls must come in the recorded order (see :mod:`cellcal.drivers.replay`).

    Raises:
        RecordingFileError: If the file is missing, corrupt or holds no configuration.
        ConfigError: If the recorded configuration does not validate in this cellcal.
    """
    recording = read_recording(path)
    document = recording.config_document
    source = f"{path} (recorded config{f' of {recording.config_source}' if recording.config_source else ''})"
    if document is None:
        raise RecordingFileError("the recording holds no configuration document", source=str(path))
    config = parse_config(document, source)
    file = str(Path(path).resolve())
    camera, arm = build_devices(config, registry, source=str(path),
                                camera={"backend": REPLAY_BACKEND, "file": file},
                                arm={"backend": REPLAY_BACKEND, "file": file, "strict": strict})
    return config, camera, arm


def exact_part(document: dict[str, Any]) -> dict[str, Any]:
    """The part of a result document a replay reproduces exactly, strict-JSON cleaned."""
    part = {k: v for k, v in document.items() if k not in VOLATILE_KEYS}
    part["poses"] = [{k: v for k, v in p.items() if k not in VOLATILE_POSE_KEYS} for p in document.get("poses", [])]
    cleaned: dict[str, Any] = json_safe(part)
    return cleaned


def compare_with_recording(path: str | Path, document: dict[str, Any]) -> str:
    """One line saying whether ``document`` equals the result recorded in ``path`` exactly."""
    recorded = read_recording(path).result
    if not recorded or not recorded.get("ok") or not isinstance(recorded.get("result"), dict):
        return "replay: the recording holds no successful result to compare with"
    want, got = exact_part(recorded["result"]), exact_part(document)
    if want == got:
        n = sum(len(p.get("measurements", [])) for p in got["poses"])
        return f"replay: identical to the recorded result ({len(got['poses'])} poses, {n} measurements, summary)"
    for i, (a, b) in enumerate(zip(want["poses"], got["poses"], strict=False)):
        for key in sorted(set(a) | set(b)):
            if a.get(key) != b.get(key):
                return f"replay: DIFFERS from the recorded result at pose {i + 1}, '{key}'"
    keys = sorted(k for k in set(want) | set(got) if want.get(k) != got.get(k))
    return f"replay: DIFFERS from the recorded result: {', '.join(keys)}"
