"""The simulated cell of several cameras (issue #40): placed cameras, ``[[sim.cameras]]`` truths, the held plate.

Noise-free frames (``noise = false``, no quantisation, ``[sim.artefacts]`` and ``[sim.systematic]`` off)
measure exactly what the scene holds, so the planes fitted from them agree with the truth to float32
rounding (micrometres); the tolerances below (1 mm, 0.5 mm, 0.1 deg) are far from that.
"""

from __future__ import annotations

import tomllib
from importlib import resources
from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray

from cellcal.core.calibration.build import build_cell, build_devices
from cellcal.core.calibration.config import load_config, parse_config
from cellcal.core.geometry.planes import Plane
from cellcal.core.handeye.fixed_plan import plate_poses
from cellcal.devices.base import BackendContext, CameraPlacement
from cellcal.devices.errors import ConfigError
from cellcal.devices.geometry.camera_model import pixel_grid_rays
from cellcal.devices.pose import Pose
from cellcal.sims.camera import SimCamera, SimCameraConfig
from cellcal.sims.camera_shell import SimCameraShell
from cellcal.sims.placement import PLATE_FACE, PlateConfig
from cellcal.sims.world import SimWorld, world_from_context

MOUNT = {"translation_m": [0.0, 0.04, 0.06], "rpy_deg": [0.0, 0.0, 90.0]}
#: A fixed camera 1.2 m over the working area looking straight down, and one at 45 deg from 0.9 m (configured).
ABOVE = Pose.from_xyz_rpy([0.3, 0.0, 1.2], np.radians([180.0, 0.0, 0.0]))
SIDE45 = Pose.from_xyz_rpy([0.3, -0.636396, 0.636396], np.radians([-135.0, 0.0, 0.0]))
#: The arm at start (tool down over the working area) and two other flange poses (base frame).
START = Pose.from_xyz_rpy([0.3, 0.0, 0.5], np.radians([180.0, 0.0, 0.0]))
MOVED = Pose.from_xyz_rpy([0.22, 0.06, 0.45], np.radians([180.0, 0.0, 25.0]))
TILTED = Pose.from_xyz_rpy([0.32, -0.04, 0.55], np.radians([165.0, 12.0, -20.0]))
#: Every artefact and systematic error off: the frames measure the scene exactly.
IDEAL: dict[str, Any] = {"artefacts": {"mixed_pixels": False, "multipath": False, "amplitude_noise": False,
                                       "temperature_drift": False}, "systematic": {"enabled": False}}
EXACT = SimCameraConfig(noise=False, quantisation_m=0.0)
PLATE = {"translation_m": [0.12, 0.0, 0.0]}


def _cell(sim: dict[str, Any], placements: list[CameraPlacement], config: SimCameraConfig = EXACT,
          seed: int = 3) -> tuple[SimWorld, SimCamera, dict[str, SimCamera]]:
    """One world: the driven camera (no placement) and a camera per placement, all connected."""
    doc = {"mount": MOUNT, "sim": sim}
    shared: dict[str, Any] = {}
    driven = SimCamera(config, BackendContext(document=doc, shared=shared, seed=seed, section="camera"))
    placed = {p.name: SimCamera(config, BackendContext(document=doc, shared=shared, seed=seed,
                                                       section=f"cameras.{p.name}", placement=p))
              for p in placements}
    for camera in (driven, *placed.values()):
        camera.connect()
    return driven.world, driven, placed


def _plate_mask(camera: SimCameraShell, flange: Pose) -> NDArray[np.bool_]:
    """Pixels whose centre ray meets the plate's measured face with the flange at ``flange`` (H*W,)."""
    world = camera.world
    rays = pixel_grid_rays(camera.intrinsics).reshape(-1, 3)
    ok = np.all(np.isfinite(rays), axis=1)
    pose = camera.camera_pose_at(flange)
    dirs = np.where(ok[:, None], rays, [0.0, 0.0, 1.0]) @ pose.rotation_matrix.T
    scene = world.scene_at(flange)
    _, _, hit, surface = scene.raycast_surfaces(pose.translation, dirs)
    out: NDArray[np.bool_] = ok & hit & (surface == scene.solid_surface_ids(0)[PLATE_FACE])
    return out


