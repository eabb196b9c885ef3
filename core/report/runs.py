"""One command run's report: its data and summary text, written at the end, then drawn from that JSON alone.

Every report is drawn from the JSON just written, so every report is proven to render from
its JSON alone (ADR 0037). Pictures that need matplotlib (hand-eye, monitor) are drawn in a
separate interpreter (``python -m cellcal.core.report DIR``): the command itself never imports
matplotlib (it stays off the fast path, ADR 0021). The calibrate report's pictures need none
(ADR 0051): they are drawn in the run's own process, which a second interpreter would cost
more than the drawing. A Ctrl-C while the report is drawn stops the child, if any, and says,
on a line of its own, how to draw the page later (ADR 0043).
"""

from __future__ import annotations

import os
import shlex
import signal
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from cellcal.core.console import Interrupted, say
from cellcal.core.report.render import (
    REPORT_DATA_FILENAME,
    REPORT_HTML_FILENAME,
    needs_matplotlib,
    new_report_data,
    write_report_data,
)
from cellcal.core.report.text import SummaryText
from cellcal.devices.interrupts import interrupts_held

__all__ = ["DRAW_TIMEOUT_S", "STOP_GRACE_S", "CalibrationReport", "RunReport", "camera_name", "draw_command",
           "draw_here", "draw_in_child"]

#: Longest the drawing child may take, s (then it is killed and the run says so).
DRAW_TIMEOUT_S = 120.0
#: Longest the drawing child is given to end after a Ctrl-C, s (it removes its temporary files; then it is killed).
STOP_GRACE_S = 5.0
#: The child gets a process group of its own: a terminal's Ctrl-C reaches this process only, which stops
#: the child and every worker it forked (none is left drawing after the run said the report is not written).
_OWN_GROUP = os.name == "posix"


def draw_command(out_dir: str | Path) -> list[str]:
    """The drawing child's command line: ``python -m cellcal.core.report DIR``."""
    return [sys.executable, "-m", "cellcal.core.report", str(out_dir)]


def draw_in_child(out_dir: str | Path, timeout_s: float = DRAW_TIMEOUT_S) -> tuple[Path | None, str]:
    """Draw the report of ``out_dir`` in a child interpreter; the page (None if not drawn) and a note.

    Raises:
        KeyboardInterrupt: Ctrl-C while the child draws; the child and its workers are stopped first.
    """
    proc = None
    try:
        with interrupts_held():  # a Ctrl-C while the child starts comes once it is known (to be stopped)
            proc = subprocess.Popen(draw_command(out_dir), stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                    stderr=subprocess.PIPE, text=True, start_new_session=_OWN_GROUP)
        _, err = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        assert proc is not None
        _stop(proc, signal.SIGKILL)
        return None, f"report not drawn: the drawing took more than {timeout_s:g} s"
    except OSError as exc:
        return None, f"report not drawn: {exc}"
    except KeyboardInterrupt:
        if proc is not None:
            _stop(proc, signal.SIGINT)
        raise
    lines = [line for line in (err or "").splitlines() if line.strip()]
    if proc.returncode != 0:
        return None, f"report not drawn: {lines[-1] if lines else f'exit status {proc.returncode}'}"
    return Path(out_dir) / REPORT_HTML_FILENAME, lines[-1] if lines else ""


def draw_here(out_dir: str | Path) -> tuple[Path | None, str]:
    """Draw the report of ``out_dir`` from its JSON in this process (pictures without matplotlib, ADR 0051).

    A drawing that fails costs the run one line, as a failing child does: the page (None if not
    drawn) and a note.

    Raises:
        KeyboardInterrupt: Ctrl-C while it draws (every file is written whole or not at all).
        CellcalError: The report data cannot be read back or a file cannot be written.
    """
    from cellcal.core.report.render import draw_report
    from cellcal.devices.errors import CellcalError

    try:
        return draw_report(out_dir, workers=1)  # on one core: no fork of a process that ran devices' threads
    except CellcalError:
        raise
    except Exception as exc:  # a bug in drawing: no traceback, the run's results stand
        return None, f"report not drawn: {type(exc).__name__}: {exc}"


def _stop(proc: subprocess.Popen[str], first: signal.Signals) -> None:
    """End the drawing child and the workers it forked: ``first`` to its group, SIGKILL after :data:`STOP_GRACE_S`."""
    for sig in (first, signal.SIGKILL):
        try:
            if _OWN_GROUP:
                os.killpg(proc.pid, sig)
            else:
                proc.kill()
        except OSError:  # already gone
            pass
        try:
            proc.communicate(timeout=STOP_GRACE_S)
            return
        except subprocess.TimeoutExpired:
            continue


