"""Whether the camera's image holds the plan's pixels: ``calibrate --check`` asks, and a run before the arm moves.

The paper's grid methods sample P1-P9 at every ``[plan] perimeters_px`` around the principal
point, each in a ``window_px`` window; an image too small for a perimeter is a configuration
that does not suit the camera (ADR 0044).
"""

from __future__ import annotations

from cellcal.core.calibration.config import CellConfig
from cellcal.core.calibration.sections import PlanSection
from cellcal.core.methods.grid import GRID_METHODS, largest_perimeter_px, perimeter_problem
from cellcal.devices.errors import ConfigError
from cellcal.devices.types import Intrinsics

__all__ = ["check_plan_image", "describe_plan_image", "plan_image_problem"]


def plan_image_problem(plan: PlanSection, intrinsics: Intrinsics) -> str | None:
    """Why the image cannot hold the plan's grid (one line naming perimeters, image and what to change), or None.

    A plan without a grid method (``full_frame`` only) needs no perimeter.
    """
    if not set(plan.methods) & set(GRID_METHODS):
        return None
    return perimeter_problem(intrinsics, plan.perimeters_px, plan.window_px)


def check_plan_image(config: CellConfig, intrinsics: Intrinsics) -> None:
    """Refuse a plan whose grid leaves the camera's image.

    Raises:
        ConfigError: Naming the file, key ``plan.perimeters_px``, the perimeters, the image
            size and the largest perimeter that fits.
    """
    why = plan_image_problem(config.plan, intrinsics)
    if why is not None:
        raise ConfigError(why, source=config.source, key="plan.perimeters_px")


def describe_plan_image(config: CellConfig, intrinsics: Intrinsics | None) -> str:
    """``calibrate --check``'s line on the image, from the intrinsics the configuration fixes (None: unknown).

    Raises:
        ConfigError: The image is known and too small for the plan (:func:`check_plan_image`).
    """
    if intrinsics is None:
        return ("size known only once the camera is connected: the run checks the plan's pixels then, "
                "before the arm moves")
    check_plan_image(config, intrinsics)
    size = f"{intrinsics.width}x{intrinsics.height} px (from the configuration)"
    plan = config.plan
    if not set(plan.methods) & set(GRID_METHODS):
        return f"{size}; no grid method in the plan, every pixel goes to the full-frame fit"
    return (f"{size} holds the grid at perimeters {', '.join(str(p) for p in plan.perimeters_px)} px with "
            f"{plan.window_px} px windows (up to {largest_perimeter_px(intrinsics, plan.window_px):g} px)")
