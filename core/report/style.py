"""The report pictures' shared look: resolution, colours, the per-pose image's layout, titles (ADR 0037)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from cellcal.core.report.capture import CLASS_INLIER, CLASS_INVALID, CLASS_MIXED, CLASS_OUTLIER

__all__ = ["CLASS_AXES", "CLASS_COLORS", "COLORBAR_AXES", "DPI", "FAILED", "IMAGE_FIGSIZE_IN", "PANEL_AXES", "PASSED",
           "THRESHOLD", "pose_title"]

#: Resolution of every PNG, dots per inch.
DPI = 80
#: Class colours (RGB hex); their lightness differs too, so the classes survive greyscale.
CLASS_COLORS = {CLASS_INVALID: "#ffffff", CLASS_INLIER: "#5aae61", CLASS_MIXED: "#fdb863", CLASS_OUTLIER: "#40004b"}
#: Size of the per-pose image figure, inches, and its three image axes (figure fractions: left,
#: bottom, width, height): depth, pixel classes, residuals. The images fill their axes exactly.
IMAGE_FIGSIZE_IN = (15.0, 4.2)
PANEL_AXES = ((0.045, 0.13, 0.2, 0.72), (0.37, 0.13, 0.19, 0.72), (0.73, 0.13, 0.17, 0.72))
#: Colour bars of the depth and residual panels (figure fractions).
COLORBAR_AXES = ((0.25, 0.13, 0.01, 0.72), (0.91, 0.13, 0.01, 0.72))
CLASS_AXES = PANEL_AXES[1]
#: Colour of failed gates, passed gates and thresholds.
FAILED, PASSED, THRESHOLD = "#b2182b", "#4d4d4d", "#000000"


def pose_title(pose: Mapping[str, Any], camera: str) -> str:
    """A per-pose picture's title: the pose (1-based), the camera, and whether it failed."""
    state = " - FAILED" if pose.get("failed") else ""
    return f"pose {int(pose['index']) + 1}, camera {camera}{state}"