def _fit_plane(points: NDArray[np.float64]) -> tuple[NDArray[np.float64], float]:
    """Least-squares plane ``n·x + c = 0`` of points (N, 3) (SVD; the sign of n is arbitrary)."""
    centroid = points.mean(axis=0)
    normal = np.linalg.svd(points - centroid, full_matrices=False)[2][2]
    return normal, float(-normal @ centroid)


def _base_points(camera: SimCamera, xyz: NDArray[np.float32], mask: NDArray[np.bool_]) -> NDArray[np.float64]:
    """The camera-frame points of ``mask``'s pixels in the base frame (the camera's true pose now)."""
    pts = xyz.reshape(-1, 3)[mask].astype(np.float64)
    assert np.all(np.isfinite(pts))
    return camera.camera_pose().apply(pts)


def _pose(table: dict[str, Any]) -> Pose:
    return Pose.from_xyz_rpy(np.asarray(table["translation_m"]), np.radians(table["rpy_deg"]))


def test_a_fixed_camera_sees_the_plane_at_the_height_of_its_true_pose() -> None:
    truth = {"translation_m": [0.304, -0.003, 1.196], "rpy_deg": [180.3, 0.2, -0.4]}
    _, _, placed = _cell({**IDEAL, "cameras": [{"name": "above", **truth}]}, [CameraPlacement("above", "base", ABOVE)])
    above = placed["above"]
    true_pose = _pose(truth)
    assert above.camera_pose().is_close(true_pose, atol_m=1e-12, atol_rad=1e-12)  # the truth, not the configured
    frame = above.capture(1.0)
    pts = frame.xyz.reshape(-1, 3)[frame.valid.ravel()].astype(np.float64)
    assert len(pts) > 0.99 * frame.valid.size
    normal, offset = _fit_plane(pts)  # the table in the camera frame
    # its distance from the camera is the true height, 1.196 m (the configured pose says 1.2 m: 4 mm away)
    assert abs(abs(offset) - 1.196) < 1e-3
    expected = true_pose.rotation_matrix.T @ np.array([0.0, 0.0, 1.0])
    assert np.degrees(np.arccos(min(1.0, abs(float(normal @ expected))))) < 0.01


def test_a_fixed_camera_frame_changes_with_the_arm_only_where_the_plate_is() -> None:
    world, _, placed = _cell({**IDEAL, "plate": PLATE}, [CameraPlacement("above", "base", ABOVE)])
    above = placed["above"]
    world.arm.set_flange_pose(START)
    before = above.capture(1.0).distance.ravel()
    plate_before = _plate_mask(above, world.true_flange_pose())
    world.arm.set_flange_pose(MOVED)
    after = above.capture(1.0).distance.ravel()
    plate_after = _plate_mask(above, world.true_flange_pose())
    assert plate_before.sum() > 2000 and plate_after.sum() > 2000  # 0.2 x 0.15 m at 0.7 m: ~2900 px
    elsewhere = ~(plate_before | plate_after)
    np.testing.assert_array_equal(after[elsewhere], before[elsewhere])  # the table: bit for bit
    changed = ~np.isclose(after, before, atol=1e-4, equal_nan=True)
    assert changed.sum() > 1000 and not np.any(changed & elsewhere)


def _shown_to(camera_base: Pose, plate: PlateConfig, tilt_deg: float = 20.0) -> list[Pose]:
    """Flange poses that show the plate 0.6 m in front of a fixed camera, tilted two ways (core's plan)."""
    return plate_poses(camera_base, distance_m=0.6, plate_flange=Plane(*plate.face_plane()), tilts_deg=(tilt_deg,),
                       azimuths_deg=(0.0, 90.0), rolls_deg=(0.0, 90.0), plate_centre_flange_m=plate.translation_m)


