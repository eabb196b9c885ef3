"""Open file descriptors of this process, for leak checks."""

from __future__ import annotations

import gc
import os


def open_fds() -> set[tuple[str, str]]:
    """Open descriptors as (number, target): unaffected by unrelated ones closing meanwhile."""
    gc.collect()
    out = set()
    for fd in os.listdir("/proc/self/fd"):
        try:
            out.add((fd, os.readlink(f"/proc/self/fd/{fd}")))
        except OSError:  # the listing's own descriptor, already closed
            continue
    return out
