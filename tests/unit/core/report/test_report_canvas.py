"""The plain pictures' drawing (ADR 0051): matplotlib's colour maps, ticks and dashes; a legend clear of the marks."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("PIL")

from report_runs import decode

from cellcal.core.report.canvas import DASHED, Canvas, colour_lut, nice_ticks, tick_labels
from cellcal.core.report.chart import Chart


@pytest.mark.parametrize("name", ["viridis", "RdBu_r"])
def test_colour_maps_are_matplotlibs_to_one_level(name: str) -> None:
    matplotlib = pytest.importorskip("matplotlib")
    theirs = matplotlib.colormaps[name](np.linspace(0.0, 1.0, 256), bytes=True)[:, :3].astype(int)
    ours = colour_lut(name).astype(int)
    assert ours.shape == (256, 3)
    assert np.abs(ours - theirs).max() <= 1  # matplotlib truncates its float table, OpenCV rounds


@pytest.mark.parametrize(("lo", "hi", "bins"), [(-0.5, 223.5, 7), (-0.5, 171.5, 9), (-0.0184, 0.0158, 9),
                                                 (421.7, 503.2, 9), (-9.6, 9.6, 9), (-0.54, 2.54, 7),
                                                 (0.0, 0.0726, 9), (-315.0, 122.0, 7)])
def test_ticks_fall_where_matplotlibs_autolocator_puts_them(lo: float, hi: float, bins: int) -> None:
    ticker = pytest.importorskip("matplotlib.ticker")
    theirs = [v for v in ticker.MaxNLocator(nbins=bins, steps=[1, 2, 2.5, 5, 10]).tick_values(lo, hi) if lo <= v <= hi]
    assert nice_ticks(lo, hi, bins) == pytest.approx(theirs, abs=1e-12)


def test_tick_labels_have_the_decimals_the_step_needs_and_a_minus_sign() -> None:
    assert tick_labels([0.0, 50.0, 100.0]) == ["0", "50", "100"]
    assert tick_labels([-7.5, -5.0, -2.5, 0.0, 2.5]) == ["\u22127.5", "\u22125.0", "\u22122.5", "0.0", "2.5"]
    assert tick_labels([-0.015, -0.01, -0.005, 0.0, 0.005]) == ["\u22120.015", "\u22120.010", "\u22120.005", "0.000",
                                                                 "0.005"]


def test_a_dashed_line_has_matplotlibs_dash_and_gap() -> None:
    canvas = Canvas((2.0, 0.5), 80)
    canvas.polyline(np.array([[10.0, 20.5], [150.0, 20.5]]), "#000000", 1.5, dashes=DASHED)
    row = canvas.pixels[20, :, 0].astype(int)
    dark = row < 128
    starts = np.flatnonzero(dark[1:] & ~dark[:-1]) + 1
    # 1.5 pt at 80 dpi: a dash 3.7 line widths (6.2 px) and a gap 1.6 (2.7 px), a period of 8.8 px
    assert len(starts) >= 14
    assert np.diff(starts).mean() == pytest.approx(8.83, abs=0.2)
    assert np.count_nonzero(dark[10:150]) / 140 == pytest.approx(3.7 / 5.3, abs=0.06)


def test_the_best_legend_place_leaves_the_marks_visible() -> None:
    canvas = Canvas((6.0, 4.0), 80)
    chart = Chart(canvas, (0.1, 0.1, 0.8, 0.8))
    rng = np.random.default_rng(3)
    # marks in the upper half only: matplotlib's first places (upper right, upper left) are taken
    xs, ys = rng.uniform(0.0, 10.0, 400), rng.uniform(6.0, 10.0, 400)
    chart.scatter(xs, ys, "#2166ac", size_pt=3.0, label="points")
    chart.limits.update(x=(0.0, 10.0), y=(0.0, 10.0))
    chart.legend()
    chart.render()
    image = decode(canvas.png())
    frame = np.all(image == (204, 204, 204), axis=2)  # the legend's frame colour, exactly
    rows, cols = np.nonzero(frame)
    assert rows.size > 40
    x0, y0, x1, y1 = chart.box
    # in the lower half (lower left: the first free place), and no dot under it
    assert rows.min() > (y0 + y1) / 2 and cols.max() < (x0 + x1) / 2
    px, py = chart.x(xs), chart.y(ys)
    assert not np.any((px >= cols.min()) & (px <= cols.max()) & (py >= rows.min()) & (py <= rows.max()))
