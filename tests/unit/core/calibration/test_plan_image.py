"""The plan's P1-P9 grid against the camera's image: the perimeters that fit, exactly at the edge, and the words."""

from __future__ import annotations

import dataclasses
import tomllib
from importlib import resources

import pytest

from cellcal.core.calibration.config import parse_config
from cellcal.core.calibration.plan_image import check_plan_image, describe_plan_image, plan_image_problem
from cellcal.core.calibration.sections import PlanSection
from cellcal.core.methods.grid import (
    DEFAULT_PERIMETERS_PX,
    DEFAULT_WINDOW_PX,
    grid_pixels,
    largest_perimeter_px,
    perimeter_problem,
)
from cellcal.devices.errors import CalibrationError, ConfigError
from cellcal.devices.types import Intrinsics

SIM_DOC = tomllib.loads(resources.files("cellcal.configs").joinpath("sim.toml").read_text())
SMALL = Intrinsics(64, 48, 60.0, 60.0, 31.5, 23.5)


def test_the_defaults_are_the_plans_and_the_packaged_configs() -> None:
    assert PlanSection().perimeters_px == DEFAULT_PERIMETERS_PX == (20, 30, 40, 50)
    assert PlanSection().window_px == DEFAULT_WINDOW_PX == 3
    assert tuple(SIM_DOC["plan"]["perimeters_px"]) == DEFAULT_PERIMETERS_PX


@pytest.mark.parametrize(("intr", "window", "reach"), [
    (SMALL, 3, 22.5),                                          # 23.5 px to the top and bottom edge, less 1
    (SMALL, 1, 23.5),                                          # no window: the point itself on the edge row
    (SMALL, 7, 20.5),
    (Intrinsics(64, 48, 60.0, 60.0, 30.0, 20.0), 3, 19.0),     # off-centre: 20 px to the top edge
    (Intrinsics(224, 172, 190.0, 190.0, 111.5, 85.5), 3, 84.5),
])
def test_the_grid_reaches_the_nearest_edge_less_half_a_window(intr: Intrinsics, window: int, reach: float) -> None:
    assert largest_perimeter_px(intr, window) == reach
    assert perimeter_problem(intr, [reach], window) is None      # exactly at the edge: fits
    beyond = reach + 1e-9
    assert perimeter_problem(intr, [beyond], window) is not None


def test_a_perimeter_that_fits_samples_inside_the_image_and_one_that_does_not_is_refused_by_the_sampler() -> None:
    """The reach agrees with the sampler's own window check (core.geometry.sampling): its windows' last pixel
    centres at 22.5 + 1 = 23.5 px from (31.5, 23.5) are rows 0 and 47."""
    uv = grid_pixels(SMALL, 22.5)
    assert uv[:, 1].min() - 1 == 0.0 and uv[:, 1].max() + 1 == 47.0
    with pytest.raises(CalibrationError, match="outside the 64x48 image"):
        grid_pixels(SMALL, 24.0)


def test_the_refusal_names_every_perimeter_too_large_the_image_and_the_largest_that_fits() -> None:
    assert perimeter_problem(SMALL, (20, 30)) == (
        "perimeter 30 px puts the P1-P9 grid with its 3 px sampling windows outside the 64x48 image (at most 22.5 px "
        "from the principal point (31.5, 23.5) px); use perimeters_px of at most 22 px")
    assert perimeter_problem(SMALL, (30, 20, 40)) == (
        "perimeters 30, 40 px put the P1-P9 grid with its 3 px sampling windows outside the 64x48 image (at most "
        "22.5 px from the principal point (31.5, 23.5) px); use perimeters_px of at most 22 px")
    tiny = Intrinsics(4, 3, 4.0, 4.0, 1.5, 1.0)                  # 1 px to the edge, less the window: 0
    assert perimeter_problem(tiny, (1,)) == (
        "perimeter 1 px puts the P1-P9 grid with its 3 px sampling windows outside the 4x3 image (at most 0 px "
        "from the principal point (1.5, 1) px); no perimeter fits: leave law_of_cosines, plane_fit, "
        "plane_fit_nominal out of the plan's methods")


def _config(**plan: object) -> object:
    return parse_config({**SIM_DOC, "plan": {**SIM_DOC["plan"], **plan}}, "cell.toml")


def test_the_calibration_layer_names_the_key_and_skips_a_plan_without_a_grid_method() -> None:
    config = _config()
    with pytest.raises(ConfigError) as info:
        check_plan_image(config, SMALL)  # type: ignore[arg-type]
    assert (info.value.source, info.value.key) == ("cell.toml", "plan.perimeters_px")
    assert str(info.value) == ("cell.toml: key 'plan.perimeters_px': perimeters 30, 40, 50 px put the P1-P9 grid with "
                               "its 3 px sampling windows outside the 64x48 image (at most 22.5 px from the principal "
                               "point (31.5, 23.5) px); use perimeters_px of at most 22 px")
    full_frame_only = _config(methods=["full_frame"])
    assert plan_image_problem(full_frame_only.plan, SMALL) is None  # type: ignore[attr-defined]
    assert describe_plan_image(full_frame_only, SMALL) == (  # type: ignore[arg-type]
        "64x48 px (from the configuration); no grid method in the plan, every pixel goes to the full-frame fit")
    wide = _config(perimeters_px=[22], window_px=5).plan  # type: ignore[attr-defined]
    assert plan_image_problem(dataclasses.replace(wide, window_px=3), SMALL) is None    # 22 <= 23.5 - 1
    assert plan_image_problem(wide, SMALL) == (                                         # 22 > 23.5 - 2
        "perimeter 22 px puts the P1-P9 grid with its 5 px sampling windows outside the 64x48 image (at most 21.5 px "
        "from the principal point (31.5, 23.5) px); use perimeters_px of at most 21 px")


def test_check_describes_the_image_it_judged_or_says_it_cannot_know_it() -> None:
    config = _config(perimeters_px=[10, 22])
    assert describe_plan_image(config, SMALL) == (  # type: ignore[arg-type]
        "64x48 px (from the configuration) holds the grid at perimeters 10, 22 px with 3 px windows (up to 22.5 px)")
    assert describe_plan_image(config, None) == (  # type: ignore[arg-type]
        "size known only once the camera is connected: the run checks the plan's pixels then, before the arm moves")
