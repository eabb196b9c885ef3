"""Command-line options shared by several ``cellcal`` subcommands."""

from __future__ import annotations

import argparse

__all__ = ["CONFIG_HELP", "add_config_option"]

CONFIG_HELP = "cell configuration (TOML); default: packaged sim.toml"


def add_config_option(parser: argparse.ArgumentParser) -> None:
    """Add ``--config PATH`` (one cell configuration; None means the packaged ``sim.toml``)."""
    parser.add_argument("--config", metavar="PATH", help=CONFIG_HELP)
