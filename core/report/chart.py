"""One axes of a plain picture: limits, ticks, grid, marks and legend, as matplotlib's Axes lays them out.

What the calibrate report's charts use of matplotlib (ADR 0051), on a
:class:`~cellcal.core.report.canvas.Canvas`: limits from the data with 5 % margins that stop
at a bar's base, ticks at AutoLocator's steps, a light grid, marks drawn in matplotlib's
order (patches and markers, grid, lines, text), and the legend at the place it names or, for
``"best"``, at the first of matplotlib's places that covers the fewest marks.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cellcal.core.report.canvas import Canvas, Handle

__all__ = ["Chart", "subplot_rects"]

#: matplotlib's legend places, in the order "best" tries them: (x, y) of the box, 0 = left/top, 1 = right/bottom.
_PLACES = {"upper right": (1.0, 0.0), "upper left": (0.0, 0.0), "lower left": (0.0, 1.0), "lower right": (1.0, 1.0),
           "right": (1.0, 0.5), "center left": (0.0, 0.5), "center right": (1.0, 0.5), "lower center": (0.5, 1.0),
           "upper center": (0.5, 0.0), "center": (0.5, 0.5)}
#: Grid lines: colour, opacity.
GRID, GRID_ALPHA = "#b0b0b0", 0.3
#: A bar's width (data units) and a marker's and a scatter dot's size, points.
BAR_WIDTH = 0.8
MARKER_PT = 6.0


def subplot_rects(n: int, left: float, right: float, bottom: float, top: float, space: float, *,
                  rows: bool = False) -> list[tuple[float, float, float, float]]:
    """The figure fractions (left, bottom, width, height) of ``n`` axes side by side (or stacked, ``rows``) between
    the margins, ``space`` (a fraction of an axes) apart: matplotlib's ``subplots`` and ``subplots_adjust``."""
    if rows:
        h = (top - bottom) / (n + (n - 1) * space)
        return [(left, top - h - i * h * (1 + space), right - left, h) for i in range(n)]
    w = (right - left) / (n + (n - 1) * space)
    return [(left + i * w * (1 + space), bottom, w, top - bottom) for i in range(n)]


