"""``python -m cellcal.core.report DIR``: draw DIR's PNGs and report.html from DIR/report-data.json.

Run by the commands in a child process (:mod:`cellcal.core.report.runs`). Exit status 0 when
the page was written (a note, e.g. no matplotlib, on stderr), 1 when it was not (one line).
"""

from __future__ import annotations

import sys


def main(argv: list[str]) -> int:
    """Draw the report of ``argv[0]``; the exit status."""
    from cellcal.core.report.render import draw_report
    from cellcal.devices.errors import CellcalError

    if len(argv) != 1:
        print("usage: python -m cellcal.core.report DIR", file=sys.stderr)
        return 2
    try:
        _, note = draw_report(argv[0])
    except CellcalError as exc:
        print(str(exc).replace("\n", " "), file=sys.stderr)
        return 1
    if note:
        print(note, file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
