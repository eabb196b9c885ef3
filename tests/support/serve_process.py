"""A real ``cellcal serve`` process for the service's benchmarks, its HTTP base URL read from its first line."""

from __future__ import annotations

import subprocess
import sys


def start_serve(*args: str, prefix: tuple[str, ...] = ()) -> tuple[subprocess.Popen[str], str]:
    """``cellcal serve ARGS`` (behind ``prefix``, e.g. ``taskset -c 0``); the process and its ``.../v1`` URL.

    Raises:
        SystemExit: The service did not say where it listens (its stderr in the message).
    """
    command = [*prefix, sys.executable, "-m", "cellcal.core.cli", "serve", *args]
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL,
                            text=True)
    assert proc.stdout is not None
    line = proc.stdout.readline()
    if "listening on" not in line:
        proc.kill()
        raise SystemExit(f"cellcal serve did not start: {line}{proc.communicate()[1]}")
    return proc, line.split("listening on ")[1].split()[0].rstrip("/")
