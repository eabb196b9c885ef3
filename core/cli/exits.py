"""Exit statuses of the ``cellcal`` command (docs/commands/index.md, "Exit status")."""

EXIT_OK = 0  # success
EXIT_FAILURE = 1  # a device or calibration failure at run time
EXIT_USAGE = 2  # bad input: configuration, CLI usage, data file
EXIT_INTERRUPTED = 130  # Ctrl-C
