"""Run reports: every ``calibrate``, ``handeye`` and ``monitor`` run explains itself (ADR 0037).

``DIR/report.html`` (one self-contained page, pictures as data URIs), its PNGs beside it,
``DIR/report.txt`` (the words the terminal showed) and ``DIR/report-data.json`` (what the
pictures need, schema ``cellcal.report/1``), from which ``cellcal report DIR --out FILE``
renders the page again. matplotlib (extra ``plots``) is imported only to draw.
"""

from cellcal.core.report.capture import CalibrationCapture, FrameKeeper, MonitorCapture
from cellcal.core.report.render import (
    REPORT_DATA_FILENAME,
    REPORT_HTML_FILENAME,
    REPORT_SCHEMA,
    REPORT_TXT_FILENAME,
    load_report_data,
    new_report_data,
    render_to_file,
    write_report,
)
from cellcal.core.report.text import SummaryText

__all__ = ["REPORT_DATA_FILENAME", "REPORT_HTML_FILENAME", "REPORT_SCHEMA", "REPORT_TXT_FILENAME",
           "CalibrationCapture", "FrameKeeper", "MonitorCapture", "SummaryText", "load_report_data",
           "new_report_data", "render_to_file", "write_report"]
