"""A plain RGB picture laid out like a matplotlib figure: numpy pixels, Pillow's text, OpenCV's PNG (ADR 0051).

The calibrate report's pictures are drawn on a :class:`Canvas` instead of matplotlib, whose
import alone costs about what the whole default sim calibration does and whose figure
machinery (artists, tick objects, text layout) costs 7 to 10 times this drawing. Sizes are
matplotlib's, in points at the canvas's dpi, and so is the font (DejaVu Sans, from
matplotlib's files: the pictures need the ``plots`` extra, which brings Pillow too).
Coordinates are pixels from the top left, a pixel ``i`` spanning ``[i, i + 1)``.
"""

from __future__ import annotations

import functools
import importlib.util
import itertools
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from cellcal.devices.errors import MissingDependencyError

__all__ = ["DASHED", "DOTTED", "Box", "Canvas", "Handle", "colour_lut", "colour_map", "hex_rgb", "nice_ticks",
           "require", "tick_labels"]

#: A box of pixels: x0, y0 (top left, included), x1, y1 (excluded).
Box = tuple[int, int, int, int]
#: Tick length and the gap between a tick and its label, points; a tick label's and an axis label's size.
TICK_PT = 3.5
LABEL_PT = 10.0
#: Gap between the tick labels and the axis label, points.
LABELPAD_PT = 4.0
#: Hatch lines: width, points, and lines per inch each way (matplotlib's hatch at density 6).
HATCH_PT = 1.0
HATCH_LINES_PER_IN = 6
#: matplotlib's dash patterns "--" and ":", in line widths: on, off.
DASHED = (3.7, 1.6)
DOTTED = (1.0, 1.65)
#: Height of a line of text, em (DejaVu Sans's ascent and descent as matplotlib lays a line out).
LINE_EM = 1.17
MINUS = "\u2212"
#: ColorBrewer's RdBu, matplotlib's "RdBu" (red to blue; reversed for "RdBu_r").
_RDBU = ("#67001f", "#b2182b", "#d6604d", "#f4a582", "#fddbc7", "#f7f7f7", "#d1e5f0", "#92c5de", "#4393c3",
         "#2166ac", "#053061")


def hex_rgb(colour: str) -> tuple[int, int, int]:
    """``"#rrggbb"`` as (r, g, b), 0-255."""
    return int(colour[1:3], 16), int(colour[3:5], 16), int(colour[5:7], 16)


@functools.lru_cache(maxsize=4)
def colour_lut(name: str) -> NDArray[np.uint8]:
    """A colour map as its 256 RGB entries (read-only): "viridis" (OpenCV's copy of matplotlib's), "RdBu_r".

    Both agree with matplotlib's to one level of 255 (tested).
    """
    if name == "viridis":
        import cv2

        lut = cv2.applyColorMap(np.arange(256, dtype=np.uint8).reshape(-1, 1), cv2.COLORMAP_VIRIDIS)[:, 0, ::-1]
    elif name == "RdBu_r":
        points = np.array([hex_rgb(c) for c in reversed(_RDBU)], dtype=np.float64) / 255.0
        x = np.linspace(0.0, 1.0, 256)
        stops = np.linspace(0.0, 1.0, len(points))
        lut = (np.stack([np.interp(x, stops, points[:, k]) for k in range(3)], axis=1) * 255.0).astype(np.uint8)
    else:
        raise ValueError(f"colour map {name!r}: expected 'viridis' or 'RdBu_r'")
    table: NDArray[np.uint8] = np.ascontiguousarray(lut, dtype=np.uint8)
    table.setflags(write=False)
    return table


def colour_map(values: NDArray[Any], lut: NDArray[np.uint8], vmin: float, vmax: float) -> NDArray[np.uint8]:
    """``values`` through ``lut`` with ``vmin``..``vmax`` spread over it (clipped); NaN is white (no paint)."""
    v = np.asarray(values, dtype=np.float64)
    span = vmax - vmin
    norm = (v - vmin) / span if span > 0 else np.zeros_like(v)
    idx = np.clip(np.floor(np.nan_to_num(norm, nan=0.0, posinf=1.0, neginf=0.0) * len(lut)), 0, len(lut) - 1)
    out = lut[idx.astype(np.intp)]
    out[~np.isfinite(v)] = 255
    return out


