"""The paper's P1–P9 grid and its two approaches, reproducing its published numbers."""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest
from repo_paths import TEST_DATA

from cellcal.core.geometry.planes import Plane
from cellcal.core.methods.grid import GRID_NAMES, grid_phi_theta, grid_pixels, grid_points
from cellcal.core.methods.paper import (
    error_pct,
    law_of_cosines_angle,
    paper_methods,
    plane_fit_angle,
    spherical_to_cartesian,
)
from cellcal.core.methods.paper_data import load_paper_table
from cellcal.devices.errors import CalibrationError
from cellcal.devices.geometry.camera_model import NominalFovModel, project
from cellcal.devices.types import Intrinsics

DATA = TEST_DATA


def expected_h1() -> dict[int, tuple[float, float]]:
    with (DATA / "paper_expected_H1.csv").open() as fh:
        return {int(r["perimeter_px"]): (float(r["law_of_cosines_deg"]), float(r["plane_fit_deg"]))
                for r in csv.DictReader(fh)}


def test_grid_layout() -> None:
    pts = grid_points(20)
    assert [p.name for p in pts] == list(GRID_NAMES)
    by = {p.name: p for p in pts}
    assert (by["P1"].dx_px, by["P1"].dy_px) == (20, 20)
    assert (by["P8"].dx_px, by["P8"].dy_px) == (0, -20)
    assert (by["P6"].dx_px, by["P6"].dy_px) == (-20, 0)
    assert [round(math.degrees(p.theta_rad)) for p in pts] == [45, 90, 135, 0, 0, 180, 315, 270, 225]


@pytest.mark.parametrize("p", [0, -5, 86, 200, float("nan"), "x"])
def test_grid_rejects_perimeter_outside_image(p: object) -> None:
    with pytest.raises(CalibrationError, match="perimeter"):
        grid_points(p)  # type: ignore[arg-type]


def test_grid_limit_is_the_image_edge() -> None:
    grid_points(85)  # 172 rows: centre 85.5, so 85 px still lands on row 0.5 .. 170.5
    intr = Intrinsics(width=224, height=172, fx=200, fy=200, cx=100.0, cy=86.0)
    uv = grid_pixels(intr, 85)
    assert uv.min() >= 0 and uv[:, 0].max() <= 223 and uv[:, 1].max() <= 171
    with pytest.raises(CalibrationError, match="outside"):
        grid_pixels(intr, 101)


def test_phi_matches_spec_table() -> None:
    phi, theta = grid_phi_theta(grid_points(20), NominalFovModel.o3r222())
    deg = dict(zip(GRID_NAMES, np.degrees(phi), strict=True))
    assert deg["P4"] == pytest.approx(5.35714, abs=1e-5)
    assert deg["P2"] == pytest.approx(5.23256, abs=1e-5)
    assert deg["P1"] == pytest.approx(7.46740, abs=1e-5)
    assert deg["P5"] == 0.0
    assert math.degrees(theta[0]) == pytest.approx(45.0)


def test_phi_from_intrinsics_matches_pinhole_geometry() -> None:
    intr = Intrinsics(width=224, height=172, fx=190.0, fy=200.0, cx=111.5, cy=85.5)
    phi, theta = grid_phi_theta(grid_points(30), intr)
    assert math.tan(phi[3]) == pytest.approx(30 / 190.0)  # P4 along x
    assert math.tan(phi[1]) == pytest.approx(30 / 200.0)  # P2 along y
    assert math.tan(phi[0]) == pytest.approx(math.hypot(30 / 190.0, 30 / 200.0))
    assert math.degrees(theta[0]) == pytest.approx(math.degrees(math.atan2(30 / 200, 30 / 190)))
    assert math.degrees(theta[7]) == pytest.approx(270.0)


def test_spherical_to_cartesian() -> None:
    xyz = spherical_to_cartesian([2.0, 1.0], [math.pi / 2, 0.0], [math.pi / 6, 0.0])
    np.testing.assert_allclose(xyz, [[0.0, 1.0, math.sqrt(3)], [0.0, 0.0, 1.0]], atol=1e-15)


