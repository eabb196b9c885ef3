"""Command-line options shared by several ``cellcal`` subcommands, and the check of input files."""

from __future__ import annotations

import argparse
import os
import stat
from typing import TYPE_CHECKING

from cellcal.core.cli.argtypes import integer, path_arg, real
from cellcal.devices.errors import ConfigError

if TYPE_CHECKING:
    from cellcal.core.calibration.config import CellConfig

__all__ = ["CAMERA_HELP", "CONFIG_HELP", "DEFAULT_VIZ_WAIT_S", "add_config_option", "add_viz_port_option",
           "check_input_file", "check_viz_options", "load_cell"]

CONFIG_HELP = "cell configuration (TOML); default: packaged sim.toml"
CAMERA_HELP = "with [[cameras]]: the camera on the flange to run (default: the first on the flange)"
#: ``--viz-wait`` without a number: the longest wait for a viewer, s.
DEFAULT_VIZ_WAIT_S = 60.0
#: Longest ``--viz-wait`` and ``--viz-linger`` accepted, s (one day: every wait is bounded).
MAX_VIZ_S = 86400.0


def add_config_option(parser: argparse.ArgumentParser) -> None:
    """Add ``--config PATH`` (one cell configuration; None means the packaged ``sim.toml``) and ``--camera NAME``."""
    parser.add_argument("--config", metavar="PATH", type=path_arg, help=CONFIG_HELP)
    # checked against the configuration's [[cameras]] (one line naming the cell's cameras when absent)
    parser.add_argument("--camera", metavar="NAME", help=CAMERA_HELP)


def load_cell(args: argparse.Namespace, allow_fixed: bool = False) -> CellConfig:
    """``--config`` for the camera of ``--camera`` (default: the first on the flange; ADR 0061).

    Raises:
        ConfigError: As :func:`~cellcal.core.calibration.config.load_config`.
    """
    from cellcal.core.calibration.config import load_config

    return load_config(args.config, args.camera, allow_fixed)


def add_viz_port_option(parser: argparse.ArgumentParser) -> None:
    """Add ``--viz-port N``: serve the live view (Foxglove WebSocket) on 127.0.0.1:N (ADR 0020), with
    ``--viz-wait [S]`` and ``--viz-linger S`` (ADR 0035)."""
    parser.add_argument("--viz-port", metavar="N", type=integer(ge=1, le=65535),
                        help="serve a live 3D view on ws://127.0.0.1:N for Foxglove (point cloud, fitted plane, "
                        "frames); needs the 'viz' extra")
    parser.add_argument("--viz-wait", metavar="S", nargs="?", const=DEFAULT_VIZ_WAIT_S,
                        type=real(gt=0, le=MAX_VIZ_S),
                        help="with --viz-port: before the run, wait until a viewer subscribes, at most S seconds "
                        f"(default {DEFAULT_VIZ_WAIT_S:g}); then the run starts anyway")
    parser.add_argument("--viz-linger", metavar="S", type=real(ge=0, le=MAX_VIZ_S),
                        help="with --viz-port: keep serving S seconds after the run ends, sending the last scene "
                        "to viewers that connect then; Ctrl-C ends it with exit status 130 (the results are "
                        "already written)")


def check_viz_options(args: argparse.Namespace) -> None:
    """Refuse ``--viz-wait`` or ``--viz-linger`` without ``--viz-port``.

    Raises:
        ConfigError: Naming the option (exit status 2).
    """
    if getattr(args, "viz_port", None) is not None:
        return
    for option in ("viz_wait", "viz_linger"):
        if getattr(args, option, None) is not None:
            raise ConfigError(f"--{option.replace('_', '-')} needs --viz-port")


def check_input_file(path: str, max_bytes: int) -> None:
    """Refuse an input that is no regular file, or larger than ``max_bytes``, before anything reads it.

    A FIFO would block the reader forever and ``/dev/zero`` never end. A missing file is
    left to the reader, which names it in its own words.

    Raises:
        ConfigError: Naming the file (exit status 2).
    """
    try:
        info = os.stat(path)
    except (OSError, ValueError):
        return
    if stat.S_ISDIR(info.st_mode):
        raise ConfigError("is a directory; expected a file", source=path)
    if not stat.S_ISREG(info.st_mode):
        raise ConfigError("not a regular file (a FIFO, device or socket cannot be read as input)", source=path)
    if info.st_size > max_bytes:
        raise ConfigError(f"{info.st_size} bytes, more than the {max_bytes} an input of this kind can have",
                          source=path)