class Chart:
    """Axes at ``rect`` (figure fractions) of ``canvas``; add marks, then :meth:`render` once."""

    def __init__(self, canvas: Canvas, rect: tuple[float, float, float, float]) -> None:
        self.canvas = canvas
        self.box = canvas.box(rect)
        self.limits: dict[str, tuple[float, float] | None] = {"x": None, "y": None}
        self.tick_spec: dict[str, tuple[Sequence[float], Sequence[str], float] | None] = {"x": None, "y": None}
        self.inverted = False
        self.grid_axes = ""
        self.labels = ("", "", "")  # title, x label, y label
        self.title_style: tuple[float, str] = (12.0, "#000000")
        self._data: dict[str, list[NDArray[np.float64]]] = {"x": [], "y": []}
        self._sticky: dict[str, list[float]] = {"x": [], "y": []}
        self._marks: list[tuple[float, Callable[[], None]]] = []
        self._footprints: list[Callable[[], tuple[NDArray[np.float64], list[tuple[float, float, float, float]]]]] = []
        self._entries: list[tuple[Handle, str]] = []
        self._legend: tuple[str, float] | None = None
        self._span: tuple[float, float, float, float] = (0.0, 1.0, 0.0, 1.0)

    # ------------------------------------------------------------------ coordinates
    def x(self, v: Any) -> NDArray[np.float64]:
        """Data x to pixels."""
        lo, hi = self._span[:2]
        return self.box[0] + (np.asarray(v, dtype=np.float64) - lo) / (hi - lo) * (self.box[2] - self.box[0])

    def y(self, v: Any) -> NDArray[np.float64]:
        """Data y to pixels (up, or down when inverted)."""
        lo, hi = self._span[2:]
        f = (np.asarray(v, dtype=np.float64) - lo) / (hi - lo)
        return self.box[1] + (f if self.inverted else 1.0 - f) * (self.box[3] - self.box[1])

    def _add(self, z: float, draw: Callable[[], None], xs: Any = (), ys: Any = (), label: str | None = None,
             handle: Handle | None = None) -> None:
        self._marks.append((z, draw))
        self._data["x"].append(np.asarray(xs, dtype=np.float64).ravel())
        self._data["y"].append(np.asarray(ys, dtype=np.float64).ravel())
        if label and handle is not None:
            self._entries.append((handle, label))

    # ------------------------------------------------------------------ marks
    def scatter(self, xs: Any, ys: Any, colour: str, size_pt: float = 2.0, label: str | None = None) -> None:
        """Round dots ``size_pt`` across (matplotlib's ``s`` is its square)."""
        self._add(1.0, lambda: self.canvas.dots(self.x(xs), self.y(ys), colour, size_pt), xs, ys, label,
                  Handle("dot", colour, width_pt=size_pt))
        self._footprints.append(lambda: (np.column_stack([self.x(xs), self.y(ys)]), []))

    def hline(self, value: float, colour: str, width_pt: float = 1.5, dashes: tuple[float, float] | None = None,
              label: str | None = None) -> None:
        """A horizontal line across the axes at ``value`` (its y counts for the limits)."""
        def draw() -> None:
            y = _snap(self.y(value))
            self.canvas.polyline(np.array([[self.box[0], y], [self.box[2], y]]), colour, width_pt, dashes=dashes)

        self._add(2.0, draw, (), [value], label, Handle("line", colour, dashes=dashes, width_pt=width_pt))
        self._footprints.append(lambda: (np.empty((0, 2)), [(self.box[0], float(self.y(value)), self.box[2],
                                                              float(self.y(value)))]))

    def vline(self, value: float, colour: str, width_pt: float = 1.5, dashes: tuple[float, float] | None = None
              ) -> None:
        """A vertical line across the axes at ``value`` (its x counts for the limits)."""
        def draw() -> None:
            x = _snap(self.x(value))
            self.canvas.polyline(np.array([[x, self.box[1]], [x, self.box[3]]]), colour, width_pt, dashes=dashes)

        self._add(2.0, draw, [value], ())

    def hspan(self, lo: float, hi: float, colour: str, alpha: float, label: str | None = None) -> None:
        """A horizontal band from ``lo`` to ``hi`` across the axes."""
        def box() -> tuple[float, float, float, float]:
            return self.box[0], float(self.y(hi if not self.inverted else lo)), self.box[2], float(
                self.y(lo if not self.inverted else hi))

        self._add(1.0, lambda: self.canvas.rectangle(box(), None, 0.0, fill=colour, alpha=alpha), (), [lo, hi], label,
                  Handle("patch", colour, alpha=alpha))
        self._footprints.append(lambda: (np.empty((0, 2)), [box()]))

    def bars(self, positions: Sequence[float], values: Sequence[float] | NDArray[np.float64],
             colours: Sequence[str], *, horizontal: bool = False, hatched: Sequence[bool] = ()) -> None:
        """Bars from zero to each value (``horizontal``: along x), ``BAR_WIDTH`` wide, black edges, hatched "//"."""
        pos = np.asarray(positions, dtype=np.float64)
        val = np.nan_to_num(np.asarray(values, dtype=np.float64), nan=0.0)
        across = np.concatenate([pos - BAR_WIDTH / 2, pos + BAR_WIDTH / 2])
        along = np.concatenate([val, np.zeros_like(val)])

        def boxes() -> list[tuple[float, float, float, float]]:
            out = []
            for p, v in zip(pos, val, strict=True):
                a, b = (self.x([0.0, v]), self.y([p - BAR_WIDTH / 2, p + BAR_WIDTH / 2])) if horizontal else \
                    (self.x([p - BAR_WIDTH / 2, p + BAR_WIDTH / 2]), self.y([0.0, v]))
                out.append((float(a.min()), float(b.min()), float(a.max()), float(b.max())))
            return out

        def draw() -> None:
            for i, rect in enumerate(boxes()):
                self.canvas.rectangle(rect, "#000000", 1.0, fill=colours[i],
                                      hatch="//" if i < len(hatched) and hatched[i] else "")

        self._add(1.0, draw, along if horizontal else across, across if horizontal else along)
        self._sticky["x" if horizontal else "y"].append(0.0)
        self._footprints.append(lambda: (np.empty((0, 2)), boxes()))

    def errorbar(self, x: float, y: float, lo: float, hi: float, colour: str, capsize_pt: float = 4.0) -> None:
        """A round marker at (``x``, ``y``) with a vertical bar from ``lo`` to ``hi`` and caps."""
        def draw() -> None:
            px, py, (plo, phi) = _snap(self.x(x)), float(self.y(y)), (_snap(v) for v in self.y([lo, hi]))
            cap = self.canvas.px(capsize_pt)
            self.canvas.polyline(np.array([[px, plo], [px, phi]]), colour, 1.5)
            for end in (plo, phi):
                self.canvas.polyline(np.array([[px - cap, end], [px + cap, end]]), colour, 1.0)
            self.canvas.dots(np.array([px]), np.array([py]), colour, MARKER_PT)

        self._add(2.0, draw, [x], [v for v in (y, lo, hi) if np.isfinite(v)])
        self._footprints.append(lambda: (np.column_stack([self.x([x, x, x]), self.y([y, lo, hi])]), []))

    def text(self, x: float, y: float, text: str, size_pt: float, colour: str = "#000000", *,
             bold: bool = False) -> None:
        """``text`` starting at (``x``, ``y``), centred vertically on it (it does not count for the limits)."""
        self._marks.append((3.0, lambda: self.canvas.text((float(self.x(x)), float(self.y(y))), text, size_pt,
                                                          colour, "lm", bold=bold)))

    # ------------------------------------------------------------------ axes
    def ticks(self, axis: str, values: Sequence[float], labels: Sequence[str], size_pt: float = 10.0) -> None:
        """Fixed ticks on ``axis`` ("x" or "y") with their labels."""
        self.tick_spec[axis] = (values, labels, size_pt)

    def legend(self, place: str = "best", size_pt: float = 7.0) -> None:
        """A legend of the labelled marks, at ``place`` (one of matplotlib's, or "best")."""
        self._legend = (place, size_pt)

    def render(self) -> None:
        """Draw the marks, the grid, the frame with ticks and labels, the title and the legend."""
        self._span = (*self._limit("x"), *self._limit("y"))
        x_ticks, y_ticks = self._ticks("x"), self._ticks("y")
        if self.grid_axes:
            self._marks.append((1.5, lambda: self._grid(x_ticks[0] if self.grid_axes == "both" else [], y_ticks[0])))
        for _, draw in sorted(self._marks, key=lambda m: m[0]):  # stable: in the order added within a layer
            draw()
        c, (x0, y0, x1, _) = self.canvas, self.box
        c.frame(self.box)
        xs, ys = self._span[:2], (self._span[2:] if self.inverted else self._span[3:1:-1])
        c.axis(self.box, "bottom", xs, self.labels[1], ticks=x_ticks[0], labels=x_ticks[1], size_pt=x_ticks[2])
        c.axis(self.box, "left", ys, self.labels[2], ticks=y_ticks[0], labels=y_ticks[1], size_pt=y_ticks[2])
        size, colour = self.title_style
        c.text(((x0 + x1) / 2, y0 - c.px(6.0)), self.labels[0], size, colour, anchor="ms")
        if self._legend and self._entries:
            self._draw_legend(*self._legend)

    def _limit(self, axis: str) -> tuple[float, float]:
        """The axis's limits: set, or the data's with 5 % margins not past a sticky edge (a bar's base)."""
        fixed = self.limits[axis]
        if fixed is not None:
            return fixed
        data = np.concatenate([np.zeros(0), *self._data[axis]])
        data = data[np.isfinite(data)]
        if not data.size:
            return 0.0, 1.0
        lo, hi = float(data.min()), float(data.max())
        if hi - lo <= 1e-12 * max(abs(lo), abs(hi), 1e-300):  # matplotlib's nonsingular
            lo, hi = (-0.05, 0.05) if lo == hi == 0.0 else (lo - 0.05 * abs(lo), hi + 0.05 * abs(hi))
        margin = 0.05 * (hi - lo)
        new_lo, new_hi = lo - margin, hi + margin
        for s in self._sticky[axis]:
            if new_lo < s <= lo:
                new_lo = s
            if hi <= s < new_hi:
                new_hi = s
        return new_lo, new_hi

    def _ticks(self, axis: str) -> tuple[list[float], list[str] | None, float]:
        """The ticks inside the limits and their labels (None: as numbers), and their size."""
        lo, hi = sorted(self._span[:2] if axis == "x" else self._span[2:])
        spec = self.tick_spec[axis]
        if spec is None:
            return self.canvas.ticks(self.box, "bottom" if axis == "x" else "left", (lo, hi)), None, 10.0
        keep = [i for i, v in enumerate(spec[0]) if lo - 1e-9 * (hi - lo) <= v <= hi + 1e-9 * (hi - lo)]
        return [float(spec[0][i]) for i in keep], [spec[1][i] for i in keep], spec[2]

    def _grid(self, xs: Sequence[float], ys: Sequence[float]) -> None:
        x0, y0, x1, y1 = self.box
        for v in xs:
            col = min(x1 - 1, int(float(self.x(v))))
            self.canvas.rectangle((col, y0, col + 1, y1), None, 0.0, fill=GRID, alpha=GRID_ALPHA)
        for v in ys:
            row = min(y1 - 1, int(float(self.y(v))))
            self.canvas.rectangle((x0, row, x1, row + 1), None, 0.0, fill=GRID, alpha=GRID_ALPHA)

    def _draw_legend(self, place: str, size_pt: float) -> None:
        """The legend at ``place``; "best": the first place whose box covers the fewest marks."""
        c = self.canvas
        w, h = c.legend_size([label for _, label in self._entries], size_pt)
        pad = 0.5 * c.px(size_pt)
        x0, y0, x1, y1 = self.box

        def corner(name: str) -> tuple[float, float]:
            fx, fy = _PLACES[name]
            return x0 + pad + fx * (x1 - x0 - 2 * pad - w), y0 + pad + fy * (y1 - y0 - 2 * pad - h)

        if place == "best":
            marks = [f() for f in self._footprints]
            place = min(_PLACES, key=lambda name: _covered(corner(name), (w, h), marks))  # first of the fewest
        c.legend(corner(place), self._entries, size_pt)


def _snap(v: Any) -> float:
    """A pixel coordinate moved to its pixel's centre: a thin straight line stays crisp (matplotlib snaps too)."""
    return float(np.floor(float(v))) + 0.5


def _covered(corner: tuple[float, float], size: tuple[float, float],
             marks: list[tuple[NDArray[np.float64], list[tuple[float, float, float, float]]]]) -> int:
    """How many of the marks' points and boxes (lines: boxes of no height) a legend box covers."""
    ax, ay = corner
    bx, by = ax + size[0], ay + size[1]
    count = 0
    for points, boxes in marks:
        if len(points):
            count += int(np.count_nonzero((points[:, 0] >= ax) & (points[:, 0] <= bx) & (points[:, 1] >= ay)
                                          & (points[:, 1] <= by)))
        count += sum(1 for (p, q, r, s) in boxes if p <= bx and r >= ax and q <= by and s >= ay)
    return count
