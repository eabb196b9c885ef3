"""``cellcal record``: run the calibration plan and record the session to one MCAP file.

The library side is :mod:`cellcal.core.calibration.replay`; re-run a recording with
``cellcal calibrate --replay FILE.mcap``. An interrupted recording is finished with
what was recorded (ADR 0009).
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import sys
from pathlib import Path
from typing import Any

from cellcal.core.calibration.calibrator import build_devices
from cellcal.core.calibration.config import load_config, read_config_text
from cellcal.core.calibration.outlock import OutputLock
from cellcal.core.calibration.replay import run_recorded
from cellcal.core.calibration.report import RESULT_FILENAME, write_json_atomic
from cellcal.core.cli.argtypes import path_arg
from cellcal.core.cli.exits import EXIT_INTERRUPTED, EXIT_OK
from cellcal.core.cli.options import add_config_option
from cellcal.core.cli.progress import progress_factory
from cellcal.devices.errors import CellcalError, ConfigError, OutputError
from cellcal.devices.recording import SessionRecorder
from cellcal.devices.recording.schema import TOPIC_ARM_CALL, TOPIC_CAPTURE


def register(sub: Any) -> None:
    """Add the ``record`` subcommand."""
    p = sub.add_parser("record", help="run the calibration plan and record the session to an MCAP file",
                       description="Run the calibration plan like 'cellcal calibrate' and record the session "
                       "(configuration, frames, arm calls, result) to one MCAP file, readable in Foxglove. "
                       "Re-run it anywhere with: cellcal calibrate --replay FILE.mcap. An interrupted run "
                       "(Ctrl-C) keeps the recording of what happened until then.")
    add_config_option(p)
    p.add_argument("--out", metavar="FILE.mcap", required=True, type=path_arg, help="recording to write")
    p.add_argument("--result", metavar="DIR", type=path_arg, help="also write DIR/result.json")
    p.add_argument("--keep-failed", action="store_true",
                   help="keep the recording of a run that fails with a device or calibration error "
                   "(default: discard it)")
    p.add_argument("--quiet", action="store_true", help="no progress bar or summary; only the paths written")
    p.set_defaults(func=run)


def _config_text(path: str | None) -> str | None:
    """The TOML text of the configuration, stored in the recording for humans."""
    try:
        return read_config_text(path)[0]
    except ConfigError:  # already read once by load_config; not worth failing over
        return None


def _interrupted(recorder: SessionRecorder) -> str:
    """The line saying what became of the recording of an interrupted run."""
    if recorder.finished:
        counts = recorder.message_counts
        return (f"cellcal: interrupted; the recording of the run so far ({counts[TOPIC_CAPTURE]} captures, "
                f"{counts[TOPIC_ARM_CALL]} arm calls, no result) is in {recorder.path}")
    return f"cellcal: interrupted; the recording could not be finished: {recorder.finish_error}"


def run(args: argparse.Namespace) -> int:
    """Run ``cellcal record``; returns the exit status."""
    config = load_config(args.config)
    camera, safe_arm = build_devices(config)
    out = Path(args.out)
    if out.is_dir():
        raise OutputError(f"{out} is a directory; --out takes the recording's file name, e.g. session.mcap",
                          errno=errno.EISDIR)
    with contextlib.ExitStack() as locks:
        locks.enter_context(OutputLock.for_file(out))
        if args.result:
            locks.enter_context(OutputLock.for_directory(args.result))
        recorder = SessionRecorder(out, config_document=config.document, config_source=config.source,
                                   config_text=_config_text(args.config), keep_on_error=args.keep_failed)
        try:
            with recorder:
                document = run_recorded(config, recorder, camera, safe_arm,
                                        progress=progress_factory("poses", "pose", args.quiet))
        except KeyboardInterrupt:
            print(_interrupted(recorder), file=sys.stderr)
            return EXIT_INTERRUPTED
        except CellcalError:
            if recorder.finished:
                print(f"recording of the failed run written to {out}", file=sys.stderr)
            raise
        if args.result:
            print(f"result written to {write_json_atomic(Path(args.result) / RESULT_FILENAME, document)}")
    if not args.quiet:
        size = out.stat().st_size
        print(f"{sum(recorder.message_counts.values())} messages, {size / 1e6:.2f} MB; "
              f"re-run with: cellcal calibrate --replay {out}")
    print(f"recording written to {out}")
    return EXIT_OK
