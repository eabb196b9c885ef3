"""The ``cellcal`` console command: dispatches to one module per subcommand.

Each subcommand module has ``register(subparsers)`` (adds its parser, sets
``func=run``) and ``run(args) -> int``; exit statuses are in :mod:`cellcal.core.cli.exits`.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
from collections.abc import Sequence
from importlib import import_module

from cellcal.core.cli.exits import EXIT_FAILURE, EXIT_INTERRUPTED, EXIT_OK, EXIT_USAGE
from cellcal.devices.errors import (
    CalibrationError,
    CalibrationQualityError,
    CellcalError,
    ConfigError,
)

#: Subcommand modules, in the order they appear in ``cellcal --help``.
SUBCOMMANDS = ("calibrate", "monitor", "study", "record", "devices", "paper")



class _Parser(argparse.ArgumentParser):
    """argparse parser whose usage errors are one line and exit with status 2."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    """The top-level parser with every available subcommand."""
    parser = _Parser(prog="cellcal", description="Target-free measuring-plane calibration for robot cells "
                     "with a 3D camera on the arm.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True
    for name in SUBCOMMANDS:
        try:
            module = import_module(f"cellcal.core.cli.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"cellcal.core.cli.{name}":
                continue  # subcommand not built (yet)
            raise
        module.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``cellcal`` command; returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        code = int(args.func(args))
    except KeyboardInterrupt:
        print("cellcal: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except BrokenPipeError:
        # output piped into e.g. `head`, which closed early: not an error of ours
        with contextlib.suppress(OSError):
            sys.stdout = open(os.devnull, "w")  # noqa: SIM115 - silence the interpreter's final flush
        return EXIT_OK
    except CalibrationQualityError as exc:
        print(f"cellcal: error: {exc}", file=sys.stderr)
        return EXIT_FAILURE
    except (ConfigError, CalibrationError) as exc:
        print(f"cellcal: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except CellcalError as exc:
        print(f"cellcal: error: {exc}", file=sys.stderr)
        return EXIT_FAILURE
    return code


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
