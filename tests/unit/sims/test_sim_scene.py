"""Ray casting of the simulated scene against known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cellcal.devices.errors import CalibrationError
from cellcal.sims.scene import Box, Scene


def _unit(v: list[float]) -> np.ndarray:
    a = np.asarray(v, dtype=float)
    return a / np.linalg.norm(a)


def test_plane_hit_distances_and_normals() -> None:
    scene = Scene(np.array([0.0, 0.0, 0.1]), np.array([0.0, 0.0, 2.0]))  # normal normalised
    origin = np.array([0.2, -0.1, 0.6])
    dirs = np.array([[0, 0, -1], _unit([1, 0, -1]), _unit([0, 1, -1]), [1, 0, 0], [0, 0, 1]], dtype=float)
    t, normal, hit = scene.raycast(origin, dirs)
    assert hit.tolist() == [True, True, True, False, False]
    np.testing.assert_allclose(t[:3], [0.5, 0.5 * math.sqrt(2), 0.5 * math.sqrt(2)], rtol=1e-12)
    assert np.all(np.isinf(t[3:]))
    np.testing.assert_allclose(normal[:3], [[0, 0, 1]] * 3, atol=1e-12)
    assert np.all(np.isnan(normal[3:]))
    # Hit points lie on the plane.
    pts = origin + dirs[:3] * t[:3, None]
    np.testing.assert_allclose(scene.signed_distance_to_plane(pts), 0.0, atol=1e-12)


def test_tilted_plane_from_below_normal_faces_ray() -> None:
    n = _unit([0.0, 1.0, 1.0])
    scene = Scene(np.zeros(3), n)
    origin = np.array([0.0, 0.0, -1.0])  # below the plane z = -y
    t, normal, hit = scene.raycast(origin, np.array([[0.0, 0.0, 1.0]]))
    assert hit[0]
    assert t[0] == pytest.approx(1.0)
    np.testing.assert_allclose(normal[0], -n, atol=1e-12)


def test_box_top_and_side_hits() -> None:
    # A 0.2 x 0.1 x 0.05 box centred at plane (x=0.3, y=0), plane z = 0.
    scene = Scene(np.zeros(3), np.array([0.0, 0.0, 1.0]), (Box((0.3, 0.0), (0.2, 0.1, 0.05)),))
    origin = np.array([0.3, 0.0, 0.5])
    dirs = np.array([[0, 0, -1], _unit([0.09, 0.0, -0.45]), _unit([0.2, 0.0, -0.45])])
    t, normal, hit = scene.raycast(origin, dirs)
    assert hit.all()
    assert t[0] == pytest.approx(0.45)  # top face at z = 0.05
    np.testing.assert_allclose(normal[0], [0, 0, 1], atol=1e-12)
    assert t[1] == pytest.approx(math.hypot(0.09, 0.45))  # still on the top (|x - 0.3| < 0.1)
    # Third ray misses the top (x offset 0.2 at z=0.05) and lands on the plane at x = 0.3 + 0.2*0.5/0.45.
    assert t[2] == pytest.approx(math.hypot(0.2 * 0.5 / 0.45, 0.5))
    np.testing.assert_allclose(normal[2], [0, 0, 1], atol=1e-12)

    # Horizontal ray at z = 0.02 towards the box's -x face (x = 0.2).
    t, normal, hit = scene.raycast(np.array([0.0, 0.0, 0.02]), np.array([[1.0, 0.0, 0.0]]))
    assert hit[0] and t[0] == pytest.approx(0.2)
    np.testing.assert_allclose(normal[0], [-1, 0, 0], atol=1e-12)


def test_yawed_box_face_normal() -> None:
    yaw = math.radians(30.0)
    scene = Scene(np.zeros(3), np.array([0.0, 0.0, 1.0]), (Box((0.0, 0.0), (0.2, 0.2, 0.1), yaw),))
    # Ray from far along the box's rotated x axis, at half height, pointing at the centre.
    ax = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    t, normal, hit = scene.raycast(ax * 1.0 + [0, 0, 0.05], -ax[None, :])
    assert hit[0]
    assert t[0] == pytest.approx(0.9)
    np.testing.assert_allclose(normal[0], ax, atol=1e-12)


def test_box_on_tilted_plane_sits_on_plane() -> None:
    n = _unit([0.2, 0.0, 1.0])
    scene = Scene(np.array([0.0, 0.0, 0.3]), n, (Box((0.0, 0.0), (0.1, 0.1, 0.04)),))
    origin = scene.plane_point_m + n * 0.5
    t, normal, hit = scene.raycast(origin, -n[None, :])
    assert hit[0] and t[0] == pytest.approx(0.46)
    np.testing.assert_allclose(normal[0], n, atol=1e-12)


def test_nearest_of_two_boxes_and_vectorised_count() -> None:
    scene = Scene(np.zeros(3), np.array([0.0, 0.0, 1.0]),
                  (Box((0.0, 0.0), (0.1, 0.1, 0.05)), Box((0.0, 0.0), (0.05, 0.05, 0.2))))
    rng = np.random.default_rng(0)
    dirs = np.column_stack([rng.uniform(-0.3, 0.3, 5000), rng.uniform(-0.3, 0.3, 5000), -np.ones(5000)])
    t, _, hit = scene.raycast(np.array([0.0, 0.0, 1.0]), dirs)
    assert hit.all()
    z = 1.0 + t * dirs[:, 2]
    x, y = dirs[:, 0] * t, dirs[:, 1] * t
    # Every hit lies on one of the surfaces: tall box top (0.2), short box top (0.05), plane (0).
    on_tall = np.isclose(z, 0.2) & (np.abs(x) <= 0.025 + 1e-12) & (np.abs(y) <= 0.025 + 1e-12)
    on_short = np.isclose(z, 0.05) & (np.abs(x) <= 0.05 + 1e-12) & (np.abs(y) <= 0.05 + 1e-12)
    on_plane = np.isclose(z, 0.0)
    assert np.all(on_tall | on_short | on_plane)
    assert on_tall.sum() > 0 and on_short.sum() > 0 and on_plane.sum() > 0


def test_bad_input_raises_cellcal_error() -> None:
    scene = Scene()
    with pytest.raises(CalibrationError):
        scene.raycast(np.zeros(3), np.zeros((3, 2)))
    with pytest.raises(CalibrationError):
        Box((0.0, 0.0), (0.1, -0.1, 0.1))
    with pytest.raises(CalibrationError):
        Scene(np.zeros(3), np.zeros(3))
