"""The fixed camera's run report, written at the end of ``cellcal handeye --camera NAME`` (``on = "base"``).

``DIR/handeye-NAME.report-data.json`` (schema ``cellcal.report/1``, kind ``handeye-fixed``: the result
document and the words printed), its pictures beside it and ``DIR/handeye-NAME.html``, drawn in the
run's process from the data alone (:mod:`.fixed_html`, :mod:`.fixed_charts`; ADR 0037, ADR 0061).
"""

from __future__ import annotations

from pathlib import Path

from cellcal.core.report.fixed_html import FIXED_KIND, fixed_report_paths, fixed_tables
from cellcal.core.report.runs import RunReport

__all__ = ["FixedReport"]


class FixedReport(RunReport):
    """The report of a fixed camera's run into ``out_dir``: ``handeye-NAME.html`` and its data, pictures beside."""

    def __init__(self, out_dir: str | Path, camera: str, config_source: str | None) -> None:
        super().__init__(FIXED_KIND, out_dir, camera, config_source)
        self.camera = camera

    def write(self, *, quiet: bool = False) -> Path | None:
        """Write the data, draw the pictures here and the page; one line says where (or why not, on stderr).

        A report that cannot be written costs the run nothing but that line.
        """
        from cellcal.core.calibration.outlock import OutputLock
        from cellcal.core.calibration.report import write_bytes_atomic, write_json_atomic
        from cellcal.core.console import say
        from cellcal.core.report.html import render_html
        from cellcal.core.report.render import NO_MATPLOTLIB, pictures
        from cellcal.devices.errors import CellcalError, MissingDependencyError

        self.data["summary_text"] = self.summary.text
        data_path, page = fixed_report_paths(self.out_dir, self.camera)
        try:
            with OutputLock.for_directory(self.out_dir):
                write_json_atomic(data_path, self.data)
                try:
                    pics, note = pictures(self.data, workers=1), ""
                except MissingDependencyError:
                    pics, note = [], NO_MATPLOTLIB
                for pic in pics:
                    write_bytes_atomic(self.out_dir / pic.name, pic.png)
                write_bytes_atomic(page, render_html(self.data, pics, note, fixed_tables).encode("utf-8"))
        except CellcalError as exc:
            say(f"cellcal: report not written: {exc}".replace("\n", " "))
            return None
        if note:
            say(f"cellcal: {note}")
        if not quiet:
            print(f"report written to {page}")
        return page
