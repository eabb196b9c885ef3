"""``--record`` / ``--replay`` of a fixed camera's run: its session in one MCAP file, re-run from the file alone.

The recording is the flange camera's (:class:`~cellcal.devices.recording.SessionRecorder`; the
backend arm recorded inside the safety wrapper, :func:`~cellcal.core.calibration.replay.recorded_devices`):
the configuration, the fixed camera's frames (its view of the measuring plane before the first move,
then one set per plate pose), every arm call and the result. The configuration recorded is the
cell's document with ``[[cameras]]`` holding the camera the run drove alone, as it was written
(its ``[cameras.pose]`` as given, so the replayed plan is the recorded one to the last bit): read
back with ``allow_fixed`` it selects that camera (:func:`fixed_replay_session`). Poses in the base
frame, metres, radians (ADR 0009, ADR 0061).
"""

from __future__ import annotations

import copy
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from cellcal.core.calibration.build import build_devices
from cellcal.core.calibration.config import CellConfig, parse_config
from cellcal.core.calibration.replay import REPLAY_BACKEND, exact_part
from cellcal.devices.camera import Camera3D
from cellcal.devices.errors import ConfigError, RecordingFileError
from cellcal.devices.recording import read_recording
from cellcal.devices.registry import Registry
from cellcal.devices.safety import SafeArm

__all__ = ["compare_fixed_with_recording", "fixed_replay_session", "recorded_fixed_document", "records_fixed_camera"]


def recorded_fixed_document(document: Mapping[str, Any], name: str) -> dict[str, Any]:
    """The configuration a fixed camera's recording holds: ``document`` with ``[[cameras]]`` = camera ``name`` alone.

    Args:
        document: The cell's configuration as read (its ``[[cameras]]`` with every camera).
        name: The fixed camera the run drives.

    Raises:
        ConfigError: ``document`` has no fixed camera ``name`` in its ``[[cameras]]``.
    """
    listed = document.get("cameras")
    entry = next((c for c in listed if isinstance(c, Mapping) and c.get("name") == name), None) \
        if isinstance(listed, list) else None
    if entry is None or entry.get("on") != "base":
        raise ConfigError(f"the configuration has no fixed camera {name!r} in its [[cameras]]", key="cameras")
    out = {k: copy.deepcopy(v) for k, v in document.items() if k != "cameras"}
    out["cameras"] = [copy.deepcopy(dict(entry))]
    return out


def _recorded_config(path: str | Path) -> tuple[CellConfig, Any]:
    """The recording of ``path`` and its configuration parsed with a fixed camera allowed.

    Raises:
        RecordingFileError: Missing, corrupt, or without a configuration document.
        ConfigError: The recorded configuration does not validate in this cellcal.
    """
    recording = read_recording(path)
    document = recording.config_document
    if document is None:
        raise RecordingFileError("the recording holds no configuration document", source=str(path))
    source = f"{path} (recorded config{f' of {recording.config_source}' if recording.config_source else ''})"
    return parse_config(document, source, allow_fixed=True), recording


def records_fixed_camera(path: str | Path) -> bool:
    """Whether ``path`` is the recording of a fixed camera's run (its configuration runs an ``on = "base"`` camera).

    Raises:
        RecordingFileError: Missing, corrupt, or without a configuration document.
    """
    try:
        config, _ = _recorded_config(path)
    except ConfigError:
        return False          # replay_session says what is wrong with it
    return config.camera_entry.on == "base"


def fixed_replay_session(path: str | Path, registry: Registry | None = None, *, strict: bool = True
                         ) -> tuple[CellConfig, Camera3D, SafeArm]:
    """The recorded fixed camera's configuration with the ``replay`` camera and arm in place of its devices.

    Args:
        path: A recording of ``cellcal handeye --camera NAME --record`` for a fixed camera.
        registry: Where to find the ``replay`` backends; default: the process-wide one.
        strict: Arm calls must come in the recorded order (see :mod:`cellcal.drivers.replay`).

    Raises:
        RecordingFileError: Missing, corrupt, without a configuration, or not a fixed camera's recording.
        ConfigError: The recorded configuration does not validate in this cellcal.
    """
    config, _ = _recorded_config(path)
    if config.camera_entry.on != "base":
        raise RecordingFileError(f"the recording runs camera {config.camera_name!r} on the flange, not a fixed one",
                                 source=str(path))
    file = str(Path(path).resolve())
    camera, arm = build_devices(config, registry, source=str(path),
                                camera={"backend": REPLAY_BACKEND, "file": file},
                                arm={"backend": REPLAY_BACKEND, "file": file, "strict": strict})
    return config, camera, arm


def compare_fixed_with_recording(path: str | Path, document: Mapping[str, Any]) -> str:
    """One line saying whether a fixed camera's result equals the one recorded in ``path`` exactly.

    Everything but provenance and timing (:data:`~cellcal.core.calibration.replay.VOLATILE_KEYS`) must be
    equal: the camera's pose and covariance, the plate, every residual, the measuring plane's view.
    """
    recorded = read_recording(path).result
    if not recorded or not recorded.get("ok") or not isinstance(recorded.get("result"), dict):
        return "replay: the recording holds no successful result to compare with"
    want, got = exact_part(recorded["result"]), exact_part(dict(document))
    n = len(got.get("residuals") or [])
    if want == got:
        return (f"replay: identical to the recorded result ({n} plate poses: the camera's pose, its covariance, "
                "the plate, the residuals, the measuring plane)")
    keys = sorted(k for k in set(want) | set(got) if want.get(k) != got.get(k))
    return f"replay: DIFFERS from the recorded result: {', '.join(keys)}"
