"""``cellcal report DIR``: open a run's report in a browser, or render it again from its JSON (``--out FILE``)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from cellcal.core.cli.argtypes import path_arg
from cellcal.core.cli.exits import EXIT_OK

__all__ = ["add_no_report_option", "register", "run"]


def add_no_report_option(parser: argparse.ArgumentParser) -> None:
    """Add ``--no-report``: skip ``DIR/report.html``, its PNGs, ``report.txt`` and ``report-data.json``."""
    parser.add_argument("--no-report", action="store_true",
                        help="write no report (DIR/report.html with its pictures, report.txt, report-data.json)")


def register(sub: Any) -> None:
    """Add the ``report`` subcommand."""
    p = sub.add_parser("report", help="open a run's report (DIR/report.html) or render it again from its JSON",
                       description="Open DIR/report.html, written by calibrate, handeye or monitor --out DIR, in a "
                       "web browser (the path is printed when there is none). With --out FILE, render the report "
                       "again from DIR/report-data.json alone into one self-contained HTML file (needs the "
                       "'plots' extra for the pictures).")
    p.add_argument("dir", metavar="DIR", type=path_arg,
                   help="the run's output directory (its report.html, or its one fixed camera's handeye-NAME.html), "
                   "or a report page itself")
    p.add_argument("--out", metavar="FILE", type=path_arg, help="render the report from DIR's JSON into FILE")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run ``cellcal report``; returns the exit status."""
    from cellcal.core.console import say
    from cellcal.core.report import REPORT_HTML_FILENAME, load_report_data, render_to_file
    from cellcal.devices.errors import ConfigError

    if args.out:
        page, note = render_to_file(args.dir, args.out)
        if note:
            say(f"cellcal: {note}")
        print(f"report written to {page}")
        return EXIT_OK
    found = _page_of(Path(args.dir), REPORT_HTML_FILENAME)
    if found is None:
        load_report_data(args.dir)  # says what is missing when the data is not there either
        raise ConfigError(f"no {REPORT_HTML_FILENAME} in {args.dir}; 'cellcal report {args.dir} --out FILE' renders "
                          "it from the report data", source=str(Path(args.dir) / REPORT_HTML_FILENAME))
    page = found
    if _open_in_browser(page.resolve()):
        print(f"report opened in a browser: {page}")
    else:
        print(f"no web browser found; the report is {page.resolve()}")
    return EXIT_OK


def _page_of(path: Path, main_page: str) -> Path | None:
    """The page to open: ``path`` itself if it is an HTML file, else DIR's ``report.html``, else its one
    fixed camera's ``handeye-NAME.html`` (None when there is none).

    Raises:
        ConfigError: DIR holds no ``report.html`` but several camera pages: they are named.
    """
    from cellcal.devices.errors import ConfigError

    if path.suffix == ".html" and path.is_file():
        return path
    if (path / main_page).is_file():
        return path / main_page
    pages = sorted(path.glob("handeye-*.html")) if path.is_dir() else []
    if len(pages) > 1:
        raise ConfigError(f"no {main_page} but {len(pages)} camera reports; name one: "
                          + ", ".join(f"cellcal report {p}" for p in pages[:6]), source=str(path))
    return pages[0] if pages else None


def _open_in_browser(page: Path) -> bool:
    """Ask the :mod:`webbrowser` module to open ``page``; False when it has no browser to use."""
    import webbrowser

    try:
        webbrowser.get()
    except webbrowser.Error:
        return False
    try:
        return bool(webbrowser.open(page.as_uri()))
    except webbrowser.Error:
        return False
