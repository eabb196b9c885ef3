"""The one progress bar of the ``cellcal`` commands (tqdm on stderr, gone when done)."""

from __future__ import annotations

import sys
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from cellcal.core.calibration.calibrator import ProgressFactory

__all__ = ["progress_factory"]


def progress_factory(desc: str, unit: str, quiet: bool) -> ProgressFactory | None:
    """A factory of progress bars counting ``unit`` s, labelled ``desc``; None when ``quiet``.

    tqdm is imported only when a bar is wanted.
    """
    if quiet:
        return None
    import threading

    from tqdm import tqdm

    tqdm.set_lock(threading.RLock())  # one process draws the bars: no multiprocessing lock (7 ms to make)

    def progress(total: int) -> Any:
        return tqdm(total=total, desc=desc, unit=unit, file=sys.stderr, leave=False)

    return progress
