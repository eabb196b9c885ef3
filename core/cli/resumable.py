"""Running a journaled plan from the CLI: an interrupted or failed run says how to resume it."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

from cellcal.core.cli.exits import EXIT_INTERRUPTED
from cellcal.core.console import say

T = TypeVar("T")


def resume_command(command: str, args: Any, *extra: str) -> str:
    """The command line that continues a run of ``cellcal <command>`` with these arguments."""
    import shlex  # here: not at `cellcal --help`

    config = f" --config {shlex.quote(args.config)}" if args.config else ""
    if getattr(args, "camera", None):
        config += f" --camera {shlex.quote(args.camera)}"
    more = "".join(f" {part}" for part in extra)
    return f"cellcal {command}{config}{more} --out {shlex.quote(args.out)} --resume"


def run_resumable(run: Callable[[], T], calibrator: Any, total: int, result_path: Path, resume: str) -> T | int:
    """``run()``; on Ctrl-C exit status 130 with a resume hint, on a failure the hint added to its message.

    Args:
        run: The plan's run (measures poses into the journal beside ``result_path``).
        calibrator: The calibrator whose journal counts the saved poses.
        total: Poses in the plan.
        result_path: The result file the journal sits beside.
        resume: The command line that continues the run (:func:`resume_command`).
    """
    from cellcal.core.calibration.calibrator import poses_saved
    from cellcal.core.calibration.journal import journal_path
    from cellcal.devices.errors import CellcalError

    def hint(saved: int) -> str:
        return f"{saved} of {total} poses are saved in {journal_path(result_path)}; '{resume}' continues the run"

    try:
        return run()
    except KeyboardInterrupt:
        saved = poses_saved(calibrator)
        say(f"cellcal: interrupted{f'; {hint(saved)}' if saved else ''}")
        return EXIT_INTERRUPTED
    except CellcalError as exc:
        saved = poses_saved(calibrator)
        if saved:  # keep the type (it sets the exit status) and the one-line message
            exc.args = (f"{exc}; {hint(saved)}",)
        raise