def test_the_plate_is_seen_where_the_true_flange_pose_puts_it_and_moves_with_the_arm() -> None:
    placements = [CameraPlacement("above", "base", ABOVE), CameraPlacement("side45", "base", SIDE45)]
    world, _, placed = _cell({**IDEAL, "plate": PLATE}, placements)
    plate = world.plate
    assert plate is not None
    held: list[Pose] = []
    shown = [(START, "above"), (TILTED, "above"), *((pose, "side45") for pose in _shown_to(SIDE45, plate))]
    for flange, name in shown:
        camera = placed[name]
        world.arm.set_flange_pose(flange)
        true_flange = world.true_flange_pose()  # the arm's kinematic errors on: the plate is on the true flange
        frame = camera.capture(1.0)
        mask = _plate_mask(camera, true_flange)
        assert mask.sum() > 2000, name  # 0.2 x 0.15 m at 0.6-0.7 m: 2400-3200 px
        pts = _base_points(camera, frame.xyz, mask)
        normal, offset = _fit_plane(pts)
        expected_n, expected_c = plate.face_plane(true_flange)
        sign = np.sign(normal @ expected_n)
        assert np.degrees(np.arccos(min(1.0, float(sign * normal @ expected_n)))) < 0.1  # measured: 3e-6 deg
        assert abs(sign * offset - expected_c) < 5e-4  # measured: 1e-8 m
        # the face looks toward the camera, and its pixels cover the face's rectangle where the true flange holds it
        assert float(expected_n @ (camera.camera_pose().translation - pts.mean(axis=0))) > 0
        local = (true_flange @ plate.pose()).inv().apply(pts)
        assert np.all(np.abs(local) <= [plate.size_m[0] / 2 + 1e-5, plate.size_m[1] / 2 + 1e-5, 1e-5])
        assert np.all(np.ptp(local[:, :2], axis=0) > 0.9 * np.asarray(plate.size_m))  # measured: > 0.965
        held.append(true_flange @ plate.pose())
        if name == "above" and len(held) == 2:  # the arm moved: the plate left where it was
            assert float(np.max(np.abs(held[0].inv().apply(pts)[:, 2]))) > 0.02


def test_a_flange_camera_with_a_placement_renders_from_its_own_true_mount() -> None:
    own = {"translation_m": [0.05, -0.03, 0.07], "rpy_deg": [0.0, 5.0, -90.0]}  # its configured [cameras.mount]
    truth = {"translation_m": [0.052, -0.031, 0.071], "rpy_deg": [0.3, 5.2, -90.4]}  # its [[sim.cameras]] entry
    for sim, mount in (({}, own), ({"cameras": [{"name": "second", **truth}]}, truth)):
        world, driven, placed = _cell({**IDEAL, **sim}, [CameraPlacement("second", "flange", _pose(own))])
        # the same cell with that mount as [sim.mount]: the camera a run drives renders from it
        reference_world, reference, _ = _cell({**IDEAL, "mount": mount}, [])
        for flange in (START, TILTED):
            world.arm.set_flange_pose(flange)
            reference_world.arm.set_flange_pose(flange)
            second = placed["second"]
            assert second.camera_pose().is_close(world.true_flange_pose() @ _pose(mount), atol_m=1e-12,
                                                 atol_rad=1e-12)
            np.testing.assert_array_equal(second.camera_pose().as_matrix(), reference.camera_pose().as_matrix())
            ours, theirs = second.capture(1.0), reference.capture(1.0)
            np.testing.assert_array_equal(ours.distance, theirs.distance)  # the same frame, bit for bit
            # and not from the driven camera's mount
            assert not driven.camera_pose().is_close(second.camera_pose(), atol_m=1e-3, atol_rad=1e-3)


def test_each_camera_draws_its_own_noise_and_leaves_the_driven_cameras_alone() -> None:
    noisy = SimCameraConfig()
    placements = [CameraPlacement("one", "base", ABOVE), CameraPlacement("two", "base", ABOVE)]
    steady = {"artefacts": {"temperature_drift": False}}  # the shared clock runs on with more cameras capturing
    _, driven, placed = _cell(steady, placements, noisy)
    _, alone, _ = _cell(steady, [], noisy)
    a, b = placed["one"].capture(1.0).distance, placed["two"].capture(1.0).distance
    both = np.isfinite(a) & np.isfinite(b)
    assert both.sum() > 30000 and np.mean(a[both] != b[both]) > 0.5  # one pose, two noise streams
    for _ in range(2):  # the placed cameras capture between the driven camera's frames: its frames do not change
        placed["one"].capture(1.0)
        np.testing.assert_array_equal(driven.capture(1.0).distance, alone.capture(1.0).distance)


