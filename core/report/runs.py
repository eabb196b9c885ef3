"""One command run's report: its data and summary text, written at the end, drawn in a child process.

The drawing runs in a separate interpreter (``python -m cellcal.core.report DIR``) from the
JSON just written: the command itself never imports matplotlib (it stays off the fast path,
ADR 0021), and every report is proven to render from its JSON alone (ADR 0037).
"""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from cellcal.core.report.render import REPORT_HTML_FILENAME, new_report_data, write_report_data
from cellcal.core.report.text import SummaryText

__all__ = ["DRAW_TIMEOUT_S", "CalibrationReport", "RunReport", "camera_name", "draw_in_child"]

#: Longest the drawing child may take, s (then it is killed and the run says so).
DRAW_TIMEOUT_S = 120.0


def draw_in_child(out_dir: str | Path, timeout_s: float = DRAW_TIMEOUT_S) -> tuple[Path | None, str]:
    """Draw the report of ``out_dir`` in a child interpreter; the page (None if not drawn) and a note."""
    try:
        done = subprocess.run([sys.executable, "-m", "cellcal.core.report", str(out_dir)], capture_output=True,
                              text=True, timeout=timeout_s, check=False)
    except subprocess.TimeoutExpired:
        return None, f"report not drawn: the drawing took more than {timeout_s:g} s"
    except OSError as exc:
        return None, f"report not drawn: {exc}"
    lines = [line for line in (done.stderr or "").splitlines() if line.strip()]
    if done.returncode != 0:
        return None, f"report not drawn: {lines[-1] if lines else f'exit status {done.returncode}'}"
    return Path(out_dir) / REPORT_HTML_FILENAME, lines[-1] if lines else ""


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
        """Write the data and text, draw the pictures and the page; one line says where (or why not).

        A report that cannot be written costs the run nothing but that line (stderr).
        """
        from cellcal.core.calibration.outlock import OutputLock
        from cellcal.devices.errors import CellcalError

        self.data["summary_text"] = self.summary.text
        try:  # one run per output directory: the report too is written under its lock
            with OutputLock.for_directory(self.out_dir):
                write_report_data(self.out_dir, self.data)
                page, note = draw_in_child(self.out_dir)
        except CellcalError as exc:
            print(f"cellcal: report not written: {exc}".replace("\n", " "), file=sys.stderr)
            return None
        if note:
            print(f"cellcal: {note}".replace("\n", " "), file=sys.stderr)
        if page is not None and not quiet:
            print(f"report written to {page}")
        return page


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


def camera_name(config: Any) -> str:
    """How titles name a configuration's camera: its backend and the cell."""
    return f"{config.camera_section['backend']} (cell '{config.cell.name}')"
