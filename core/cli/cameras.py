"""``cellcal cameras FILE...``: several cameras' hand-eye results: every pair's transform, the planes' agreement."""

from __future__ import annotations

import argparse
from typing import Any

from cellcal.core.cli.argtypes import path_arg
from cellcal.core.cli.exits import EXIT_FAILURE, EXIT_OK

#: Largest result file read, bytes (a hand-eye result with its poses is far below).
MAX_INPUT_BYTES = 50 << 20


def register(sub: Any) -> None:
    """Add the ``cameras`` subcommand."""
    p = sub.add_parser("cameras", help="relate several cameras' calibrations: pair transforms, plane agreement",
                       description="Read the hand-eye results of a cell's cameras (handeye.json of a camera on the "
                       "flange, handeye-NAME.json of a fixed one) and print every pair's transform with the same "
                       "parent (two on the flange, two fixed) with intervals, and whether the cameras' measuring "
                       "planes in the base frame agree (else which camera disagrees). Exit 1 when they disagree.")
    p.add_argument("results", metavar="FILE", nargs="+", type=path_arg, help="hand-eye result files, one per camera")
    p.add_argument("--json", metavar="FILE", type=path_arg, help="also write the comparison as JSON (atomically)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run ``cellcal cameras``; returns the exit status (1: the planes disagree)."""
    from pathlib import Path

    from cellcal.core.calibration.report import write_json_atomic
    from cellcal.core.cli.export import read_document
    from cellcal.core.handeye.relate import camera_result, format_relate, relate

    document = relate([camera_result(read_document(path, need_mount=False), path) for path in args.results])
    print(format_relate(document))
    if args.json:
        write_json_atomic(Path(args.json), document)
        print(f"written to {args.json}")
    agreement = document["plane_agreement"]
    return EXIT_FAILURE if agreement is not None and not agreement["agree"] else EXIT_OK
