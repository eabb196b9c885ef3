"""The ``cellcal`` command: one thin module per subcommand (``cellcal.core.cli:main``)."""

from cellcal.core.cli.exits import EXIT_FAILURE, EXIT_INTERRUPTED, EXIT_OK, EXIT_USAGE
from cellcal.core.cli.main import build_parser, main

__all__ = ["EXIT_FAILURE", "EXIT_INTERRUPTED", "EXIT_OK", "EXIT_USAGE", "build_parser", "main"]