class RunReport:
    """The report of one run of ``kind`` (``calibrate``, ``handeye``, ``monitor``) into ``out_dir``."""

    def __init__(self, kind: str, out_dir: str | Path, camera: str, config_source: str | None) -> None:
        self.kind = kind
        self.out_dir = Path(out_dir)
        self.data = new_report_data(kind, camera, config_source)
        self.summary = SummaryText()

    @property
    def section(self) -> dict[str, Any]:
        """The run's own part of the data (``data[kind]``)."""
        return self.data[self.kind]  # type: ignore[no-any-return]

    @contextmanager
    def tee(self) -> Iterator[None]:
        """While active, what the command prints on stdout is also the report's summary text."""
        with self.summary.tee():
            yield

    def failed(self, exc: BaseException, line: str) -> None:
        """The run failed with ``exc``: status, error, and ``line``, the error as the terminal shows it."""
        self.data["status"] = "failed"
        self.data["error"] = str(exc)
        self.summary.line(line)

    def write(self, *, quiet: bool = False) -> Path | None:
        """Write the data and text, draw the pictures and the page (here or in a child); one line says where (or
        why not).

        A report that cannot be written costs the run nothing but that line (stderr).

        Raises:
            Interrupted: Ctrl-C before the page was written; its line says what is missing and how to
                draw the page afterwards.
        """
        from cellcal.core.calibration.outlock import OutputLock
        from cellcal.devices.errors import CellcalError

        self.data["summary_text"] = self.summary.text
        page_before = _identity(self.out_dir / REPORT_HTML_FILENAME)
        stage = "data"
        try:  # one run per output directory: the report too is written under its lock
            with OutputLock.for_directory(self.out_dir):
                write_report_data(self.out_dir, self.data)
                stage = "drawing"
                page, note = draw_in_child(self.out_dir) if needs_matplotlib(self.data) else draw_here(self.out_dir)
                stage = "done"
        except CellcalError as exc:
            say(f"cellcal: report not written: {exc}".replace("\n", " "))
            return None
        except KeyboardInterrupt:
            raise Interrupted(self._interrupted_line(stage != "data", page_before)) from None
        if note:
            say(f"cellcal: {note}".replace("\n", " "))
        if page is not None and not quiet:
            print(f"report written to {page}")
        return page

    def _interrupted_line(self, data_written: bool, page_before: tuple[int, int, int] | None) -> str:
        """What a Ctrl-C while the report was written left undone, and how to draw the page afterwards.

        Args:
            data_written: Whether the report data was written (the page can be drawn from it).
            page_before: :func:`_identity` of the page before the drawing (an earlier run's page, or None).
        """
        page = self.out_dir / REPORT_HTML_FILENAME
        now = _identity(page)
        if now is not None and now != page_before:  # written (atomically: a new file) before the child stopped
            return f"cellcal: interrupted; the report was written to {page}"
        earlier = now is not None
        if not data_written:
            return (f"cellcal: interrupted before the report was written: no report of this run in {self.out_dir}"
                    + (f" ({page} is an earlier run's)" if earlier else ""))
        again = f"cellcal report {shlex.quote(str(self.out_dir))} --out {shlex.quote(str(page))}"
        return (f"cellcal: interrupted while drawing the report: {page} was not written"
                + (" (the one there is an earlier run's)" if earlier else "")
                + f"; '{again}' draws it from {self.out_dir / REPORT_DATA_FILENAME}")


class CalibrationReport(RunReport):
    """The report of a ``calibrate`` run: the camera wrapped to keep its frames, and a pose observer.

    Args:
        config: The cell configuration.
        camera: The run's camera (wrapped in :class:`FrameKeeper`: use :attr:`camera` in its place).
        out_dir: The output directory.
    """

    def __init__(self, config: Any, camera: Any, out_dir: str | Path) -> None:
        from cellcal.core.report.capture import CalibrationCapture, FrameKeeper

        name = camera_name(config)
        super().__init__("calibrate", out_dir, name, config.source)
        self.capture = CalibrationCapture(config, name)
        self.camera = FrameKeeper(camera, config.plan.frames_per_pose)

    def observer(self, other: Any = None) -> Any:
        """A pose observer that keeps the pose's pictures, then calls ``other`` (e.g. the live view's)."""

        def observe(record: Any, frames: Any, result: Any) -> None:
            self.capture(record, frames, result)
            if other is not None:
                other(record, frames, result)

        return observe

    def failed_run(self, exc: BaseException, line: str, plan_poses: Any) -> None:
        """The run failed (``line``: as the terminal says it): a refused pose is fitted again without gates,
        so its pictures show why."""
        from cellcal.devices.errors import CalibrationQualityError

        self.failed(exc, line)
        if isinstance(exc, CalibrationQualityError):
            self.capture.failed_pose(exc, list(self.camera.frames), plan_poses)
        self._store()

    def finished(self, document: dict[str, Any]) -> None:
        """The run's result document (tables, consistency, the methods) joins the pictures."""
        self.section["result"] = document
        self._store()

    def _store(self) -> None:
        self.section["poses"] = sorted(self.capture.poses, key=lambda p: int(p["index"]))


def _identity(path: Path) -> tuple[int, int, int] | None:
    """Device, inode and modification time of ``path`` (None: no such file): a file replaced atomically differs."""
    try:
        st = path.stat()
    except OSError:
        return None
    return st.st_dev, st.st_ino, st.st_mtime_ns


def camera_name(config: Any) -> str:
    """How titles name a configuration's camera: its backend and the cell."""
    return f"{config.camera_section['backend']} (cell '{config.cell.name}')"
