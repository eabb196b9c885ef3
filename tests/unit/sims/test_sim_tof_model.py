"""The simulated ToF cameras state their measurement model, and it describes the noise they draw."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cellcal.devices.base import BackendContext
from cellcal.devices.pose import Pose
from cellcal.sims.camera import SimCamera, SimCameraConfig
from cellcal.sims.o3r.backend import EmulatedO3RCamera, EmulatedO3RConfig
from cellcal.sims.scene import Scene
from cellcal.sims.tof import (
    DATASHEET_FIT_NOISE,
    STATED_COS,
    STATED_RANGE_M,
    ArtefactsConfig,
    noise_sigma_m,
)
from cellcal.sims.world import SimWorld

DOWN = Rotation.from_euler("x", 180.0, degrees=True)


def looking_down(height_m: float) -> Pose:
    return Pose(DOWN, np.array([0.0, 0.0, height_m]))


def make(artefacts: ArtefactsConfig | None = None, height_m: float = 0.8, **cfg: object) -> SimCamera:
    world = SimWorld(Scene(), Pose.identity(), flange_pose=looking_down(height_m), seed=2, artefacts=artefacts)
    return SimCamera(SimCameraConfig(**cfg), world=world)  # type: ignore[arg-type]


@pytest.mark.parametrize(("noise", "exponent", "bounds"), [
    ({}, (0.2, 0.5), (0.75, 1.3)),  # the defaults, set against the real O3R frame: nearly flat in range
    (DATASHEET_FIT_NOISE, (0.9, 1.3), (0.85, 1.1)),  # the earlier defaults: the amplitude law fitted to the data sheet
])
def test_camera_states_tof_with_a_law_close_to_the_noise_it_draws(
        noise: dict[str, float], exponent: tuple[float, float], bounds: tuple[float, float]) -> None:
    arte = ArtefactsConfig(**noise)
    model = make(arte).measurement_model
    assert (model.kind, model.source, model.range_step_m) == ("tof", "sim", 0.001)
    assert model.sigma_at_1m_m is not None and exponent[0] < model.distance_exponent < exponent[1]
    # the stated power law against the amplitude law it summarises, over the stated ranges and incidences
    d, c = np.meshgrid(np.geomspace(*STATED_RANGE_M, 30), np.linspace(*STATED_COS, 8))
    drawn = noise_sigma_m(d, c, noise_floor=arte.noise_floor, shot_noise_at_1m_m=arte.shot_noise_at_1m_m,
                          pixel_noise_m=arte.pixel_noise_m)
    ratio = model.range_sigma_m(d, c) / np.sqrt(drawn**2 + 0.001**2 / 12.0)
    assert ratio.min() > bounds[0] and ratio.max() < bounds[1]
    assert np.exp(np.mean(np.log(ratio))) == pytest.approx(1.0, abs=0.05)
    # and the frames show the drawn law: a window on the axis, 40 frames, noise per pixel
    cam = make(arte, quantisation_m=0.0)
    window = (slice(80, 92), slice(106, 118))
    stack = np.array([cam.render(looking_down(0.8)).distance[window] for _ in range(40)], dtype=np.float64)
    measured = float(np.sqrt(np.mean(stack.std(axis=0, ddof=1) ** 2)))
    assert measured == pytest.approx(float(noise_sigma_m(0.8, 1.0, noise_floor=arte.noise_floor,
                                                         shot_noise_at_1m_m=arte.shot_noise_at_1m_m,
                                                         pixel_noise_m=arte.pixel_noise_m)), rel=0.06)


def test_datasheet_law_is_stated_exactly_and_frames_show_it() -> None:
    arte = ArtefactsConfig(amplitude_noise=False)
    cam = make(arte, quantisation_m=0.0, noise_scale=2.0)
    model = cam.measurement_model
    assert model.sigma_at_1m_m == pytest.approx(2.0 * 0.0032) and model.distance_exponent == 1.5
    pose = looking_down(0.8)
    window = (slice(80, 92), slice(106, 118))  # on the axis: cos(incidence) > 0.999
    stack = np.array([cam.render(pose).distance[window] for _ in range(40)], dtype=np.float64)
    measured = float(np.sqrt(np.mean(stack.std(axis=0, ddof=1) ** 2)))
    assert measured == pytest.approx(float(model.range_sigma_m(0.8)), rel=0.06)


def test_a_noise_free_camera_states_no_sigma_and_scale_zero_neither() -> None:
    for cam in (make(noise=False), make(noise_scale=0.0)):
        model = cam.measurement_model
        assert model.kind == "tof" and model.sigma_at_1m_m is None and model.range_sigma_m(1.0) is None
        frame = cam.render(looking_down(0.8))
        assert frame.measurement == model


def test_frames_carry_the_model_and_a_config_override_replaces_it() -> None:
    world = SimWorld(Scene(), Pose.identity(), flange_pose=looking_down(0.6), seed=1)
    context = BackendContext(section="camera", shared={"sim.world": world})
    cam = SimCamera.from_config({"noise_scale": 1.5}, context)
    with cam:
        frame = cam.capture()
    assert frame.measurement == cam.measurement_model and frame.measurement.source == "sim"
    assert frame.measurement.sigma_at_1m_m == pytest.approx(1.5 * make().measurement_model.sigma_at_1m_m)
    over = SimCamera.from_config({"model": {"kind": "tof", "sigma_at_1m_m": 0.01}}, context)
    with over:
        assert over.capture().measurement.sigma_at_1m_m == 0.01


def test_emulated_o3r_states_the_simulated_cameras_tof_model() -> None:
    world = SimWorld(Scene(), Pose.identity(), flange_pose=looking_down(0.6), seed=1)
    cam = EmulatedO3RCamera(EmulatedO3RConfig(noise_scale=0.5), BackendContext(shared={"sim.world": world}))
    model = cam.measurement_model  # stated without a connection
    assert model.kind == "tof" and model == cam.sim.measurement_model
    assert model.sigma_at_1m_m == pytest.approx(0.5 * make().measurement_model.sigma_at_1m_m)
    # its frames carry the sim's model, not the driver's data-sheet one: the noise on the wire is the sim's
    with cam:
        assert cam.capture().measurement == model
