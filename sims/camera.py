"""The ``sim`` camera: a simulated ifm O3R222-like 3D time-of-flight camera (:class:`SimCamera`).

224 x 172 px, 60° x 45° field of view, pinhole + Brown–Conrady distortion (OpenCV
conventions); it renders the shared simulated world from the arm's true camera pose,
with the ToF artefacts of ``[sim.artefacts]`` (:mod:`cellcal.sims.tof`). The pipeline is
documented on :meth:`SimCamera.render`; why the sim is built this way and where its
levels come from: docs/adr/0014-simulated-cell.md.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, NamedTuple, Self

import numpy as np
from numpy.typing import NDArray

from cellcal.devices.base import BackendContext
from cellcal.devices.errors import ConfigError
from cellcal.devices.geometry.camera_model import pixel_grid_rays
from cellcal.devices.measurement import MeasurementModel
from cellcal.devices.pose import Pose
from cellcal.devices.systematic import SystematicError, normalised_pixels
from cellcal.devices.types import DeviceInfo, Frame, Intrinsics

from .camera_shell import SimCameraShell
from .charuco import BoardTexture
from .mixed_pixels import PixelReturns, blend_edges
from .multipath import SurfacePoints, second_bounce
from .placement import PLATE_FACE
from .scene import Scene
from .systematic import SystematicConfig
from .tof import (
    SIGMA_AT_1M_M,
    SIGMA_DISTANCE_EXPONENT,
    amplitude_sigma_m,
    datasheet_sigma_m,
    drift_offset_m,
    noise_sigma_m,
    relative_amplitude,
    stated_tof_model,
)
from .world import SimWorld

__all__ = ["CONF_INVALID", "CONF_LOW_AMPLITUDE", "CONF_OUT_OF_RANGE", "CONF_SATURATED", "REPEATABILITY_SIGMAS",
           "SIGMA_AT_1M_M", "SIGMA_DISTANCE_EXPONENT", "SimCamera", "SimCameraConfig", "datasheet_sigma_m",
           "noise_sigma_m", "o3r222_intrinsics"]

#: Repeatability figures are read as this many sigma.
REPEATABILITY_SIGMAS = 2.0

#: Confidence bits (O3R meaning).
CONF_INVALID = 1
CONF_SATURATED = 2
CONF_LOW_AMPLITUDE = 8
CONF_OUT_OF_RANGE = 64


class _Cast(NamedTuple):
    """Centre-ray geometry of a frame, flattened (H*W,)."""

    range_m: NDArray[np.float64]  # true radial distance, NaN where nothing is hit
    cos_incidence: NDArray[np.float64]  # 0 where nothing is hit
    hit: NDArray[np.bool_]
    surface: NDArray[np.int32]
    normals: NDArray[np.float64]  # world frame, NaN where nothing is hit
    dirs: NDArray[np.float64]  # unit rays, world frame


def o3r222_intrinsics(width: int = 224, height: int = 172, fov_x_deg: float = 60.0, fov_y_deg: float = 45.0,
                      principal_offset_px: tuple[float, float] = (0.0, 0.0), **distortion: float) -> Intrinsics:
    """Pinhole intrinsics whose focal lengths reproduce a field of view.

    ``fx = (W/2) / tan(fov_x/2)`` (193.99 px for the defaults) and
    ``fy = (H/2) / tan(fov_y/2)`` (207.62 px); the principal point is the image centre
    ``((W-1)/2, (H-1)/2)`` plus ``principal_offset_px``.

    Args:
        width, height: Image size, px.
        fov_x_deg, fov_y_deg: Full field of view of the pinhole part, degrees.
        principal_offset_px: Principal point offset from the image centre, px.
        **distortion: OpenCV distortion coefficients by name (k1, k2, p1, p2, k3, ...).
    """
    fx = (width / 2.0) / math.tan(math.radians(fov_x_deg) / 2.0)
    fy = (height / 2.0) / math.tan(math.radians(fov_y_deg) / 2.0)
    return Intrinsics(width=width, height=height, fx=fx, fy=fy,
                      cx=(width - 1) / 2.0 + principal_offset_px[0], cy=(height - 1) / 2.0 + principal_offset_px[1],
                      **distortion)


@dataclass(frozen=True)
class SimCameraConfig:
    """Config of the ``sim`` camera backend (the ``[camera]`` table)."""

    width: int = field(default=224, metadata={"gt": 0, "le": 4096, "doc": "image width, px"})
    height: int = field(default=172, metadata={"gt": 0, "le": 4096, "doc": "image height, px"})
    fov_x_deg: float = field(default=60.0, metadata={"gt": 1.0, "lt": 179.0, "doc": "horizontal FoV, deg"})
    fov_y_deg: float = field(default=45.0, metadata={"gt": 1.0, "lt": 179.0, "doc": "vertical FoV, deg"})
    principal_offset_px: tuple[float, float] = field(
        default=(0.0, 0.0), metadata={"ge": -50.0, "le": 50.0, "doc": "principal point offset from the centre, px"})
    distortion: bool = field(default=True, metadata={"doc": "apply the lens distortion below (false: pinhole)"})
    k1: float = field(default=-0.06, metadata={"ge": -1.0, "le": 1.0, "doc": "radial distortion k1"})
    k2: float = field(default=0.015, metadata={"ge": -1.0, "le": 1.0, "doc": "radial distortion k2"})
    k3: float = field(default=0.0, metadata={"ge": -1.0, "le": 1.0, "doc": "radial distortion k3"})
    p1: float = field(default=4e-4, metadata={"ge": -0.1, "le": 0.1, "doc": "tangential distortion p1"})
    p2: float = field(default=-2e-4, metadata={"ge": -0.1, "le": 0.1, "doc": "tangential distortion p2"})
    noise: bool = field(default=True, metadata={"doc": "add distance noise"})
    noise_scale: float = field(default=1.0, metadata={"ge": 0.0, "le": 100.0, "doc": "noise sigma multiplier"})
    min_range_m: float = field(default=0.1, metadata={"ge": 0.0, "le": 100.0, "doc": "nearest valid distance, m"})
    max_range_m: float = field(default=4.0, metadata={"gt": 0.0, "le": 100.0, "doc": "farthest valid distance, m"})
    grazing_limit_deg: float = field(default=80.0, metadata={"gt": 0.0, "le": 90.0,
                                                             "doc": "max ray/normal angle of a valid pixel, deg"})
    quantisation_m: float = field(default=0.001, metadata={"ge": 0.0, "le": 0.1,
                                                           "doc": "distance step, m (0 = none)"})
    frame_rate_hz: float = field(default=20.0, metadata={"gt": 0.0, "le": 1000.0, "doc": "frame rate, Hz"})
    amplitude_at_1m: float = field(default=1000.0, metadata={
        "gt": 0.0, "doc": "amplitude of the reference target (reflectivity 0.5) at 1 m, normal"})
    seed: int | None = field(default=None, metadata={"ge": 0, "doc": "noise seed; default: the world's seed"})

    def __post_init__(self) -> None:
        if self.max_range_m <= self.min_range_m:
            raise ConfigError(f"max_range_m ({self.max_range_m}) must exceed min_range_m ({self.min_range_m})")

    def intrinsics(self) -> Intrinsics:
        """The intrinsics this config describes."""
        dist = {"k1": self.k1, "k2": self.k2, "k3": self.k3, "p1": self.p1, "p2": self.p2} if self.distortion else {}
        return o3r222_intrinsics(self.width, self.height, self.fov_x_deg, self.fov_y_deg,
                                 self.principal_offset_px, **dist)


class SimCamera(SimCameraShell):
    """Simulated O3R222-like ToF camera rendering the shared :class:`SimWorld`.

    Each pixel's unit ray comes from
    :func:`cellcal.devices.geometry.camera_model.pixel_grid_rays` of exactly the
    camera's intrinsics and the point is ``XYZ = ray * distance``, so a frame agrees
    with its intrinsics exactly. Noise stream, frame pacing, resume and fault injection
    (:attr:`fault_hook`; for ``o3r-emulated`` it runs on the emulator's server thread,
    the place to inject a wire fault into that very frame) are
    :class:`~cellcal.sims.camera_shell.SimCameraShell`'s.

    ``[camera] kind`` picks the sim camera: ``"tof"`` (default, this class) or ``"stereo"``
    (:class:`~cellcal.sims.stereo.SimStereoCamera`, an OAK-like stereo pair with its own
    keys, :class:`~cellcal.sims.stereo.SimStereoConfig`).

    Args:
        config: Backend config; None uses the defaults.
        context: Backend context (gives the shared world); None makes a private one.
        world: Use this world instead of the context's (emulators, tests).
    """

    backend_name = "sim"
    Config = SimCameraConfig

    @classmethod
    def from_config(cls, section: Mapping[str, Any] | None, context: BackendContext | None = None) -> Self:
        """As :meth:`Camera3D.from_config`; ``kind = "stereo"`` builds a :class:`~cellcal.sims.stereo.SimStereoCamera`.

        Raises:
            ConfigError: On a bad key or value, naming it (``camera.kind`` for an unknown kind).
        """
        rest = dict(section or {})
        kind = rest.pop("kind", "tof")
        where = (context.section if context is not None and context.section else "camera")
        if kind == "stereo" and cls is SimCamera:
            from .stereo import SimStereoCamera  # the stereo module imports this one

            return SimStereoCamera.from_config(section, context)  # type: ignore[return-value]
        if kind != "tof":
            raise ConfigError(f"must be one of tof, stereo, got {kind!r}", key=f"{where}.kind",
                              source=context.source if context is not None else None)
        return super().from_config(rest, context)

    def __init__(self, config: SimCameraConfig | None = None, context: BackendContext | None = None, *,
                 world: SimWorld | None = None) -> None:
        self.config = config or SimCameraConfig()
        super().__init__(context, world, self.config.seed, self.config.frame_rate_hz)
        self._intr = self.config.intrinsics()
        rays = pixel_grid_rays(self._intr)
        self._rays_cam = rays.reshape(-1, 3)
        self._ray_ok = np.all(np.isfinite(self._rays_cam), axis=1)
        self._rays_safe = np.where(self._ray_ok[:, None], self._rays_cam, np.array([0.0, 0.0, 1.0]))
        # Solid angle of each pixel, sr: cos^3 (angle to the optical axis) / (fx fy) (pinhole).
        self._solid_angle = np.where(self._ray_ok, self._rays_safe[:, 2] ** 3, 0.0) / (self._intr.fx * self._intr.fy)
        self._cos_grazing = math.cos(math.radians(self.config.grazing_limit_deg))
        self._board: BoardTexture | None = None
        self._systematic_of: SystematicConfig | None = None
        self._systematic_cache: tuple[SystematicError, NDArray[np.float64], NDArray[np.float64]] | None = None
        self._systematic_parts: tuple[SystematicError, NDArray[np.float64]] | None = None

    def systematic_error(self) -> tuple[SystematicError, NDArray[np.float64], NDArray[np.float64]]:
        """The world's systematic error for this camera and every pixel's normalised ``u``, ``v``, (H*W,) each."""
        table = self.world.systematic
        if self._systematic_cache is None or self._systematic_of is not table:
            intr = self._intr
            u, v = normalised_pixels(intr.width, intr.height, intr.cx, intr.cy)
            err = table.tof(intr.width, intr.height)
            self._systematic_cache = (err, u.ravel(), v.ravel())
            # scale and offset alone, and the field of every pixel, evaluated once (not per frame)
            head = dataclasses.replace(err, wiggle_cos_m=0.0, wiggle_sin_m=0.0, wiggle_period_m=0.0, field_order=0,
                                       field_coeffs=())
            self._systematic_parts = (head, err.field_at(u.ravel(), v.ravel()))
            self._systematic_of = table
        return self._systematic_cache

    def _distort_range(self, range_m: NDArray[np.float64]) -> NDArray[np.float64]:
        """:meth:`SystematicError.distort` of the true ranges (H*W,), m, with the field and the wiggle's phase cached.

        ``A cos(2πr/P - φ)`` is the model's ``a cos + b sin`` with ``a = A cos φ``, ``b = A sin φ`` (one cosine
        instead of two trigonometric passes: the wiggle was most of the systematic error's cost per frame).
        """
        self.systematic_error()
        assert self._systematic_parts is not None
        head, field_m = self._systematic_parts
        out = head.distort(range_m, 0.0, 0.0) + field_m
        table = self.world.systematic
        if table.wiggle_amplitude_m > 0.0 and table.wiggle_period_m > 0.0:
            phase = (2.0 * math.pi / table.wiggle_period_m) * range_m - math.radians(table.wiggle_phase_deg)
            out += table.wiggle_amplitude_m * np.cos(phase)
        return out

    # ------------------------------------------------------------------ rendering
    def render(self, camera_pose: Pose, *, timestamp: float | None = None, sequence: int = 0,
               flange_pose: Pose | None = None) -> Frame:
        """Render one frame from a camera pose (``T_base_camera``), without moving the arm.

        Draws noise from this camera's generator (so successive calls differ unless
        the noise is off). Usable before :meth:`connect`. The rays are rotated into the
        world by ``camera_pose``, cast against the scene (with the plate the arm holds at
        ``flange_pose``, :meth:`~cellcal.sims.world.SimWorld.scene_at`), and then, with the world's
        ``[sim.artefacts]`` (:class:`~cellcal.sims.tof.ArtefactsConfig`):

        * **return**: relative amplitude ``(rho / 0.5) cos θ / d²`` of the surface hit;
        * **multipath** (``multipath``): a second bounce off the other surfaces in view
          lengthens the range and changes the amplitude (:mod:`cellcal.sims.multipath`);
        * **mixed pixels** (``mixed_pixels``): a pixel near a depth edge returns the phasor
          blend of its (lens-blurred) footprint (:mod:`cellcal.sims.mixed_pixels`);
        * **systematic error** (``[sim.systematic]``, ADR 0054): the range becomes what the camera
          measures, ``(1 + range_scale_error)·r + range_offset_m + wiggle(r) + bow(u, v)``
          (:meth:`~cellcal.devices.systematic.SystematicError.distort`); the frame's
          ``metadata["sim_systematic"]`` carries that truth (benchmarks only);
        * **drift** (``temperature_drift``): a range offset decaying with warm-up time;
        * **noise**: Gaussian range noise of :func:`~cellcal.sims.tof.amplitude_sigma_m` of
          the return's amplitude with the ``[sim.artefacts]`` per-pixel and shot-noise terms
          (``amplitude_noise``; else the data-sheet law :func:`~cellcal.sims.tof.datasheet_sigma_m`),
          scaled by ``noise_scale``;
        * **quantisation**: the noisy distance is rounded to ``quantisation_m`` (1 mm);
        * **invalid pixels** (distance and XYZ NaN, ``valid`` False): no surface hit or no
          return, angle between ray and surface normal above ``grazing_limit_deg``,
          measured distance outside ``[min_range_m, max_range_m]``, and with
          ``amplitude_noise`` an amplitude below ``min_amplitude`` or above ``saturation_amplitude``;
        * **amplitude**: ``amplitude_at_1m`` times the relative amplitude (0 where no return);
        * **confidence**: an O3R-like uint16 image: bit 0 invalid, 2 saturated, 8 low
          amplitude (or grazing), 64 outside range.

        Args:
            camera_pose: Camera pose in the world/base frame.
            timestamp: Frame time, seconds since the epoch; None uses the simulated clock.
            sequence: Sequence number to stamp.
            flange_pose: True ``T_base_flange`` of the held plate (``[sim.plate]``); None: the flange's now.
        """
        h, w = self._intr.height, self._intr.width
        scene = self.world.scene_at(flange_pose)
        cast = self._cast(camera_pose, scene)
        ret = self._returns(camera_pose, cast, scene, flange_pose)
        d = self._measure(ret, cast)
        valid, conf = self._validity(d, ret.amplitude, cast)
        arte = self.world.artefacts
        # amplitude image; a saturated pixel reads the saturation level
        ceiling = arte.saturation_amplitude if arte.amplitude_noise else np.inf
        amp = np.minimum(ret.amplitude, ceiling) * self.config.amplitude_at_1m
        # Invalid pixels read NaN; XYZ is the exact pixel ray times the measured distance.
        dist = np.where(valid, d, np.nan)
        xyz = self._rays_cam * dist[:, None]
        return Frame(
            distance=dist.astype(np.float32).reshape(h, w),
            xyz=xyz.astype(np.float32).reshape(h, w, 3),
            amplitude=amp.astype(np.float32).reshape(h, w),
            valid=valid.reshape(h, w),
            intrinsics=self._intr,
            timestamp=self.world.clock.now() if timestamp is None else float(timestamp),
            sequence=int(sequence),
            confidence=conf.reshape(h, w),
            measurement=self._measurement_model(),
            # the truth, for benchmarks; no estimator reads it
            metadata={"sim_systematic": self.systematic_error()[0].to_dict()} if self.world.systematic.enabled else {},
        )

    def _cast(self, camera_pose: Pose, scene: Scene) -> _Cast:
        """Centre-ray geometry per pixel, (H*W,)."""
        # Pixel rays, camera frame -> world frame.
        r_wc = camera_pose.rotation_matrix
        dirs = self._rays_safe @ r_wc.T
        t, normal, hit, surface = scene.raycast_surfaces(camera_pose.translation, dirs)
        # Pixels without a defined ray never hit.
        hit &= self._ray_ok
        surface[~hit] = -1
        # cos θ between the ray and the surface normal (normals face the ray, rays are unit).
        cos_inc = np.where(hit, -np.einsum("ij,ij->i", normal, dirs), 0.0)
        return _Cast(np.where(hit, t, np.nan), cos_inc, hit, surface, normal, dirs)

    def _returns(self, camera_pose: Pose, cast: _Cast, scene: Scene, flange_pose: Pose | None = None
                 ) -> PixelReturns:
        """Effective range (m) and relative amplitude of each pixel's return, before noise (``flange_pose``: the
        true ``T_base_flange`` the held plate is drawn at; None: the flange's now)."""
        arte = self.world.artefacts
        # A lone plane has one surface: no depth edge (its horizon is beyond the grazing limit), no multipath.
        edges = scene.has_edges
        rho = scene.reflectivity(cast.surface) if edges else scene.plane_reflectivity
        board = self._board_texture()
        plate = self.world.plate
        if board is not None and board.config.on == "plate" and plate is not None:  # printed on the held plate
            flange = self.world.true_flange_pose() if flange_pose is None else flange_pose
            face = scene.solid_surface_ids(0)[PLATE_FACE]
            rho = board.reflectivity(camera_pose, cast.hit & (cast.surface == face), rho,
                                     board.config.pose_on_plate(flange @ plate.pose()))
        elif board is not None and board.config.on == "plane":  # a ChArUco board printed on the plane ([sim.charuco])
            rho = board.reflectivity(camera_pose, cast.hit & (cast.surface == 0), rho)
        t_safe = np.where(cast.hit, cast.range_m, 1.0)
        ret = PixelReturns(cast.range_m, np.where(cast.hit, relative_amplitude(t_safe, cast.cos_incidence, rho), 0.0))
        z = None
        if arte.multipath and edges:
            origin = np.asarray(camera_pose.translation, dtype=np.float64)
            seen = SurfacePoints(origin + cast.dirs * t_safe[:, None], np.where(cast.hit[:, None], cast.normals, 0.0),
                                 t_safe, cast.cos_incidence, np.broadcast_to(rho, t_safe.shape), self._solid_angle,
                                 cast.surface)
            z = second_bounce(seen, (self._intr.height, self._intr.width), arte)
        if arte.mixed_pixels and edges:
            h, w = self._intr.height, self._intr.width
            ret = blend_edges(ret, scene, camera_pose.translation, cast.dirs.reshape(h, w, 3),
                              cast.surface.reshape(h, w), arte)
        rng, amp = ret.range_m, ret.amplitude
        if z is not None and np.any(z):
            # the second bounce: phase of (direct + indirect) relative to the direct return
            rng = rng + np.angle(1.0 + z) / arte.wavenumber_rad_m
            amp = amp * np.abs(1.0 + z)
        if self.world.systematic.enabled:
            # what the camera measures of the (effective) range, before drift and noise
            rng = self._distort_range(rng)
        offset = drift_offset_m(arte, self.world.clock.elapsed_s)
        return PixelReturns(rng + offset if offset else rng, amp)

    def _board_texture(self) -> BoardTexture | None:
        """The world's ChArUco board as a texture for this camera's pixels (built once), or None."""
        config = self.world.charuco
        if config is None:
            return None
        if self._board is None or self._board.config is not config:
            scene = self.world.scene
            where = config.pose_on_plane(np.asarray(scene.plane_point_m, float), np.asarray(scene.plane_normal, float))
            self._board = BoardTexture(config, where, self._intr)
        return self._board

    def _measure(self, ret: PixelReturns, cast: _Cast) -> NDArray[np.float64]:
        """Measured radial distance, metres: effective range + noise, quantised."""
        cfg, arte = self.config, self.world.artefacts
        noise_draw = self._rng.standard_normal(ret.range_m.shape[0])  # drawn every frame: the stream stays aligned
        if cfg.noise and cfg.noise_scale > 0:
            if arte.amplitude_noise:
                sigma = amplitude_sigma_m(np.where(ret.amplitude > 0, ret.amplitude, 1.0), arte.noise_floor,
                                          cfg.noise_scale, shot_noise_at_1m_m=arte.shot_noise_at_1m_m,
                                          pixel_noise_m=arte.pixel_noise_m)
            else:  # the data-sheet law of the true distance and incidence (1 m, normal where nothing was hit)
                sigma = datasheet_sigma_m(np.where(cast.hit, cast.range_m, 1.0),
                                          np.where(cast.hit, cast.cos_incidence, 1.0), cfg.noise_scale)
            d = ret.range_m + sigma * noise_draw
        else:
            d = ret.range_m
        if cfg.quantisation_m > 0:
            # round to the distance step
            d = np.round(d / cfg.quantisation_m) * cfg.quantisation_m
        return d

    def _validity(self, d: NDArray[np.float64], amplitude: NDArray[np.float64], cast: _Cast
                  ) -> tuple[NDArray[np.bool_], NDArray[np.uint16]]:
        """Validity mask and O3R-like confidence bits per pixel from the measured distance ``d`` (m)."""
        cfg, arte = self.config, self.world.artefacts
        hit = cast.hit & (amplitude > 0)  # a pixel whose footprint returned no light has no measurement
        # Grazing: angle between ray and normal above the limit (cos below its cosine).
        low = hit & (cast.cos_incidence < self._cos_grazing)
        saturated = np.zeros_like(hit)
        if arte.amplitude_noise:
            low |= hit & (amplitude < arte.min_amplitude)
            saturated = hit & (amplitude > arte.saturation_amplitude)
        with np.errstate(invalid="ignore"):
            out_of_range = ~hit | (d < cfg.min_range_m) | (d > cfg.max_range_m)
        valid = hit & ~low & ~saturated & ~out_of_range
        conf = np.zeros(d.shape[0], dtype=np.uint16)
        conf[low] |= CONF_LOW_AMPLITUDE
        conf[saturated] |= CONF_SATURATED
        conf[out_of_range] |= CONF_OUT_OF_RANGE
        conf[~valid] |= CONF_INVALID
        return valid, conf

    # ------------------------------------------------------------------ backend hooks
    def _on_connect(self) -> None:
        self._board_texture()  # a ChArUco board's sub-rays are traced once, here, not in the first capture

    def _info(self) -> DeviceInfo:
        return DeviceInfo(backend="sim", vendor="cellcal (simulated ifm)", model="O3R222 (simulated)",
                          serial=f"SIM-{self.world.seed:08d}", firmware="sim",
                          extra={"frame_rate_hz": self.config.frame_rate_hz, "noise": self.config.noise,
                                 "distortion": self.config.distortion})

    def _intrinsics(self) -> Intrinsics:
        return self._intr

    def _configured_intrinsics(self) -> Intrinsics:
        return self._intr

    def _measurement_model(self) -> MeasurementModel:
        """ToF, with the noise law this camera draws from (:func:`~cellcal.sims.tof.stated_tof_model`)."""
        cfg = self.config
        return stated_tof_model(self.world.artefacts, noise=cfg.noise, noise_scale=cfg.noise_scale,
                                range_step_m=cfg.quantisation_m, systematic=self.world.systematic.enabled)

    def describe(self) -> dict[str, Any]:
        """Model parameters for reports."""
        return {"intrinsics": self._intr.to_dict(), "sigma_at_1m_m": SIGMA_AT_1M_M * self.config.noise_scale,
                "sigma_distance_exponent": SIGMA_DISTANCE_EXPONENT, "repeatability_sigmas": REPEATABILITY_SIGMAS,
                "artefacts": dataclasses.asdict(self.world.artefacts),
                "measurement": self._measurement_model().to_dict()}