def nice_ticks(lo: float, hi: float, max_bins: int) -> list[float]:
    """The ticks in [lo, hi] at the smallest step of 1, 2, 2.5, 5 or 10 x 10^k giving at most ``max_bins`` bins."""
    span = hi - lo
    if not (math.isfinite(span) and span > 0):
        return [lo] if math.isfinite(lo) else []
    raw = span / max(1, max_bins)
    magnitude = 10.0 ** math.floor(math.log10(raw))
    step = next(m * magnitude for m in (1.0, 2.0, 2.5, 5.0, 10.0) if m * magnitude >= raw * (1 - 1e-9))
    first = math.ceil(lo / step - 1e-9)
    last = math.floor(hi / step + 1e-9)
    return [k * step for k in range(first, last + 1)]


def tick_labels(ticks: Sequence[float]) -> list[str]:
    """The labels of ``ticks``: as few decimals as show every one exactly, minus signs as matplotlib sets them."""
    decimals = next((d for d in range(7) if all(abs(round(t, d) - t) <= 1e-9 * max(1.0, abs(t)) for t in ticks)), 6)
    return [f"{0.0 if abs(t) < 1e-12 else t:.{decimals}f}".replace("-", MINUS) for t in ticks]


def _font_file(bold: bool) -> Path | None:
    """matplotlib's DejaVu Sans (bold) file, found without importing matplotlib; None without it."""
    try:
        spec = importlib.util.find_spec("matplotlib")
    except (ImportError, ValueError):
        return None
    if spec is None or spec.origin is None:
        return None
    path = Path(spec.origin).parent / "mpl-data" / "fonts" / "ttf" / f"DejaVuSans{'-Bold' if bold else ''}.ttf"
    return path if path.is_file() else None


def require() -> None:
    """Check that pictures can be drawn: Pillow and matplotlib's font.

    Raises:
        MissingDependencyError: Without matplotlib or Pillow (extra ``plots``).
    """
    if _font_file(False) is None or importlib.util.find_spec("PIL") is None:
        raise MissingDependencyError("matplotlib", "plots")


@functools.lru_cache(maxsize=16)
def _font(size_px: int, bold: bool = False) -> Any:
    """DejaVu Sans at ``size_px`` pixels per em."""
    from PIL import ImageFont

    path = _font_file(bold) or _font_file(False)
    if path is None:
        raise MissingDependencyError("matplotlib", "plots")
    return ImageFont.truetype(str(path), size_px)


class Handle(NamedTuple):
    """A legend entry's handle: a ``patch`` (fill, edge, hatch), a ``line`` (dashes in line widths) or a ``dot``."""

    kind: str
    colour: str
    edge: str | None = None
    hatch: str = ""
    dashes: tuple[float, float] | None = None
    width_pt: float = 1.0
    alpha: float = 1.0


class _Text(NamedTuple):
    xy: tuple[float, float]
    text: str
    size_px: int
    colour: str
    anchor: str
    vertical: bool
    bold: bool


