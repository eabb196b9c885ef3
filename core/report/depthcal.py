"""``cellcal depthcal``'s report: ``DIR/depthcal-report.html`` and its PNGs (issue #39 item 8, ADR 0057).

Plain images drawn in the run's own process on :class:`~cellcal.core.report.canvas.Canvas`
(ADR 0051): the learned field over the image, a held-out view's residual to the fitted plane
before and after the correction (:func:`cellcal.core.depthcal.report.held_out_residuals`),
every view's residual RMS before and after (held-out views hatched), and the held-out RMS of
each field order tried; the page holds the terminal summary and the observability table.
"""

from __future__ import annotations

import html
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cellcal.core.calibration.report import write_bytes_atomic
from cellcal.core.depthcal.report import format_summary, held_out_residuals
from cellcal.devices.systematic import normalised_pixels

__all__ = ["REPORT_FILENAME", "write_report"]

#: The report page in the output directory (its pictures beside it, ``depthcal-*.png``).
REPORT_FILENAME = "depthcal-report.html"


def _map_figure(maps: Sequence[tuple[str, NDArray[np.float64]]], title: str, unit: str) -> bytes:
    """Maps side by side on one diverging colour scale, each titled, a colour bar on the right."""
    from cellcal.core.report.canvas import Canvas, colour_lut, colour_map

    n = len(maps)
    canvas = Canvas((3.6 * n + 1.6, 3.4), 100)
    finite = np.concatenate([m[np.isfinite(m)] for _, m in maps]) if maps else np.zeros(0)
    lim = float(np.percentile(np.abs(finite), 99)) if finite.size else 1.0
    lim = lim if lim > 0 else 1.0
    lut = colour_lut("RdBu_r")
    width = 0.86 / n
    for k, (name, values) in enumerate(maps):
        h, w = values.shape
        aspect = h / w
        box_w = width * 0.9
        box_h = min(0.72, box_w * canvas.width / canvas.height * aspect)
        box = canvas.box((0.03 + k * width, 0.1, box_w, box_h))
        canvas.image(box, colour_map(values, lut, -lim, lim))
        canvas.frame(box)
        canvas.text(((box[0] + box[2]) / 2, box[1] - canvas.px(5.0)), name, 9.0, anchor="ms")
    bar = canvas.box((0.03 + n * width, 0.1, 0.02, 0.72))
    canvas.colorbar(bar, lut, -lim, lim, unit)
    canvas.title(title)
    return canvas.png()


def _bars_figure(groups: Sequence[tuple[str, Sequence[float], str]], labels: Sequence[str], hatched: Sequence[bool],
                 title: str, xlabel: str, ylabel: str, line: float | None = None, line_label: str = "") -> bytes:
    """Grouped bars (one colour per group) over ``labels``; ``hatched`` marks some positions (held out)."""
    from cellcal.core.report.canvas import DASHED, Canvas
    from cellcal.core.report.chart import Chart

    canvas = Canvas((max(5.0, 0.45 * len(labels) * max(1, len(groups)) + 1.5), 3.6), 100)
    chart = Chart(canvas, (0.12, 0.27, 0.84, 0.6))
    k = len(groups)
    step = k + 1
    for g, (_name, values, colour) in enumerate(groups):
        pos = [i * step + g for i in range(len(labels))]
        chart.bars(pos, np.asarray(values, dtype=np.float64), [colour] * len(labels), hatched=hatched)
    if line is not None and math.isfinite(line):
        chart.hline(line, "#000000", 1.0, DASHED)
    chart.ticks("x", [i * step + (k - 1) / 2 for i in range(len(labels))], list(labels), 7.0)
    chart.labels = (title, xlabel, ylabel)
    chart.grid_axes = "y"
    chart.render()
    keys = [(name, colour) for name, _values, colour in groups] if k > 1 else []
    if line is not None and math.isfinite(line) and line_label:
        keys.append((f"- - {line_label}", ""))
    x, y = 0.12 * canvas.width, canvas.height - canvas.px(9.0)
    for name, colour in keys:  # the key, in one line under the axes
        if colour:
            canvas.rectangle((x, y - canvas.px(4.0), x + canvas.px(10.0), y + canvas.px(4.0)), "#000000", 1.0,
                             fill=colour)
            x += canvas.px(14.0)
        canvas.text((x, y), name, 8.0, anchor="lm")
        x += canvas.text_width(name, 8.0) + canvas.px(18.0)
    return canvas.png()