#: Frames of the packaged one-camera cells (seed 7) as they were before cameras could be placed (float32 values).
BEFORE = {"sim.toml": [(38528, [0.4390000104904175, 0.4729999899864197, 0.47099998593330383,
                                0.45399999618530273, 0.531000018119812]),
                       (38528, [0.4410000145435333, 0.4659999907016754, 0.46799999475479126,
                                0.45399999618530273, 0.5249999761581421])],
          "sim_oak.toml": [(255510, [0.4375259280204773, 0.474926233291626, 0.4762515723705292,
                                     0.4564673602581024, 0.5631833076477051]),
                           (255551, [0.43970993161201477, 0.4765014350414276, 0.4778338074684143,
                                     0.4549558758735657, 0.5631833076477051])]}


@pytest.mark.parametrize("name", sorted(BEFORE))
def test_without_a_placement_the_frames_are_what_they_were(name: str) -> None:
    camera, _ = build_devices(load_config(str(resources.files("cellcal.configs").joinpath(name))))
    camera.connect()
    for valid, pixels in BEFORE[name]:
        frame = camera.capture(1.0)
        h, w = frame.distance.shape
        at = [(h // 2, w // 2), (h // 4, w // 4), (3 * h // 4, 3 * w // 4), (h // 3, 2 * w // 3), (10, 10)]
        assert int(frame.valid.sum()) == valid
        # a micrometre: another noise draw moves these by millimetres
        np.testing.assert_allclose([float(frame.distance[p]) for p in at], pixels, rtol=0, atol=1e-6)


MULTI = resources.files("cellcal.configs").joinpath("sim_multi.toml")


def test_sim_multi_builds_three_cameras_that_connect_and_capture() -> None:
    config = load_config(str(MULTI))
    assert config.camera_name == "wrist"
    configured_plate = PlateConfig(size_m=config.plate.size_m, translation_m=config.plate.translation_m,
                                   rpy_deg=config.plate.rpy_deg)  # [plate]: as the cell believes the plate is
    cameras, arm = build_cell(config)
    assert list(cameras) == ["wrist", "above", "side45"]
    arm.connect()
    truths = {t["name"]: t for t in tomllib.loads(MULTI.read_text())["sim"]["cameras"]}
    worlds = set()
    for name, camera in cameras.items():
        camera.connect()
        frame = camera.capture(1.0)
        assert frame.valid.mean() > 0.95, name
        assert isinstance(camera, SimCameraShell)
        worlds.add(id(camera.world))
        if name == "wrist":  # the driven camera: [sim.mount] on the true flange
            assert camera.placement is None
            assert camera.camera_pose().is_close(camera.world.true_flange_pose() @ camera.world.mount)
            assert not _plate_mask(camera, camera.world.true_flange_pose()).any()  # the paddle is behind it
            continue
        assert camera.placement is not None and camera.placement.on == "base"
        assert camera.camera_pose().is_close(_pose(truths[name]), atol_m=1e-12, atol_rad=1e-12)
        assert camera.camera_pose().distance_to(camera.placement.pose) > 3e-3  # a few mm off the configured pose
        # the arm holds the plate before it (planned with the configured [plate], as `cellcal handeye` plans)
        camera.world.arm.set_flange_pose(_shown_to(camera.placement.pose, configured_plate)[1])
        assert _plate_mask(camera, camera.world.true_flange_pose()).sum() > 1000, name
    assert len(worlds) == 1  # one world for the three cameras


def test_the_wrist_camera_does_not_see_the_default_plate_at_the_plans_tilts() -> None:
    world, driven, _ = _cell({**IDEAL, "plate": {}}, [])
    for rpy in ([180.0, 0.0, 0.0], [170.0, 0.0, 0.0], [190.0, 0.0, 0.0], [180.0, 10.0, 45.0]):
        world.arm.set_flange_pose(Pose.from_xyz_rpy([0.3, 0.0, 0.5], np.radians(rpy)))
        assert not _plate_mask(driven, world.true_flange_pose()).any(), rpy
    assert PlateConfig().translation_m == (0.12, 0.0, 0.0)


def _multi_document(**sim: Any) -> dict[str, Any]:
    doc = tomllib.loads(MULTI.read_text())
    doc["sim"].update(sim)
    return doc


def test_a_truth_naming_no_placed_camera_is_one_line_naming_it() -> None:
    cameras = [*_multi_document()["sim"]["cameras"], {"name": "abvoe", "translation_m": [0.3, 0.0, 1.2]}]
    # the builder gives the cell's camera names: the typo is named exactly, the driven "wrist" is a camera
    placed, _ = build_cell(parse_config(_multi_document(cameras=cameras), "cell.toml"))
    with pytest.raises(ConfigError) as err:
        placed["above"].connect()
    assert err.value.key == "sim.cameras[3].name"
    assert "'abvoe' names no camera of the cell (its cameras: wrist, above, side45)" in str(err.value)
    assert "cell.toml" in str(err.value) and "\n" not in str(err.value)
    # without the typo the cell connects; without the names (a world built directly), a world whose cameras are all
    # placed allows no unnamed one
    placed, _ = build_cell(parse_config(_multi_document(), "cell.toml"))
    placed["above"].connect()
    world = world_from_context(BackendContext(document=_multi_document()))
    world.place_camera(CameraPlacement("above", "base", ABOVE))
    world.place_camera(CameraPlacement("side45", "base", SIDE45))
    with pytest.raises(ConfigError, match="'wrist' name no camera") as err:
        world.check_camera_truths("cell.toml")
    assert err.value.key == "sim.cameras[0].name"


@pytest.mark.parametrize(("entries", "key"), [
    ([{"name": "above"}, {"name": "above"}], "sim.cameras[1].name"),
    ([{"name": "above", "translation_m": [0.0, 0.0, 30.0]}], "sim.cameras[0].translation_m"),
    ([{"translation_m": [0.0, 0.0, 1.0]}], "sim.cameras[0].name"),
])
def test_bad_sim_cameras_are_one_line(entries: list[dict[str, Any]], key: str) -> None:
    with pytest.raises(ConfigError) as err:
        world_from_context(BackendContext(source="cell.toml", document={"sim": {"cameras": entries}}))
    assert err.value.key == key and "cell.toml" in str(err.value)


def test_a_placed_stereo_camera_renders_from_its_pose_and_sees_the_plate() -> None:
    doc = {"mount": MOUNT, "sim": {**IDEAL, "plate": PLATE}}
    section = {"kind": "stereo", "noise": False, "speckle_fraction": 0.0, "subpixel_bits": 8}
    context = BackendContext(document=doc, section="cameras.above", placement=CameraPlacement("above", "base", ABOVE))
    camera = SimCamera.from_config(section, context)
    camera.connect()
    frame = camera.capture(1.0)
    assert camera.camera_pose().is_close(ABOVE, atol_m=1e-12, atol_rad=1e-12)
    mask = _plate_mask(camera, camera.world.true_flange_pose())
    assert mask.sum() > 5000  # 640 x 400 px at 72 deg: the plate covers ~6 % of the image
    table = frame.valid.ravel() & ~mask
    # Z-depth of the table is the height, 1.2 m (disparity steps of 1/256 px: 0.2 mm), of the plate 0.7 m
    assert abs(float(np.median(frame.xyz.reshape(-1, 3)[table, 2])) - 1.2) < 1e-3
    plate_z = frame.xyz.reshape(-1, 3)[mask & frame.valid.ravel(), 2]
    expected = 1.2 - camera.world.true_flange_pose().translation[2]
    assert abs(float(np.median(plate_z)) - expected) < 1e-3