class Canvas:
    """A white RGB picture of ``size_in`` inches at ``dpi`` dots per inch; lengths in points as matplotlib's."""

    def __init__(self, size_in: tuple[float, float], dpi: int) -> None:
        self.dpi = dpi
        self.width, self.height = round(size_in[0] * dpi), round(size_in[1] * dpi)
        self.pixels = np.full((self.height, self.width, 3), 255, dtype=np.uint8)
        self._texts: list[_Text] = []

    def px(self, points: float) -> float:
        """``points`` (1/72 in) in pixels."""
        return points * self.dpi / 72.0

    def box(self, rect: tuple[float, float, float, float]) -> Box:
        """The pixels of ``rect`` (figure fractions: left, bottom, width, height, from the bottom left)."""
        left, bottom, width, height = rect
        return (int(left * self.width), int((1.0 - bottom - height) * self.height), int((left + width) * self.width),
                int((1.0 - bottom) * self.height))

    def scale(self, box: Box, shape: tuple[int, ...]) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
        """For each row and column of ``box``, the row and column of a map of ``shape`` under its centre."""
        x0, y0, x1, y1 = box
        rows = np.minimum(((np.arange(y1 - y0) + 0.5) * shape[0] / (y1 - y0)).astype(np.intp), shape[0] - 1)
        cols = np.minimum(((np.arange(x1 - x0) + 0.5) * shape[1] / (x1 - x0)).astype(np.intp), shape[1] - 1)
        return rows, cols

    def image(self, box: Box, rgb: NDArray[np.uint8]) -> None:
        """Fill ``box`` with the map ``rgb`` (H, W, 3) scaled by nearest neighbour."""
        rows, cols = self.scale(box, rgb.shape)
        self.pixels[box[1]:box[3], box[0]:box[2]] = rgb[rows[:, None], cols[None, :]]

    def title(self, text: str, size_pt: float = 11.0) -> None:
        """The figure's title, centred, the top of its letters 2 % of the height below the top (0.76 em high)."""
        self.text((self.width / 2, 0.02 * self.height + 0.76 * self.px(size_pt)), text, size_pt, anchor="ms")

    def text(self, xy: tuple[float, float], text: str, size_pt: float, colour: str = "#000000",
             anchor: str = "la", *, vertical: bool = False, bold: bool = False) -> None:
        """Write ``text`` at ``xy`` (Pillow's anchors; ``vertical``: turned to read upward, anchored by its box:
        l/m/r across, centred along)."""
        self._texts.append(_Text(xy, text, max(1, round(self.px(size_pt))), colour, anchor, vertical, bold))

    def text_width(self, text: str, size_pt: float, bold: bool = False) -> float:
        """Length of ``text`` written at ``size_pt``, pixels."""
        return float(_font(max(1, round(self.px(size_pt))), bold).getlength(text))

    def frame(self, box: Box, colour: str = "#000000") -> None:
        """A 1-pixel frame just outside ``box`` (the axes' spines)."""
        x0, y0, x1, y1 = box
        c = hex_rgb(colour)
        self.pixels[max(0, y0 - 1), max(0, x0 - 1):x1 + 1] = c
        self.pixels[min(self.height - 1, y1), max(0, x0 - 1):x1 + 1] = c
        self.pixels[max(0, y0 - 1):y1 + 1, max(0, x0 - 1)] = c
        self.pixels[max(0, y0 - 1):y1 + 1, min(self.width - 1, x1)] = c

    def ticks(self, box: Box, side: str, span: tuple[float, float]) -> list[float]:
        """The ticks matplotlib's AutoLocator gives along ``side`` of ``box`` for ``span``."""
        length_pt = ((box[2] - box[0]) if side == "bottom" else (box[3] - box[1])) * 72.0 / self.dpi
        bins = max(1, min(int(length_pt // (LABEL_PT * (3 if side == "bottom" else 2))), 9))
        return nice_ticks(min(span), max(span), bins)

    def axis(self, box: Box, side: str, span: tuple[float, float], label: str, *,
             ticks: Sequence[float] | None = None, labels: Sequence[str] | None = None,
             size_pt: float = LABEL_PT) -> None:
        """Ticks, tick labels and ``label`` on ``side`` (bottom, left, right) of ``box``; ``span``: the values at
        its left or top end and at its right or bottom end; ``ticks`` (and their ``labels``) or automatic ones."""
        x0, y0, x1, y1 = box
        start, end = span
        values = list(self.ticks(box, side, span) if ticks is None else ticks)
        texts = list(tick_labels(values) if labels is None else labels)
        tick, pad = round(self.px(TICK_PT)), self.px(TICK_PT)
        widest = 0.0
        for value, text in zip(values, texts, strict=True):
            f = (value - start) / (end - start) if end != start else 0.5
            if side == "bottom":
                x = min(x1 - 1, int(x0 + f * (x1 - x0)))
                self.pixels[y1 + 1:y1 + 1 + tick, x] = 0
                self.text((x + 0.5, y1 + 1 + tick + pad), text, size_pt, anchor="ma")
            else:
                y = min(y1 - 1, int(y0 + f * (y1 - y0)))
                self.pixels[y, slice(x0 - 1 - tick, x0 - 1) if side == "left" else slice(x1 + 1, x1 + 1 + tick)] = 0
                self.text((x0 - 1 - tick - pad if side == "left" else x1 + 1 + tick + pad, y + 0.5), text, size_pt,
                          anchor="rm" if side == "left" else "lm")
                widest = max(widest, self.text_width(text, size_pt))
        gap = tick + pad + self.px(LABELPAD_PT)
        if side == "bottom":
            self.text(((x0 + x1) / 2, y1 + gap + self.px(size_pt) * LINE_EM), label, LABEL_PT, anchor="ma")
        elif side == "left":
            self.text((x0 - gap - widest, (y0 + y1) / 2), label, LABEL_PT, anchor="rm", vertical=True)
        else:
            self.text((x1 + gap + widest, (y0 + y1) / 2), label, LABEL_PT, anchor="lm", vertical=True)

    def colorbar(self, box: Box, lut: NDArray[np.uint8], vmin: float, vmax: float, label: str) -> None:
        """A vertical colour bar of ``lut``, ``vmin`` at the bottom to ``vmax`` at the top, ticked on the right."""
        x0, y0, x1, y1 = box
        n = y1 - y0
        values = vmax - (np.arange(n) + 0.5) / n * (vmax - vmin)
        self.pixels[y0:y1, x0:x1] = colour_map(values, lut, vmin, vmax)[:, None, :]
        self.frame(box)
        self.axis(box, "right", (vmax, vmin), label)

    def polyline(self, points: NDArray[Any], colour: str, width_pt: float, *,
                 dashes: tuple[float, float] | None = None, closed: bool = False) -> None:
        """A line through ``points`` ((N, 2) pixels, x and y), anti-aliased with butt ends; ``dashes`` (on, off) in
        line widths (:data:`DASHED`, :data:`DOTTED`), the pattern running on across corners."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        if len(pts) < 2 or not np.all(np.isfinite(pts)):
            return
        pattern = (self.px(dashes[0] * width_pt), self.px(dashes[1] * width_pt)) if dashes else None
        phase = 0.0  # length drawn before this segment, pixels
        for a, b in itertools.pairwise(np.vstack([pts, pts[:1]]) if closed else pts):
            phase += self._stroke(a, b, colour, width_pt, pattern, phase)

    def _stroke(self, p: NDArray[np.float64], q: NDArray[np.float64], colour: str, width_pt: float,
                pattern: tuple[float, float] | None = None, phase: float = 0.0) -> float:
        """A straight stroke from ``p`` to ``q`` ``width_pt`` wide with butt ends, anti-aliased by the share of each
        pixel it covers; dashed by ``pattern`` (on, off, pixels) from ``phase`` on. Its length, pixels."""
        half = self.px(width_pt) / 2
        length = float(np.hypot(*(q - p)))
        lo = np.floor(np.minimum(p, q) - half - 1).astype(int).clip(0)
        hi = np.ceil(np.maximum(p, q) + half + 2).astype(int).clip(None, (self.width, self.height))
        if length <= 0 or np.any(hi <= lo):
            return length
        u = (q - p) / length
        ys, xs = np.mgrid[lo[1]:hi[1], lo[0]:hi[0]]
        dx, dy = xs + 0.5 - p[0], ys + 0.5 - p[1]  # pixel centres from p
        along, across = dx * u[0] + dy * u[1], np.abs(dx * u[1] - dy * u[0])
        cover = np.clip(half + 0.5 - across, 0.0, 1.0) * np.clip(np.minimum(along + 0.5, length - along + 0.5), 0, 1)
        if pattern is not None:  # the share of each pixel's run along the line that falls on a dash
            on, period = pattern[0], pattern[0] + pattern[1]
            t = np.mod(along + phase, period)
            cover *= sum(np.clip(np.minimum(t + 0.5, k * period + on) - np.maximum(t - 0.5, k * period), 0.0, 1.0)
                         for k in (-1, 0, 1))
        self._blend((slice(lo[1], hi[1]), slice(lo[0], hi[0])), cover, colour)
        return length

    def _blend(self, where: tuple[slice, slice], cover: NDArray[np.float64], colour: str) -> None:
        """Paint ``colour`` over the pixels ``where`` at opacity ``cover`` (0-1, their shape)."""
        region = self.pixels[where]
        c = cover[..., None]
        region[...] = np.round(region * (1.0 - c) + np.asarray(hex_rgb(colour)) * c).astype(np.uint8)

    def dots(self, xs: NDArray[Any], ys: NDArray[Any], colour: str, diameter_pt: float) -> None:
        """Round dots ``diameter_pt`` across centred at (``xs``, ``ys``) (pixels), anti-aliased."""
        x = np.asarray(xs, dtype=np.float64).ravel()
        y = np.asarray(ys, dtype=np.float64).ravel()
        keep = np.isfinite(x) & np.isfinite(y)
        x, y = x[keep], y[keep]
        if not x.size:
            return
        r = self.px(diameter_pt) / 2
        reach = math.ceil(r + 1)
        # the pixels the dots can touch: their bounding box on the canvas
        left, top = max(0, int(x.min()) - reach), max(0, int(y.min()) - reach)
        right, bottom = min(self.width, int(x.max()) + reach + 1), min(self.height, int(y.max()) + reach + 1)
        if right <= left or bottom <= top:
            return
        cover = np.zeros((bottom - top, right - left), dtype=np.float64)
        for dy, dx in itertools.product(range(-reach, reach + 1), repeat=2):
            px, py = np.floor(x).astype(int) + dx, np.floor(y).astype(int) + dy
            ok = (px >= left) & (px < right) & (py >= top) & (py < bottom)
            share = np.clip(r + 0.5 - np.hypot(px + 0.5 - x, py + 0.5 - y), 0.0, 1.0)
            np.maximum.at(cover, (py[ok] - top, px[ok] - left), share[ok])
        self._blend((slice(top, bottom), slice(left, right)), cover, colour)

    def rectangle(self, box: tuple[float, float, float, float], edge: str | None, width_pt: float = 1.0, *,
                  fill: str | None = None, alpha: float = 1.0, hatch: str = "") -> None:
        """A rectangle (x0, y0, x1, y1, pixels): ``fill`` at ``alpha``, a hatch in ``edge`` ("/" rising diagonals,
        "x" both; doubled as matplotlib writes it), an outline ``width_pt`` wide."""
        x0, y0, x1, y1 = (round(v) for v in box)
        x0, x1 = max(0, min(x0, x1)), min(self.width, max(x0, x1))
        y0, y1 = max(0, min(y0, y1)), min(self.height, max(y0, y1))
        if x1 <= x0 or y1 <= y0:
            return
        where = (slice(y0, y1), slice(x0, x1))
        if fill is not None:
            self._blend(where, np.full((y1 - y0, x1 - x0), alpha), fill)
        if hatch and edge is not None:
            spacing, width = self.dpi / HATCH_LINES_PER_IN, self.px(HATCH_PT)
            ys, xs = np.mgrid[y0:y1, x0:x1]
            lines = (xs + ys) % spacing < width
            if "x" in hatch:
                lines |= (xs - ys) % spacing < width
            self.pixels[where][lines] = hex_rgb(edge)
        if edge is not None and width_pt > 0:
            w = max(1, round(self.px(width_pt)))
            lo, hi = w // 2, w - w // 2  # the outline is centred on the edge
            for ya, yb, xa, xb in ((y0 - lo, y0 + hi, x0 - lo, x1 + hi), (y1 - lo, y1 + hi, x0 - lo, x1 + hi),
                                   (y0 - lo, y1 + hi, x0 - lo, x0 + hi), (y0 - lo, y1 + hi, x1 - lo, x1 + hi)):
                self.pixels[max(0, ya):max(0, yb), max(0, xa):max(0, xb)] = hex_rgb(edge)

    def legend_size(self, labels: Sequence[str], size_pt: float) -> tuple[float, float]:
        """Width and height of a legend of ``labels`` (pixels), as matplotlib lays one out."""
        em = self.px(size_pt)
        widest = max((self.text_width(label, size_pt) for label in labels), default=0.0)
        n = len(labels)
        return 0.8 * em + 2.8 * em + widest, 0.8 * em + n * LINE_EM * em + max(0, n - 1) * 0.5 * em

    def legend(self, xy: tuple[float, float], entries: Sequence[tuple[Handle, str]], size_pt: float, *,
               frame: bool = True) -> None:
        """A legend with its top left at ``xy``: each handle (2 em by 0.7 em) and its label, one per line."""
        em = self.px(size_pt)
        if frame:
            w, h = self.legend_size([label for _, label in entries], size_pt)
            self.rectangle((xy[0], xy[1], xy[0] + w, xy[1] + h), "#cccccc", 1.0, fill="#ffffff", alpha=0.8)
        x, y = xy[0] + 0.4 * em, xy[1] + 0.4 * em
        for handle, label in entries:
            mid = y + LINE_EM * em / 2
            if handle.kind == "line":
                self.polyline(np.array([[x, mid], [x + 2.0 * em, mid]]), handle.colour, handle.width_pt,
                              dashes=handle.dashes)
            elif handle.kind == "dot":
                self.dots(np.array([x + em]), np.array([mid]), handle.colour, handle.width_pt)
            else:
                self.rectangle((x, mid - 0.35 * em, x + 2.0 * em, mid + 0.35 * em), handle.edge, handle.width_pt,
                               fill=None if handle.colour == "none" else handle.colour, alpha=handle.alpha,
                               hatch=handle.hatch)
            self.text((x + 2.8 * em, mid), label, size_pt, anchor="lm")
            y += (LINE_EM + 0.5) * em

    def png(self) -> bytes:
        """The picture with its text, as PNG bytes."""
        import cv2

        ok, data = cv2.imencode(".png", np.ascontiguousarray(self._with_text()[..., ::-1]),
                                [cv2.IMWRITE_PNG_COMPRESSION, 3])
        if not ok:
            raise ValueError("the picture could not be encoded as PNG")
        return bytes(data.tobytes())

    def _with_text(self) -> NDArray[np.uint8]:
        """The pixels with every text written (Pillow)."""
        from PIL import Image, ImageDraw

        img = Image.fromarray(self.pixels)
        draw = ImageDraw.Draw(img)
        for t in self._texts:
            font = _font(t.size_px, t.bold)
            if not t.vertical:
                draw.text(t.xy, t.text, fill=t.colour, font=font, anchor=t.anchor)
                continue
            left, top, right, bottom = font.getbbox(t.text, anchor="ls")
            mask = Image.new("L", (max(1, right - left), max(1, bottom - top)))
            ImageDraw.Draw(mask).text((-left, -top), t.text, fill=255, font=font, anchor="ls")
            mask = mask.rotate(90, expand=True)
            w, h = mask.size
            x = t.xy[0] - {"l": 0.0, "m": w / 2, "r": float(w)}[t.anchor[0]]
            img.paste(t.colour, (round(x), round(t.xy[1] - h / 2)), mask)
        return np.asarray(img, dtype=np.uint8)
