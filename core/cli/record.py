"""``cellcal record``: run the calibration plan and record the session to one MCAP file.

The library side is :mod:`cellcal.core.calibration.replay`; re-run a recording with
``cellcal calibrate --replay FILE.mcap``.
"""

from __future__ import annotations

import argparse
import sys
from importlib import resources
from pathlib import Path
from typing import Any

from cellcal.core.calibration.config import DEFAULT_CONFIG_NAME, load_config
from cellcal.core.calibration.replay import record
from cellcal.core.calibration.report import RESULT_FILENAME, write_json_atomic
from cellcal.core.cli.options import add_config_option
from cellcal.core.cli.progress import progress_factory
from cellcal.devices.errors import CellcalError, RecordingError


def register(sub: Any) -> None:
    """Add the ``record`` subcommand."""
    p = sub.add_parser("record", help="run the calibration plan and record the session to an MCAP file",
                       description="Run the calibration plan like 'cellcal calibrate' and record the session "
                       "(configuration, frames, arm calls, result) to one MCAP file, readable in Foxglove. "
                       "Re-run it anywhere with: cellcal calibrate --replay FILE.mcap")
    add_config_option(p)
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


def run(args: argparse.Namespace) -> int:
    """Run ``cellcal record``; returns the exit status."""
    config = load_config(args.config)
    try:
        document, recorder = record(config, args.out, config_text=_config_text(args.config),
                                    keep_failed=args.keep_failed,
                                    progress=progress_factory("poses", "pose", args.quiet))
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
