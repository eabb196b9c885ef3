"""The ``cellcal`` command's implementation: the parser, the dispatch, the exit statuses.

Each subcommand module has ``register(subparsers)`` (adds its parser, sets
``func=run``) and ``run(args) -> int``; exit statuses are in :mod:`cellcal.core.cli.exits`.
The entry point :func:`cellcal.core.cli.main` imports this module once it handles Ctrl-C.
A command line imports only the subcommand module it names; the others are listed by
name and summary (:data:`SUMMARIES`), so ``cellcal --help`` imports none (ADR 0021, ADR 0049).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
from collections.abc import Collection, Sequence
from importlib import import_module

from cellcal.core.cli.exits import EXIT_FAILURE, EXIT_INTERRUPTED, EXIT_OK, EXIT_USAGE
from cellcal.core.cli.text import escape, one_line
from cellcal.core.console import Interrupted, say
from cellcal.devices.errors import (
    CalibrationError,
    CalibrationQualityError,
    CellcalError,
    ConfigError,
    OutputError,
)

__all__ = ["SUBCOMMANDS", "SUMMARIES", "build_parser", "exit_status", "run_command"]

#: Each subcommand's line in ``cellcal --help``, in its order: the ``help`` its module's ``register`` gives
#: (tests/unit/core/cli/test_lazy_subcommands.py holds them equal), so the listing needs no module.
SUMMARIES = {
    "calibrate": "run the calibration plan and write DIR/result.json",
    "handeye": "estimate the camera mount ([mount]) from the measuring plane",
    "depthcal": "calibrate the camera's systematic depth error from the plane and the arm's motion",
    "board": "write the ChArUco board of [handeye] charuco_* as a page to print",
    "monitor": "watch cameras for drift of the measuring plane (tilt, height)",
    "track": "keep the mount and the plane calibrated from the cell's normal work",
    "serve": "run the cell's calibration service over HTTP, XML-RPC and OPC UA (runs, calibration, pixel_to_base, "
             "events, history, metrics)",
    "report": "open a run's report (DIR/report.html) or render it again from its JSON",
    "study": "Monte Carlo accuracy study of every method on the simulated cell",
    "record": "run the calibration plan and record the session to an MCAP file or a ROS 2 bag",
    "export": "print the cameras of results as ROS 2 launch and URDF text",
    "cameras": "relate several cameras' calibrations: pair transforms, plane agreement",
    "devices": "list camera and arm backends and where they come from",
    "paper": "reproduce the paper's two tilt-measurement approaches from a P1-P9 table",
}
#: Subcommand modules, in the order they appear in ``cellcal --help``.
SUBCOMMANDS = tuple(SUMMARIES)


class _Parser(argparse.ArgumentParser):
    """argparse parser whose usage errors are one line and exit with status 2."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(EXIT_USAGE, one_line(f"{self.prog}: error: {message}") + "\n")


def build_parser(full: Collection[str] | None = None) -> argparse.ArgumentParser:
    """The top-level parser with every available subcommand.

    Args:
        full: The subcommands registered by their modules (imported for it); the others
            only by name and :data:`SUMMARIES` line, enough for ``cellcal --help`` and a
            usage error naming the choices. None: every one (documentation, tests).
    """
    parser = _Parser(prog="cellcal", description="Target-free measuring-plane calibration for robot cells "
                     "with a 3D camera on the arm.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True
    for name in SUBCOMMANDS:
        if full is not None and name not in full:
            sub.add_parser(name, help=SUMMARIES[name])
            continue
        try:
            module = import_module(f"cellcal.core.cli.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"cellcal.core.cli.{name}":
                continue  # subcommand not built (yet)
            raise
        module.register(sub)
    return parser


def _named(argv: Sequence[str]) -> tuple[str, ...]:
    """The subcommand a command line names (its first word not starting with '-'), if it is one."""
    word = next((w for w in argv if not w.startswith("-")), None)
    return (word,) if word in SUMMARIES else ()


def exit_status(exc: CellcalError) -> int:
    """The exit status of a run that ended in ``exc`` (README, "Exit status").

    2 for bad input (configuration, data file, an output path that cannot be used);
    1 for everything that failed at run time (devices, safety, a quality gate, a full
    disk, another run holding the output).
    """
    if isinstance(exc, OutputError):
        return EXIT_USAGE if exc.bad_path else EXIT_FAILURE
    if isinstance(exc, CalibrationQualityError):
        return EXIT_FAILURE
    if isinstance(exc, (ConfigError, CalibrationError)):
        return EXIT_USAGE
    return EXIT_FAILURE


def run_command(argv: Sequence[str] | None = None) -> int:
    """Parse ``argv`` (None: ``sys.argv``), run the subcommand, turn its errors into one line; the exit status."""
    with contextlib.suppress(AttributeError, ValueError, OSError):  # a path of undecodable bytes still prints
        sys.stdout.reconfigure(errors="backslashreplace")  # type: ignore[union-attr]
    words = sys.argv[1:] if argv is None else argv
    args = build_parser(_named(words)).parse_args(argv)
    if not hasattr(args, "func"):  # argparse took another word for the command than _named: parse in full
        args = build_parser().parse_args(argv)
    try:
        return int(args.func(args))
    except KeyboardInterrupt as exc:  # a line of its own, whatever stderr had before (ADR 0043)
        say(escape(exc.line) if isinstance(exc, Interrupted) else "cellcal: interrupted")  # its paths unshortened
        return EXIT_INTERRUPTED
    except BrokenPipeError:
        # output piped into e.g. `head`, which closed early: not an error of ours
        with contextlib.suppress(OSError):
            sys.stdout = open(os.devnull, "w")  # noqa: SIM115 - silence the interpreter's final flush
        return EXIT_OK
    except CellcalError as exc:
        say(one_line(f"cellcal: error: {exc}"))
        return exit_status(exc)
