"""``cellcal board``: write the configuration's ChArUco board as a printable page (PNG and/or PDF)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from cellcal.core.cli.argtypes import path_arg, real
from cellcal.core.cli.exits import EXIT_OK
from cellcal.core.cli.options import add_config_option, load_cell

#: The resolution asked for by default, dots per inch.
DEFAULT_DPI = 300.0


def register(sub: Any) -> None:
    """Add the ``board`` subcommand."""
    p = sub.add_parser("board", help="write the ChArUco board of [handeye] charuco_* as a page to print",
                       description="Write the ChArUco board of the configuration ([handeye] charuco_squares, "
                       "charuco_square_m, charuco_marker_ratio, charuco_dictionary) at its physical size with "
                       "margins, a 100 mm scale bar and its figures for the print-at-100 % check. FILE.png "
                       "writes a PNG, FILE.pdf a PDF (page = board + margins; needs the 'plots' extra), a FILE "
                       "without either suffix both.")
    add_config_option(p)
    p.add_argument("--out", metavar="FILE", required=True, type=path_arg,
                   help="FILE.png, FILE.pdf, or FILE (both FILE.png and FILE.pdf)")
    p.add_argument("--dpi", metavar="N", type=real(ge=72, le=1200), default=DEFAULT_DPI,
                   help="resolution (default %(default)g; the nearest at which a square is whole pixels is used "
                   "and stated)")
    p.set_defaults(func=run)


def _targets(out: Path) -> list[Path]:
    """The files to write for ``--out``: by suffix, or both for none."""
    from cellcal.devices.errors import ConfigError

    suffix = out.suffix.lower()
    if suffix in (".png", ".pdf"):
        return [out]
    if suffix:
        raise ConfigError(f"--out {out}: expected a .png or .pdf file, or a name without suffix for both")
    return [out.with_suffix(".png"), out.with_suffix(".pdf")]


def run(args: argparse.Namespace) -> int:
    """Run ``cellcal board``; returns the exit status."""
    from cellcal.core.calibration.report import write_bytes_atomic
    from cellcal.core.handeye.board_config import board_spec
    from cellcal.core.handeye.board_print import pdf_bytes, png_bytes, render_page
    from cellcal.devices.errors import MissingDependencyError

    targets = _targets(Path(args.out))
    page = render_page(board_spec(load_cell(args)), args.dpi)
    print(page.describe())
    for path in targets:
        if path.suffix.lower() == ".png":
            data = png_bytes(page)
        else:
            try:
                data = pdf_bytes(page)
            except MissingDependencyError as exc:
                if len(targets) == 1:
                    raise
                print(f"{path} not written: {exc}")
                continue
        write_bytes_atomic(path, data)
        print(f"board written to {path}")
    print("print at 100 % (no fit to page), then measure: the bar must be 100 mm and a square "
          f"{1000 * page.spec.square_m:g} mm")
    return EXIT_OK
