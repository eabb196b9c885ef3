"""One pose's maps as one plain image: depth, pixel classes with the region, residuals (ADR 0037, ADR 0051).

The picture is laid out as the matplotlib figure it replaces (:data:`~cellcal.core.report.style.PANEL_AXES`
at 80 dpi; titles, axes in pixels, colour bars, the legend) and drawn on a
:class:`~cellcal.core.report.canvas.Canvas`: the maps by nearest neighbour through viridis
(depth) and reversed RdBu (residuals, centred on zero), as matplotlib has them, the pixel
classes in :data:`~cellcal.core.report.style.CLASS_COLORS`, the region dashed with the outside
veiled, the cells the coverage gate refused hatched in the failed colour.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cellcal.core.report.arrays import decode_array
from cellcal.core.report.canvas import DASHED, Box, Canvas, Handle, colour_lut, colour_map, hex_rgb
from cellcal.core.report.capture import CLASS_INLIER, CLASS_INVALID, CLASS_MIXED, CLASS_NAMES, CLASS_OUTLIER, REGION_BIT
from cellcal.core.report.style import (
    CLASS_COLORS,
    COLORBAR_AXES,
    DPI,
    FAILED,
    IMAGE_FIGSIZE_IN,
    PANEL_AXES,
    pose_title,
)

__all__ = ["pose_image_figure"]

#: Sizes of the figure's title, the panels' titles and the legend, points.
SUPTITLE_PT, TITLE_PT, NOTE_TITLE_PT, LEGEND_PT = 11.0, 12.0, 9.0, 7.0
#: Veil over the pixels outside the region: white at this opacity.
VEIL_ALPHA = 0.65
#: Class order of the class colour table (index = class).
_CLASS_ORDER = (CLASS_INVALID, CLASS_INLIER, CLASS_MIXED, CLASS_OUTLIER)


def pose_image_figure(pose: Mapping[str, Any], camera: str) -> bytes:
    """Depth (mm), pixel classes with the region, and residuals (mm, diverging, centred on zero): PNG bytes."""
    pics = pose["pictures"]
    depth = decode_array(pics["depth_mm"]).astype(np.float32)
    residual = decode_array(pics["residual_mm"]).astype(np.float32)
    classes = decode_array(pics["classes"])
    h, w = (int(n) for n in pics["shape_px"])
    canvas = Canvas(IMAGE_FIGSIZE_IN, DPI)
    canvas.title(pose_title(pose, camera), SUPTITLE_PT)
    boxes = [canvas.box(rect) for rect in PANEL_AXES]
    bars = [canvas.box(rect) for rect in COLORBAR_AXES]
    _depth_panel(canvas, boxes[0], bars[0], depth)
    _class_panel(canvas, boxes[1], pose, classes, (h, w))
    _residual_panel(canvas, boxes[2], bars[1], pose, residual, classes)
    for box in boxes:  # full-resolution pixel coordinates: pixel centres at integers, v downward
        canvas.frame(box)
        canvas.axis(box, "bottom", (-0.5, w - 0.5), "u (px)")
        canvas.axis(box, "left", (-0.5, h - 0.5), "v (px)")
    return canvas.png()


def _title(canvas: Canvas, box: Box, text: str, size_pt: float = TITLE_PT, colour: str = "#000000") -> None:
    """A panel's title, centred, its baseline 6 points above the panel."""
    canvas.text(((box[0] + box[2]) / 2, box[1] - canvas.px(6.0)), text, size_pt, colour, anchor="ms")


def _depth_panel(canvas: Canvas, box: Box, bar: Box, depth: NDArray[np.float32]) -> None:
    """Depth along the optical axis in viridis (lightness increases with the value), with its colour bar."""
    finite = depth[np.isfinite(depth)]
    vmin, vmax = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    lut = colour_lut("viridis")
    canvas.image(box, colour_map(depth, lut, vmin, vmax))
    canvas.colorbar(bar, lut, vmin, vmax, "depth z (mm)")
    _title(canvas, box, "depth (camera z)")


def _class_panel(canvas: Canvas, box: Box, pose: Mapping[str, Any], classes: NDArray[np.uint8],
                 shape_px: tuple[int, int]) -> None:
    """The pixel classes; with a region its dashed outline and the outside veiled; the legend; uncovered cells."""
    pics = pose["pictures"]
    table = np.array([hex_rgb(CLASS_COLORS[c]) for c in _CLASS_ORDER], dtype=np.uint8)
    canvas.image(box, table[classes & 3])
    if pics.get("region"):
        rows, cols = canvas.scale(box, classes.shape)
        inside = ((classes & REGION_BIT) > 0)[rows[:, None], cols[None, :]]
        panel = canvas.pixels[box[1]:box[3], box[0]:box[2]]
        # outside the region the fit did not look: veiled in white
        panel[~inside] = np.round(panel[~inside] * (1.0 - VEIL_ALPHA) + 255.0 * VEIL_ALPHA).astype(np.uint8)
        _outline(canvas, box, inside)
    uncovered = _uncovered_cells(canvas, box, pose, shape_px)
    _legend(canvas, box, pics, uncovered)
    _title(canvas, box, "pixels: plane, mixed, outliers" + (", region" if pics.get("region") else ""))