def _figures(document: Mapping[str, Any], result: Any, views: Sequence[Any], mount: Any
             ) -> list[tuple[str, str, bytes]]:
    """(file name, caption, PNG) of every picture."""
    kind = document.get("kind")
    unit, scale = ("px", 1.0) if kind == "stereo" else ("mm", 1000.0)
    correction = result.correction
    out = []
    if views:
        intr = views[0].frame.intrinsics
        u, v = normalised_pixels(intr.width, intr.height, intr.cx, intr.cy)
        field = correction.field_at(u, v) * scale
        out.append(("depthcal-field.png", "The learned image field: the disparity (stereo) or range (ToF) the camera "
                    "adds at each pixel, beyond scale and offset.",
                    _map_figure([(f"field (order {correction.field_order})", field)], "learned field over the image",
                                unit)))
    held = [i for i, r in enumerate(document.get("views") or []) if r.get("held_out")]
    pick = held[0] if held else (0 if views else None)
    if pick is not None and pick < len(views):
        before, after = held_out_residuals(views[pick], mount, document, correction)
        name = views[pick].name or f"view {pick + 1}"
        out.append(("depthcal-residuals.png", f"{name}{' (held out)' if held else ''}: measured minus the fitted "
                    "plane, before and after the correction.",
                    _map_figure([("before", before * scale), ("after", after * scale)],
                                f"residual of {name}{' (held out)' if held else ''}", unit)))
    rows = document.get("views") or []
    if rows:
        labels = [str(r.get("name", i + 1)).replace("pose ", "") for i, r in enumerate(rows)]
        noise = (document.get("holdout") or {}).get("noise_only_rms")
        out.append(("depthcal-views.png", "Each view's residual RMS before and after the correction; hatched views "
                    "were held out of the fit.",
                    _bars_figure([("before", [scale * r["rms_before"] for r in rows], "#d6604d"),
                                  ("after", [scale * r["rms_after"] for r in rows], "#4393c3")], labels,
                                 [bool(r.get("held_out")) for r in rows] * 2,
                                 "residual RMS per view (hatched: held out)", "pose", f"RMS ({unit})",
                                 None if noise is None else scale * noise, "noise alone")))
    noise = (document.get("holdout") or {}).get("noise_only_rms")
    scores = {int(k): val for k, val in (document.get("order_scores") or {}).items() if val is not None}
    if scores:
        orders = sorted(scores)
        chosen = document.get("field_order")
        out.append(("depthcal-orders.png", "Held-out residual RMS of each field order tried; the chosen order is the "
                    "lowest within the noise of the best.",
                    _bars_figure([("held-out RMS", [scale * scores[k] for k in orders], "#92c5de")],
                                 [f"{k}{' *' if k == chosen else ''}" for k in orders], [],
                                 "held-out RMS per field order (* chosen)", "field order", f"RMS ({unit})",
                                 None if noise is None else scale * noise, "noise alone")))
    return out


def write_report(out_dir: str | Path, config: Any, document: Mapping[str, Any], result: Any, views: Sequence[Any]
                 ) -> Path | None:
    """Draw the pictures and write ``DIR/depthcal-report.html``; the page, or None (one line says why) if it could
    not be written. The result file is written before and stays valid whatever happens here."""
    from cellcal.core.console import say
    from cellcal.devices.errors import CellcalError

    out = Path(out_dir)
    try:
        figures = _figures(document, result, views, config.mount.pose())
        for name, _caption, png in figures:
            write_bytes_atomic(out / name, png)
        page = out / REPORT_FILENAME
        write_bytes_atomic(page, _page(document, figures, out).encode("utf-8"))
    except CellcalError as exc:
        say(f"cellcal: report not written: {exc}".replace("\n", " "))
        return None
    return page


def _page(document: Mapping[str, Any], figures: Sequence[tuple[str, str, bytes]], out: Path) -> str:
    """The HTML page: the summary, the pictures, the observability table."""
    from cellcal.core.depthcal.run import DEPTHCAL_FILENAME

    e = html.escape
    obs = (document.get("observability") or {}).get("parameters") or []
    rows = "".join(f"<tr><td>{e(str(p.get('name')))}</td><td>{'yes' if p.get('observable') else 'NO'}</td>"
                   f"<td>{e(str(p.get('reason') or ''))}</td></tr>" for p in obs)
    pictures = "".join(f'<figure><img src="{e(name)}" alt="{e(caption)}"><figcaption>{e(caption)}</figcaption>'
                       "</figure>" for name, caption, _ in figures)
    return ("<!doctype html><html><head><meta charset=\"utf-8\"><title>cellcal depthcal</title>"
            "<style>body{font-family:sans-serif;max-width:1100px;margin:auto}pre{background:#f4f4f4;padding:8px}"
            "img{max-width:100%}td{padding:2px 8px}</style></head><body>"
            f"<h1>Depth calibration ({e(str(document.get('kind')))})</h1>"
            f"<pre>{e(format_summary(document, out / DEPTHCAL_FILENAME))}</pre>{pictures}"
            f"<h2>What the plan can and cannot see</h2><table><tr><th>parameter</th><th>seen</th><th>why not</th>"
            f"</tr>{rows}</table></body></html>\n")
