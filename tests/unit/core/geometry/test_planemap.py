"""PlaneMap: pixel <-> point on the measuring plane, camera and base frames."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from cellcal.core.calibration.config import look_at_pose
from cellcal.core.geometry.planemap import PlaneMap
from cellcal.core.geometry.planes import Plane
from cellcal.devices.errors import CalibrationError
from cellcal.devices.geometry.camera_model import pixel_rays
from cellcal.devices.pose import Pose
from cellcal.devices.types import Intrinsics
from cellcal.sims.camera import SimCamera, SimCameraConfig, o3r222_intrinsics
from cellcal.sims.scene import Box, Scene
from cellcal.sims.systematic import SystematicConfig
from cellcal.sims.world import SimWorld

# ~23-27 px shift at the image corners: strong for a 224 x 172 ToF lens
BROWN_CONRADY = {"k1": -0.3, "k2": 0.1, "k3": -0.02, "p1": 1e-3, "p2": -1e-3}
RATIONAL = {"k1": 0.5, "k2": -0.1, "k4": 0.8, "k5": 0.05, "p1": 5e-4, "s1": 1e-3}
LENSES = {"pinhole": {}, "brown_conrady": BROWN_CONRADY, "rational": RATIONAL}


def full_grid(intr: Intrinsics) -> np.ndarray:
    vv, uu = np.mgrid[0:intr.height, 0:intr.width]
    return np.stack([uu, vv], axis=-1).astype(np.float64)


def tilted_plane(distance_m: float = 0.6, tilt_deg: float = 10.0) -> Plane:
    t = math.radians(tilt_deg)
    return Plane.from_point_normal([0.0, 0.0, distance_m], [0.0, -math.sin(t), -math.cos(t)])


@pytest.mark.parametrize("lens", sorted(LENSES))
def test_pixel_plane_pixel_round_trip_over_the_full_image(lens: str) -> None:
    intr = o3r222_intrinsics(**LENSES[lens])
    pm = PlaneMap(intr, tilted_plane())
    uv = full_grid(intr)
    pts = pm.pixel_to_camera(uv)
    assert pts.shape == (intr.height, intr.width, 3)
    assert np.all(np.isfinite(pts))
    assert np.max(np.abs(pm.plane_cam.signed_distance(pts))) < 1e-12
    back = pm.camera_to_pixel(pts)
    err = np.max(np.abs(back - uv))
    assert err < 1e-6, f"round trip {err:.3g} px"
    # the four corners, where the distortion is strongest, and sub-pixel positions
    rng = np.random.default_rng(3)
    sub = rng.uniform([-0.5, -0.5], [intr.width - 0.5, intr.height - 0.5], size=(500, 2))
    corners = np.array([[0, 0], [intr.width - 1, 0], [0, intr.height - 1], [intr.width - 1, intr.height - 1]], float)
    for px in (sub, corners):
        assert np.max(np.abs(pm.camera_to_pixel(pm.pixel_to_camera(px)) - px)) < 1e-6


def test_distortion_is_really_honoured() -> None:
    """The corner's point differs from the pinhole model's by far more than the round-trip error."""
    intr = o3r222_intrinsics(**BROWN_CONRADY)
    pinhole = o3r222_intrinsics()
    corner = np.array([0.0, 0.0])
    p_dist = PlaneMap(intr, tilted_plane()).pixel_to_camera(corner)
    p_pin = PlaneMap(pinhole, tilted_plane()).pixel_to_camera(corner)
    assert np.linalg.norm(p_dist - p_pin) > 0.05  # metres at ~0.6 m
    # and it agrees with the camera model's own ray
    ray = pixel_rays(intr, corner)[0]
    assert np.allclose(np.cross(p_dist, ray), 0.0, atol=1e-12)


@pytest.mark.parametrize("lens", ["brown_conrady", "rational"])
def test_pixel_to_base_equals_the_sim_ray_cast(lens: str) -> None:
    intr = o3r222_intrinsics(**LENSES[lens])
    scene = Scene(np.array([0.0, 0.0, 0.02]), np.array([0.05, -0.03, 1.0]))
    camera_in_base = look_at_pose(np.array([0.3, 0.05, 0.0]), np.array([0.0, 0.0, 1.0]), 0.55,
                                  math.radians(75.0), "x") @ Pose.from_xyz_rpy([0, 0, 0], [0.0, 0.0, 0.3])
    uv = full_grid(intr).reshape(-1, 2)
    # independent truth: the scene's own ray cast along the camera model's rays, in the base frame
    dirs = camera_in_base.apply_vector(pixel_rays(intr, uv))
    t, _, hit = scene.raycast(camera_in_base.translation, dirs)
    truth = camera_in_base.translation + t[:, None] * dirs
    plane_base = Plane.from_point_normal(scene.plane_point_m, scene.plane_normal)
    pm = PlaneMap.from_base_plane(intr, plane_base, camera_in_base)
    got = pm.pixel_to_base(uv)
    assert hit.all()
    assert np.max(np.linalg.norm(got - truth, axis=1)) < 1e-9
    back = pm.base_to_pixel(got)
    assert np.max(np.abs(back - uv)) < 1e-6


def test_pixel_to_camera_matches_a_rendered_noise_free_sim_frame() -> None:
    cfg = SimCameraConfig(noise=False, quantisation_m=0.0)  # the sim's default distorted lens
    scene = Scene(np.zeros(3), np.array([0.0, 0.0, 1.0]), (Box((0.5, 0.3), (0.05, 0.05, 0.05)),))
    cam = SimCamera(cfg, world=SimWorld(scene, Pose.identity(), systematic=SystematicConfig.off()))  # ideal range
    camera_in_base = look_at_pose(np.array([0.3, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]), 0.46,
                                  math.radians(80.0), "x")
    frame = cam.render(camera_in_base)
    pm = PlaneMap.from_base_plane(frame.intrinsics, Plane.from_point_normal([0, 0, 0], [0, 0, 1]), camera_in_base)
    pts = pm.pixel_to_camera(full_grid(frame.intrinsics))
    on_plane = frame.valid
    assert on_plane.mean() > 0.9
    err = np.linalg.norm(pts[on_plane] - frame.xyz[on_plane].astype(np.float64), axis=1)
    assert err.max() < 1e-6  # float32 storage of the frame
    base = pm.pixel_to_base(full_grid(frame.intrinsics))
    assert np.max(np.abs(base[on_plane][:, 2])) < 1e-12  # z = 0 in the base frame


def test_base_and_camera_frames_agree() -> None:
    intr = o3r222_intrinsics(**BROWN_CONRADY)
    camera_in_base = Pose.from_xyz_rpy([0.3, -0.1, 0.5], [math.pi - 0.2, 0.1, 0.7])
    plane_base = Plane.from_point_normal([0.0, 0.0, 0.01], [0.02, 0.01, 1.0])
    pm = PlaneMap.from_base_plane(intr, plane_base, camera_in_base)
    uv = np.random.default_rng(1).uniform([0, 0], [intr.width - 1, intr.height - 1], size=(7, 9, 2))
    cam = pm.pixel_to_camera(uv)
    base = pm.pixel_to_base(uv)
    assert base.shape == (7, 9, 3)
    assert np.allclose(base.reshape(-1, 3), camera_in_base.apply(cam.reshape(-1, 3)), atol=1e-12)
    assert np.max(np.abs(plane_base.signed_distance(base))) < 1e-12
    assert np.allclose(pm.plane_base.normal, plane_base.normal) and pm.plane_base.offset_m == pytest.approx(
        plane_base.offset_m, abs=1e-12)
    assert np.max(np.abs(pm.base_to_pixel(base) - uv)) < 1e-6
    assert np.allclose(pm.base_to_pixel(base), pm.camera_to_pixel(cam), atol=1e-9)
    # moving the camera: the same base-frame plane, new pixels, same base points where visible
    moved = pm.with_camera_pose(camera_in_base @ Pose.from_xyz_rpy([0.02, 0.0, 0.0], [0.0, 0.05, 0.0]))
    uv2 = moved.base_to_pixel(base)
    assert not np.allclose(uv2, uv)
    assert np.allclose(moved.pixel_to_base(uv2), base, atol=1e-9)


@settings(max_examples=60, deadline=None)
@given(st.floats(-0.6, 0.6), st.floats(-0.6, 0.6), st.floats(0.2, 2.0),
       st.floats(0.0, 223.0), st.floats(0.0, 171.0))
def test_round_trip_property(tilt_x: float, tilt_y: float, dist: float, u: float, v: float) -> None:
    intr = o3r222_intrinsics(**BROWN_CONRADY)
    n = Rotation.from_euler("xy", [tilt_x, tilt_y]).apply([0.0, 0.0, -1.0])
    pm = PlaneMap(intr, Plane.from_point_normal([0.0, 0.0, dist], n))
    p = pm.pixel_to_camera([u, v])
    assert p.shape == (3,)
    if np.all(np.isfinite(p)):
        assert p[2] > 0
        assert np.max(np.abs(pm.camera_to_pixel(p) - [u, v])) < 1e-6
    else:  # only when the ray misses the plane
        assert pm.rays_cam([u, v]) @ pm.plane_cam.normal >= -1e-15 or pm.plane_cam.offset_m < 0


def test_rays_parallel_or_away_from_the_plane_give_nan() -> None:
    intr = o3r222_intrinsics(**BROWN_CONRADY)
    # a wall at x = 0.1 m: only rays with x > 0 reach it
    pm = PlaneMap(intr, Plane(np.array([-1.0, 0.0, 0.0]), 0.1))
    uv = full_grid(intr)
    pts = pm.pixel_to_camera(uv)
    rays = pm.rays_cam(uv)
    hits = np.all(np.isfinite(pts), axis=-1)
    assert np.array_equal(hits, rays[..., 0] > 0)
    assert 0.3 < hits.mean() < 0.7
    assert np.allclose(pts[hits][:, 0], 0.1)
    # a plane behind the camera: nothing
    behind = PlaneMap(intr, Plane(np.array([0.0, 0.0, 1.0]), 0.5))  # z = -0.5
    assert np.all(np.isnan(behind.pixel_to_camera(uv)))
    # NaN in -> NaN out, and points behind the camera have no pixel
    assert np.all(np.isnan(pm.pixel_to_camera([np.nan, 3.0])))
    out = pm.camera_to_pixel([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0], [np.nan, 0.0, 1.0]])
    assert np.all(np.isnan(out[0])) and np.allclose(out[1], [intr.cx, intr.cy]) and np.all(np.isnan(out[2]))
    assert pm.pixel_to_camera(np.empty((0, 2))).shape == (0, 3)


def test_in_image() -> None:
    pm = PlaneMap(o3r222_intrinsics(), tilted_plane())
    assert pm.in_image([[0, 0], [223, 171], [-1, 5], [5, 172], [np.nan, 1]]).tolist() == [
        True, True, False, False, False]


@pytest.mark.parametrize(("call", "arg", "message"), [
    ("pixel_to_camera", np.zeros((4, 3)), r"pixels must have shape \(\.\.\., 2\), got \(4, 3\)"),
    ("pixel_to_camera", 5.0, r"pixels must have shape"),
    ("pixel_to_camera", [["a", "b"]], r"pixels must be numeric"),
    ("camera_to_pixel", np.zeros((4, 2)), r"camera-frame points must have shape \(\.\.\., 3\)"),
    ("base_to_pixel", np.zeros(2), r"base-frame points must have shape"),
])
def test_bad_input_gives_one_line_errors(call: str, arg: object, message: str) -> None:
    pm = PlaneMap(o3r222_intrinsics(), tilted_plane(), Pose.identity())
    with pytest.raises(CalibrationError, match=message) as info:
        getattr(pm, call)(arg)
    assert "\n" not in str(info.value)


def test_base_frame_needs_a_camera_pose() -> None:
    pm = PlaneMap(o3r222_intrinsics(), tilted_plane())
    for call, arg in (("pixel_to_base", [1.0, 2.0]), ("base_to_pixel", [0.0, 0.0, 1.0])):
        with pytest.raises(CalibrationError, match="no camera pose in the base frame"):
            getattr(pm, call)(arg)
    with pytest.raises(CalibrationError, match="no camera pose"):
        _ = pm.plane_base
    with pytest.raises(CalibrationError, match="must be a Plane"):
        PlaneMap(o3r222_intrinsics(), "plane")  # type: ignore[arg-type]


def test_from_pose_record_and_document_errors() -> None:
    intr = o3r222_intrinsics(**BROWN_CONRADY)
    cam = Pose.from_xyz_rpy([0.3, 0.0, 0.5], [math.pi, 0.0, 0.0])
    plane_cam = tilted_plane()
    record = {"camera_intrinsics": intr.to_dict(), "camera_pose": cam.to_dict(),
              "full_frame": {"plane_cam": {"normal": plane_cam.normal.tolist(), "offset_m": plane_cam.offset_m}}}
    pm = PlaneMap.from_pose_record(record)
    assert pm.intrinsics == intr and pm.camera_in_base is not None and pm.camera_in_base.is_close(cam)
    uv = np.array([[10.0, 20.0], [200.0, 150.0]])
    assert np.allclose(pm.pixel_to_camera(uv), PlaneMap(intr, plane_cam).pixel_to_camera(uv), atol=1e-12)
    doc = {"poses": [record], "summary": {"plane_consistency": {
        "consensus_plane_base": {"normal": pm.plane_base.normal.tolist(), "offset_m": pm.plane_base.offset_m}}}}
    other = cam @ Pose.from_xyz_rpy([0.01, 0.0, 0.0], [0.0, 0.0, 0.1])
    cons = PlaneMap.from_document(doc, camera_in_base=other)
    assert np.allclose(cons.pixel_to_base(cons.base_to_pixel(pm.pixel_to_base(uv))), pm.pixel_to_base(uv), atol=1e-9)
    assert np.allclose(PlaneMap.from_document(doc, pose_index=0).pixel_to_base(uv), pm.pixel_to_base(uv))
    with pytest.raises(CalibrationError, match="needs the camera's current"):
        PlaneMap.from_document(doc)
    with pytest.raises(CalibrationError, match="out of range"):
        PlaneMap.from_document(doc, pose_index=3)
    with pytest.raises(CalibrationError, match="no 'full_frame' plane"):
        PlaneMap.from_pose_record({"camera_pose": cam.to_dict()})
    with pytest.raises(CalibrationError, match="no camera_intrinsics"):
        PlaneMap.from_pose_record({k: v for k, v in record.items() if k != "camera_intrinsics"})
