"""``cellcal record``: run the calibration plan and record the session to one MCAP file.

The recording holds the configuration, every frame and every arm call (ADR 0009), so
the calibration re-runs anywhere from the file alone::

    cellcal record --config cell.toml --out session.mcap      # on the cell
    cellcal calibrate --replay session.mcap --out replayed    # on a laptop

Replay builds the recorded configuration with the ``replay`` camera and arm backends
(:mod:`cellcal.drivers.replay.backends`, found through the registry like any backend) and
reports whether the result equals the recorded one exactly.
"""

from __future__ import annotations

import argparse
import sys
from importlib import resources
from pathlib import Path
from typing import Any

from cellcal.core.calibration.calibrator import Calibrator, build_devices
from cellcal.core.calibration.config import DEFAULT_CONFIG_NAME, CellConfig, load_config, parse_config
from cellcal.core.calibration.report import RESULT_FILENAME, write_json_atomic
from cellcal.devices.base import BackendContext
from cellcal.devices.camera import Camera3D
from cellcal.devices.errors import CellcalError, RecordingError, RecordingFileError
from cellcal.devices.jsonsafe import json_safe
from cellcal.devices.recording import SessionRecorder, read_recording
from cellcal.devices.registry import Registry, default_registry
from cellcal.devices.safety import SafeArm

#: Backend name of the replay camera and arm.
REPLAY_BACKEND = "replay"
#: Keys of the result document (top level / per pose) a replay need not reproduce: timing and
#: provenance. Everything else — poses, measurements, summary and any key added later — must be equal.
VOLATILE_KEYS = ("cellcal_version", "created_utc", "config_source", "timings_s")
VOLATILE_POSE_KEYS = ("timings_s",)


def register(sub: Any) -> None:
    """Add the ``record`` subcommand."""
    p = sub.add_parser("record", help="run the calibration plan and record the session to an MCAP file",
                       description="Run the calibration plan like 'cellcal calibrate' and record the session "
                       "(configuration, frames, arm calls, result) to one MCAP file, readable in Foxglove. "
                       "Re-run it anywhere with: cellcal calibrate --replay FILE.mcap")
    p.add_argument("--config", metavar="PATH", help="cell configuration (TOML); default: packaged sim.toml")
    p.add_argument("--out", metavar="FILE.mcap", required=True, help="recording to write")
    p.add_argument("--result", metavar="DIR", help="also write DIR/result.json")
    p.add_argument("--keep-failed", action="store_true",
                   help="keep the recording of a run that fails with a device or calibration error "
                   "(default: discard it)")
    p.add_argument("--quiet", action="store_true", help="no progress bar or summary; only the paths written")
    p.set_defaults(func=run)


def _config_text(path: str | None) -> str | None:
    """The TOML text of the configuration, stored in the recording for humans."""
    try:
        if path is None:
            return resources.files("cellcal.configs").joinpath(DEFAULT_CONFIG_NAME).read_text(encoding="utf-8")
        return Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError):  # already read once by load_config; not worth failing over
        return None


def record(config: CellConfig, out: str | Path, *, config_text: str | None = None, keep_failed: bool = False,
           registry: Registry | None = None, progress: Any = None) -> tuple[dict[str, Any], SessionRecorder]:
    """Run the plan of ``config`` with its devices behind a recorder writing ``out``.

    The backend arm is recorded inside the safety wrapper, so the file holds exactly
    what the backend was asked and answered.

    Returns:
        The result document and the (closed) recorder, for its message counts.

    Raises:
        CellcalError: As :meth:`Calibrator.run`; the recording is then discarded, or
            finished with the error logged when ``keep_failed``.
    """
    camera, safe_arm = build_devices(config, registry)
    with SessionRecorder(out, config_document=config.document, config_source=config.source,
                         config_text=config_text, keep_on_error=keep_failed) as recorder:
        arm = SafeArm(recorder.arm(safe_arm.inner), safe_arm.limits)
        document = Calibrator(config, recorder.camera(camera), arm, progress=progress).run()
        recorder.log_result(document)
    return document, recorder


def replay_session(path: str | Path, registry: Registry | None = None, *, strict: bool = True
                   ) -> tuple[CellConfig, Camera3D, SafeArm]:
    """The recorded configuration of ``path`` with the ``replay`` camera and arm in place of its devices.

    Args:
        path: A recording written by ``cellcal record``.
        registry: Where to find the ``replay`` backends; default: the process-wide one.
        strict: Arm calls must come in the recorded order (see :mod:`cellcal.drivers.replay.backends`).

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
    registry = registry or default_registry()
    shared: dict[str, Any] = {}

    def ctx(section: str) -> BackendContext:
        return BackendContext(source=str(path), section=section, document=document, shared=shared,
                              seed=config.cell.seed)

    file = str(Path(path).resolve())
    camera = registry.create_camera({"backend": REPLAY_BACKEND, "file": file}, ctx("camera"))
    arm = registry.create_arm({"backend": REPLAY_BACKEND, "file": file, "strict": strict}, ctx("arm"))
    return config, camera, SafeArm(arm, config.safety_limits())


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


def run(args: argparse.Namespace) -> int:
    """Run ``cellcal record``; returns the exit status."""
    config = load_config(args.config)
    progress = None
    if not args.quiet:
        from tqdm import tqdm

        def progress(total: int) -> Any:
            return tqdm(total=total, desc="poses", unit="pose", file=sys.stderr, leave=False)

    try:
        document, recorder = record(config, args.out, config_text=_config_text(args.config),
                                    keep_failed=args.keep_failed, progress=progress)
    except CellcalError as exc:
        if args.keep_failed and not isinstance(exc, RecordingError):
            print(f"recording of the failed run written to {args.out}", file=sys.stderr)
        raise
    if args.result:
        print(f"result written to {write_json_atomic(Path(args.result) / RESULT_FILENAME, document)}")
    if not args.quiet:
        size = Path(args.out).stat().st_size
        print(f"{sum(recorder.message_counts.values())} messages, {size / 1e6:.2f} MB; "
              f"re-run with: cellcal calibrate --replay {args.out}")
    print(f"recording written to {args.out}")
    return 0
