"""A printable page of the configured ChArUco board (``cellcal board``): PNG and PDF at a stated resolution.

The page is the board at its physical size with white margins; in the bottom margin a
100 mm scale bar (10 mm segments) and the board's figures let one check a print made at
100 %. Every square is a whole number of pixels, so the resolution is the one nearest
the asked DPI at which a square is exact; the PNG states it (``pHYs``) and the PDF page
is the page's physical size (ADR 0034). The PDF needs matplotlib (extra ``plots``).
"""

from __future__ import annotations

import io
import itertools
import struct
import zlib
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cellcal.core.handeye.charuco import BoardSpec
from cellcal.devices.errors import ConfigError, MissingDependencyError

#: Metres per inch.
INCH_M = 0.0254
#: Page margins around the board (left, right, top), and the bottom band with the scale bar and text, m.
MARGIN_M = 0.012
BOTTOM_M = 0.032
#: Length of the scale bar, its segments and its height, m.
SCALE_BAR_M = 0.100
SCALE_SEGMENT_M = 0.010
SCALE_HEIGHT_M = 0.004
#: Height of a text line, m.
TEXT_HEIGHT_M = 0.0032
#: Most pixels a page may have (a 1.2 m x 1.2 m board at 600 dpi fits).
MAX_PIXELS = 800_000_000 // 3


@dataclass(frozen=True)
class BoardPage:
    """A rendered page.

    Attributes:
        image: Grey page, 0 = ink, 255 = paper (rows, columns).
        px_per_m: Pixels per metre (exact for every square).
        board_origin_px: Column and row of the board's top-left outer corner.
        square_px: Pixels per square side.
        spec: The board.
    """

    image: NDArray[np.uint8]
    px_per_m: float
    board_origin_px: tuple[int, int]
    square_px: int
    spec: BoardSpec

    @property
    def dpi(self) -> float:
        """The page's resolution, dots per inch."""
        return self.px_per_m * INCH_M

    @property
    def size_m(self) -> tuple[float, float]:
        """Page width and height, metres."""
        return self.image.shape[1] / self.px_per_m, self.image.shape[0] / self.px_per_m

    def describe(self) -> str:
        """One line: board, page size (mm) and resolution."""
        s = self.spec
        w, h = self.size_m
        return (f"ChArUco {s.squares[0]} x {s.squares[1]} squares of {1000 * s.square_m:g} mm (markers "
                f"{1000 * s.square_m * s.marker_ratio:g} mm, DICT_{s.dictionary}); board "
                f"{1000 * s.squares[0] * s.square_m:g} x {1000 * s.squares[1] * s.square_m:g} mm, page "
                f"{1000 * w:.1f} x {1000 * h:.1f} mm at {self.dpi:.2f} dpi ({self.square_px} px per square)")


def render_page(spec: BoardSpec, dpi: float) -> BoardPage:
    """The page of ``spec`` at the resolution nearest ``dpi`` where a square is a whole number of pixels.

    Raises:
        ConfigError: If a square would be under 20 pixels or the page too large.
    """
    import cv2

    square_px = round(spec.square_m * dpi / INCH_M)
    if square_px < 20:
        raise ConfigError(f"a {1000 * spec.square_m:g} mm square is {square_px} px at {dpi:g} dpi: too few to "
                          "print its marker; raise --dpi", key="--dpi")
    ppm = square_px / spec.square_m
    cols, rows = spec.squares
    board_w, board_h = cols * square_px, rows * square_px
    margin, bottom = round(MARGIN_M * ppm), round(BOTTOM_M * ppm)
    width = max(board_w + 2 * margin, round((SCALE_BAR_M + 2 * MARGIN_M) * ppm))
    height = board_h + margin + bottom
    if width * height > MAX_PIXELS:
        raise ConfigError(f"the page would be {width} x {height} px; lower --dpi", key="--dpi")
    page = np.full((height, width), 255, dtype=np.uint8)
    x0 = (width - board_w) // 2
    board = np.asarray(spec.board().generateImage((board_w, board_h), marginSize=0, borderBits=1), dtype=np.uint8)
    page[margin:margin + board_h, x0:x0 + board_w] = board
    _scale_bar(page, ppm, margin, margin + board_h + round(0.006 * ppm))
    line = round(TEXT_HEIGHT_M * ppm)
    texts = [f"ChArUco {cols} x {rows}, square {1000 * spec.square_m:g} mm, marker "
             f"{1000 * spec.square_m * spec.marker_ratio:g} mm, DICT_{spec.dictionary}; {ppm * INCH_M:.2f} dpi",
             "Print at 100 % (no fit to page): the bar must measure 100 mm and a square "
             f"{1000 * spec.square_m:g} mm."]
    y = margin + board_h + round(0.006 * ppm) + round(SCALE_HEIGHT_M * ppm) + round(1.8 * line)
    for text in texts:
        _text(cv2, page, text, margin, y, line, width - 2 * margin)
        y += round(1.7 * line)
    return BoardPage(page, ppm, (x0, margin), square_px, spec)


