"""Ray casting of the simulated scene against known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cellcal.devices.errors import CalibrationError
from cellcal.sims.scene import SURFACE_NONE, SURFACE_PLANE, Box, Scene


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


def test_surface_ids_and_reflectivities() -> None:
    # Box 0: 0.2 x 0.1 x 0.05 at (0.3, 0); box 1: a white 0.1 cube at (-0.3, 0).
    scene = Scene(np.zeros(3), np.array([0.0, 0.0, 1.0]),
                  (Box((0.3, 0.0), (0.2, 0.1, 0.05)), Box((-0.3, 0.0), (0.1, 0.1, 0.1), reflectivity=0.9)),
                  plane_reflectivity=0.3)
    origin = np.array([0.0, 0.0, 0.02])
    dirs = np.array([[1.0, 0, 0], [-1.0, 0, 0], [0, 0, -1.0], [0, 0, 1.0]])
    t, _, hit, surface = scene.raycast_surfaces(origin, dirs)
    # +x ray enters box 0 through its -x face (axis 0, minus side: face 0): id 1 + 0; -x ray enters box 1
    # through its +x face (face 1): id 1 + 6 + 1; down: the plane; up: nothing.
    assert surface.tolist() == [1, 8, SURFACE_PLANE, SURFACE_NONE]
    assert hit.tolist() == [True, True, True, False]
    np.testing.assert_allclose(t[:3], [0.2, 0.25, 0.02])
    np.testing.assert_allclose(scene.reflectivity(surface), [0.5, 0.9, 0.3, 0.0])
    # The top face of box 0 from above: face 5 (axis 2, plus side).
    _, _, _, top = scene.raycast_surfaces(np.array([0.3, 0.0, 1.0]), np.array([[0.0, 0.0, -1.0]]))
    assert top.tolist() == [1 + 5]
    for bad in (0.0, -0.1, 1e3):
        with pytest.raises(CalibrationError, match="reflectivity"):
            Box((0.0, 0.0), (0.1, 0.1, 0.1), reflectivity=bad)
        with pytest.raises(CalibrationError, match="reflectivity"):
            Scene(plane_reflectivity=bad)


def _slab_reference(origin: np.ndarray, dirs: np.ndarray, scene: Scene) -> np.ndarray:
    """Nearest hit by brute force: every ray against every box face rectangle and the plane."""
    best = np.full(dirs.shape[0], np.inf)
    denom = dirs @ scene.plane_normal
    with np.errstate(divide="ignore", invalid="ignore"):
        tp = float((scene.plane_point_m - origin) @ scene.plane_normal) / denom
    best = np.where(tp > 1e-9, tp, best)
    for b in scene.boxes:
        c, s = math.cos(b.yaw_rad), math.sin(b.yaw_rad)
        rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])  # plane frame == world frame here
        centre = np.array([*b.center_xy_m, b.size_m[2] / 2])
        half = np.asarray(b.size_m) / 2
        o_l, d_l = rot.T @ (origin - centre), dirs @ rot
        for axis in range(3):
            for sign in (-1.0, 1.0):
                with np.errstate(divide="ignore", invalid="ignore"):
                    t = (sign * half[axis] - o_l[axis]) / d_l[:, axis]
                p = o_l + t[:, None] * d_l
                others = [a for a in range(3) if a != axis]
                inside = np.all(np.abs(p[:, others]) <= half[others] + 1e-12, axis=1) & (t > 1e-9)
                best = np.where(inside & (t < best), t, best)
    return best


def test_culled_ray_casting_agrees_with_brute_force() -> None:
    rng = np.random.default_rng(4)
    boxes = tuple(Box((float(rng.uniform(-0.3, 0.3)), float(rng.uniform(-0.3, 0.3))),
                      tuple(float(v) for v in rng.uniform(0.03, 0.2, 3)), float(rng.uniform(0, math.pi)))
                  for _ in range(6))
    scene = Scene(np.zeros(3), np.array([0.0, 0.0, 1.0]), boxes)  # type: ignore[arg-type]
    for origin in (np.array([0.0, 0.0, 0.8]), np.array([0.5, -0.4, 0.1])):
        dirs = rng.normal(size=(20000, 3))
        dirs[:, 2] = -np.abs(dirs[:, 2])
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        t, _, hit = scene.raycast(origin, dirs)
        ref = _slab_reference(origin, dirs, scene)
        np.testing.assert_array_equal(hit, np.isfinite(ref))
        np.testing.assert_allclose(t[hit], ref[hit], rtol=1e-12, atol=1e-12)
        # the boxes are really in the way of a good share of the rays (the plane is farther there)
        t_plane, _, _ = Scene(np.zeros(3), np.array([0.0, 0.0, 1.0])).raycast(origin, dirs)
        assert np.mean(t[hit] < t_plane[hit] - 1e-9) > 0.02