def _outline(canvas: Canvas, box: Box, inside: NDArray[np.bool_]) -> None:
    """The region's edge (``inside``: the panel's pixels in the region), dashed black."""
    import cv2

    contours, _ = cv2.findContours(inside.astype(np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    for contour in contours:
        poly = cv2.approxPolyDP(contour, 1.0, True).reshape(-1, 2).astype(np.float64)
        canvas.polyline(poly + np.array([box[0] + 0.5, box[1] + 0.5]), "#000000", 1.5, dashes=DASHED, closed=True)


def _uncovered_cells(canvas: Canvas, box: Box, pose: Mapping[str, Any], shape_px: tuple[int, int]
                     ) -> tuple[int, int] | None:
    """On a pose the coverage gate refused: outline and hatch the grid cells without enough plane inliers.

    Returns (uncovered, counted) cells, or None when the gate did not refuse the pose.
    """
    coverage = pose["pictures"].get("coverage")
    gate = ((pose.get("full_frame") or {}).get("gates") or {}).get("coverage")
    if not coverage or not gate or gate.get("passed", True):
        return None
    h, w = shape_px
    x0, y0, x1, y1 = box
    rows = [*coverage["row_edges_px"], h]  # cell edges in full-resolution pixels
    cols = [*coverage["col_edges_px"], w]
    bad = np.asarray(coverage["uncovered"], dtype=bool)
    for r, c in zip(*np.nonzero(bad), strict=True):
        cell = (x0 + cols[c] / w * (x1 - x0), y0 + rows[r] / h * (y1 - y0),
                x0 + cols[c + 1] / w * (x1 - x0), y0 + rows[r + 1] / h * (y1 - y0))
        canvas.rectangle(cell, FAILED, 2.0, hatch="xx")
    return int(bad.sum()), int(np.asarray(coverage["counted"], dtype=bool).sum())


def _legend(canvas: Canvas, box: Box, pics: Mapping[str, Any], uncovered: tuple[int, int] | None) -> None:
    """The class legend right of the panel, its top at the panel's top, frameless (matplotlib's layout)."""
    em = canvas.px(LEGEND_PT)
    counts = pics.get("class_counts", {})
    entries = [(Handle("patch", CLASS_COLORS[c], "#000000"), f"{CLASS_NAMES[c].split(' ')[0]}: "
                                                             f"{counts.get(CLASS_NAMES[c], 0)} px")
               for c in (CLASS_INLIER, CLASS_MIXED, CLASS_OUTLIER, CLASS_INVALID)]
    if pics.get("region"):
        entries.append((Handle("line", "#000000", dashes=DASHED, width_pt=1.5), "region used (outside: veiled)"))
    if uncovered:
        entries.append((Handle("patch", "none", FAILED, hatch="xx", width_pt=2.0),
                        f"too few plane pixels: {uncovered[0]} of {uncovered[1]} cells"))
    # anchored at 1.01 of the panel's width, half an em off it
    canvas.legend((box[2] + 0.01 * (box[2] - box[0]) + 0.5 * em, box[1] + 0.5 * em), entries, LEGEND_PT, frame=False)


def _residual_panel(canvas: Canvas, box: Box, bar: Box, pose: Mapping[str, Any], residual: NDArray[np.float32],
                    classes: NDArray[np.uint8]) -> None:
    """Residuals, diverging and symmetric about zero, scaled to the inliers' spread; a refused flatness says so."""
    inl = (classes & 3) == CLASS_INLIER
    finite = residual[inl & np.isfinite(residual)]
    lim = float(np.percentile(np.abs(finite), 99)) if finite.size else float(np.nanmax(np.abs(residual), initial=1.0))
    lim = lim if lim > 0 else 1.0
    lut = colour_lut("RdBu_r")
    canvas.image(box, colour_map(residual, lut, -lim, lim))
    canvas.colorbar(bar, lut, -lim, lim, "residual (mm, + toward the camera)")
    flat = ((pose.get("full_frame") or {}).get("gates") or {}).get("flatness")
    if flat and not flat.get("passed", True) and flat.get("value") is not None:
        # a non-flat surface: the residual pattern is why; the title says by how much
        _title(canvas, box, f"residual: NOT FLAT, a local plane {1000.0 * float(flat['value']):.2g} mm off "
                            f"(tolerance {1000.0 * float(flat['threshold']):.2g} mm)", NOTE_TITLE_PT, FAILED)
    else:
        _title(canvas, box, "residual to the fitted plane")