def _scale_bar(page: NDArray[np.uint8], ppm: float, x0: int, y0: int) -> None:
    """A 100 mm bar of alternately filled 10 mm segments, outlined, from column ``x0``, row ``y0``."""
    h = round(SCALE_HEIGHT_M * ppm)
    ends = [x0 + round(k * SCALE_SEGMENT_M * ppm) for k in range(round(SCALE_BAR_M / SCALE_SEGMENT_M) + 1)]
    stroke = max(1, round(0.0002 * ppm))
    for k, (a, b) in enumerate(itertools.pairwise(ends)):
        if k % 2 == 0:
            page[y0:y0 + h, a:b] = 0
    page[y0:y0 + stroke, ends[0]:ends[-1]] = 0
    page[y0 + h - stroke:y0 + h, ends[0]:ends[-1]] = 0
    for e in (ends[0], ends[-1] - stroke):
        page[y0 - h // 2:y0 + h, e:e + stroke] = 0  # end ticks, longer than the bar


def _text(cv2: object, page: NDArray[np.uint8], text: str, x: int, y: int, height: int, max_width: int) -> None:
    """Black text with its baseline at row ``y``, about ``height`` px tall, shrunk to fit ``max_width``."""
    font = cv2.FONT_HERSHEY_SIMPLEX  # type: ignore[attr-defined]
    thickness = max(1, height // 12)
    scale = height / cv2.getTextSize("H", font, 1.0, thickness)[0][1]  # type: ignore[attr-defined]
    width = cv2.getTextSize(text, font, scale, thickness)[0][0]  # type: ignore[attr-defined]
    if width > max_width:
        scale *= max_width / width
    cv2.putText(page, text, (x, y), font, scale, 0, thickness, cv2.LINE_AA)  # type: ignore[attr-defined]


def png_bytes(page: BoardPage) -> bytes:
    """The page as a PNG stating its resolution (``pHYs``, pixels per metre)."""
    import cv2

    ok, data = cv2.imencode(".png", page.image)
    if not ok:
        raise ConfigError("OpenCV could not encode the page as PNG")
    raw = data.tobytes()
    ppm = round(page.px_per_m)
    body = b"pHYs" + struct.pack(">IIB", ppm, ppm, 1)  # unit 1: metre
    chunk = struct.pack(">I", 9) + body + struct.pack(">I", zlib.crc32(body) & 0xFFFFFFFF)
    ihdr_end = 8 + 4 + 4 + 13 + 4  # signature, IHDR length, type, data, CRC
    return raw[:ihdr_end] + chunk + raw[ihdr_end:]


def pdf_bytes(page: BoardPage) -> bytes:
    """The page as a one-page PDF whose page size is the page's physical size (the raster embedded as is).

    Raises:
        MissingDependencyError: Without matplotlib (extra ``plots``).
    """
    try:
        from matplotlib.figure import Figure
    except ImportError:
        raise MissingDependencyError("matplotlib", "plots") from None
    w, h = page.size_m
    fig = Figure(figsize=(w / INCH_M, h / INCH_M))
    ax = fig.add_axes((0.0, 0.0, 1.0, 1.0))
    ax.imshow(page.image, cmap="gray", vmin=0, vmax=255, interpolation="none", aspect="auto",
              extent=(0.0, page.image.shape[1], page.image.shape[0], 0.0))
    ax.set_axis_off()
    buf = io.BytesIO()
    fig.savefig(buf, format="pdf", dpi=page.dpi,
                metadata={"Title": page.describe(), "Creator": "cellcal board", "CreationDate": None})
    return buf.getvalue()


__all__ = ["BoardPage", "pdf_bytes", "png_bytes", "render_page"]
