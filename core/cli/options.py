"""Command-line options shared by several ``cellcal`` subcommands, and the check of input files."""

from __future__ import annotations

import argparse
import os
import stat

from cellcal.core.cli.argtypes import integer, path_arg
from cellcal.devices.errors import ConfigError

__all__ = ["CONFIG_HELP", "add_config_option", "add_viz_port_option", "check_input_file"]

CONFIG_HELP = "cell configuration (TOML); default: packaged sim.toml"


def add_config_option(parser: argparse.ArgumentParser) -> None:
    """Add ``--config PATH`` (one cell configuration; None means the packaged ``sim.toml``)."""
    parser.add_argument("--config", metavar="PATH", type=path_arg, help=CONFIG_HELP)


def add_viz_port_option(parser: argparse.ArgumentParser) -> None:
    """Add ``--viz-port N``: serve the live view (Foxglove WebSocket) on 127.0.0.1:N (ADR 0020)."""
    parser.add_argument("--viz-port", metavar="N", type=integer(ge=1, le=65535),
                        help="serve a live 3D view on ws://127.0.0.1:N for Foxglove (point cloud, fitted plane, "
                        "frames); needs the 'viz' extra")


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