def test_law_of_cosines_on_a_known_triangle() -> None:
    # camera 0.5 m above a plane tilted so the axis meets it at 70 deg
    alpha = math.radians(70.0)
    co, oay = 0.5, 0.12
    cay = math.sqrt(co**2 + oay**2 - 2 * co * oay * math.cos(alpha))
    assert math.degrees(law_of_cosines_angle(co, cay, oay)) == pytest.approx(70.0, abs=1e-12)
    with pytest.raises(CalibrationError, match="triangle"):
        law_of_cosines_angle(0.5, 2.0, 0.1)
    with pytest.raises(CalibrationError, match="OAy"):
        law_of_cosines_angle(0.5, 0.5, 0.0)
    with pytest.raises(CalibrationError, match="CO"):
        law_of_cosines_angle(float("nan"), 0.5, 0.1)


def test_plane_fit_angle_on_synthetic_plane() -> None:
    """Exact distances along nominal rays to a plane at 80 deg give back 80 deg."""
    model = NominalFovModel.o3r222()
    grid = grid_points(40)
    phi, theta = grid_phi_theta(grid, model, nominal_theta=False)
    alpha = math.radians(10.0)
    plane = Plane(np.array([0.0, -math.sin(alpha), -math.cos(alpha)]), 0.46)
    rays = spherical_to_cartesian(np.ones(9), theta, phi)
    r = np.linalg.norm(plane.intersect_rays(rays), axis=1)
    assert math.degrees(plane_fit_angle(r, phi, theta)) == pytest.approx(80.0, abs=1e-9)


def test_paper_methods_with_real_intrinsics_recover_tilt() -> None:
    """With the lens model instead of the nominal one, a distorted camera is exact too."""
    intr = Intrinsics(width=224, height=172, fx=205.0, fy=203.0, cx=112.3, cy=84.9,
                      k1=-0.21, k2=0.05, p1=5e-4, p2=-3e-4)
    alpha = math.radians(10.0)
    plane = Plane(np.array([0.0, -math.sin(alpha), -math.cos(alpha)]), 0.5)
    grid = grid_points(40, width_px=224, height_px=172, cx=intr.cx, cy=intr.cy)
    phi, theta = grid_phi_theta(grid, intr)
    pts = plane.intersect_rays(spherical_to_cartesian(np.ones(9), theta, phi))
    np.testing.assert_allclose(project(intr, pts), grid_pixels(intr, 40), atol=1e-6)
    res = paper_methods(dict(zip(GRID_NAMES, pts, strict=True)), 40, intr)
    # plane fit uses R = z (the paper's simplification), so it is only approximately 80
    assert math.degrees(res.plane_fit_rad) == pytest.approx(80.0, abs=3.0)
    exact = plane_fit_angle(np.linalg.norm(pts, axis=1), phi, theta)
    assert math.degrees(exact) == pytest.approx(80.0, abs=1e-9)


def test_reproduces_published_h1_results() -> None:
    expected = expected_h1()
    datasets = [d for d in load_paper_table(DATA / "paper_table2.csv") if d.height == "H1"]
    assert sorted(int(d.perimeter_px) for d in datasets) == sorted(expected)
    for ds in datasets:
        res = paper_methods(ds.points_m, ds.perimeter_px)
        loc_deg, fit_deg = expected[int(ds.perimeter_px)]
        assert abs(math.degrees(res.law_of_cosines_rad) - loc_deg) < 1e-7
        assert abs(math.degrees(res.plane_fit_rad) - fit_deg) < 1e-4


def test_reproduces_published_mean_errors() -> None:
    """The paper's summary: law of cosines 2.19-11.42 % (mean 7.48 %), plane 0.25-2.57 %."""
    datasets = load_paper_table(DATA / "paper_table2.csv")
    assert len(datasets) == 12
    true = math.radians(80.0)
    res = [paper_methods(d.points_m, d.perimeter_px) for d in datasets]
    loc = [error_pct(r.law_of_cosines_rad, true) for r in res]
    fit = [error_pct(r.plane_fit_rad, true) for r in res]
    assert round(min(loc), 2) == 2.19 and round(max(loc), 2) == 11.42
    assert round(float(np.mean(loc)), 2) == 7.48
    assert round(min(fit), 2) == 0.25 and round(max(fit), 2) == 2.57
    assert round(float(np.mean(fit)), 2) == 1.02


def test_paper_methods_validates() -> None:
    ds = load_paper_table(DATA / "paper_table2.csv")[0]
    pts = dict(ds.points_m)
    del pts["P5"]
    with pytest.raises(CalibrationError, match="P5"):
        paper_methods(pts, 20)
    with pytest.raises(CalibrationError, match="outside"):
        paper_methods(ds.points_m, 90)
