"""The ``sim`` camera: a simulated ifm O3R222-like 3D time-of-flight camera (:class:`SimCamera`).

224 x 172 px, 60° x 45° field of view, pinhole + Brown–Conrady distortion (OpenCV
conventions); it renders the shared simulated world from the arm's true camera pose.
The noise, validity and confidence model is documented on :meth:`SimCamera.render`;
why the sim is built this way: docs/adr/0014-simulated-cell.md.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cellcal.devices.base import BackendContext
from cellcal.devices.camera import Camera3D
from cellcal.devices.errors import ConfigError
from cellcal.devices.geometry.camera_model import pixel_grid_rays
from cellcal.devices.pose import Pose
from cellcal.devices.types import DeviceInfo, Frame, Intrinsics

from .world import SimWorld, world_from_context

#: Distance-noise sigma at 1 m, normal incidence, metres.
SIGMA_AT_1M_M = 0.0032
#: Exponent of the distance in the noise model.
SIGMA_DISTANCE_EXPONENT = 1.5
#: Repeatability figures are read as this many sigma.
REPEATABILITY_SIGMAS = 2.0

#: Confidence bits (O3R meaning).
CONF_INVALID = 1
CONF_LOW_AMPLITUDE = 8
CONF_OUT_OF_RANGE = 64


def noise_sigma_m(distance_m: ArrayLike, cos_incidence: ArrayLike = 1.0, noise_scale: float = 1.0
                  ) -> NDArray[np.float64]:
    """Standard deviation (m) of the simulated radial-distance noise.

    ``sigma = noise_scale * 3.2 mm * (d / 1 m)**1.5 / sqrt(cos θ)``, θ the angle between
    the ray and the surface normal. Reading ifm's quoted repeatability as **2 sigma** at
    normal incidence, this gives 2.3 mm at 0.6 m, 6.4 mm at 1 m (quoted < 7 mm under
    1 m), 11.8 mm at 1.5 m and 18.1 mm at 2 m (quoted ~15 mm at 1–2 m) and 51 mm at 4 m
    (quoted up to 51 mm beyond 4 m).

    Args:
        distance_m: True radial distance, metres.
        cos_incidence: Cosine of the angle between ray and surface normal (0..1].
        noise_scale: Multiplier (0 = noise-free).
    """
    d = np.asarray(distance_m, dtype=np.float64)
    c = np.clip(np.asarray(cos_incidence, dtype=np.float64), 1e-6, 1.0)
    if SIGMA_DISTANCE_EXPONENT == 1.5:  # d**1.5 via sqrt: several times faster than pow
        out: NDArray[np.float64] = (noise_scale * SIGMA_AT_1M_M) * d * np.sqrt(d / c)
    else:  # pragma: no cover - kept for anyone changing the exponent
        out = noise_scale * SIGMA_AT_1M_M * d**SIGMA_DISTANCE_EXPONENT / np.sqrt(c)
    return out


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
    amplitude_at_1m: float = field(default=1000.0, metadata={"gt": 0.0, "doc": "amplitude at 1 m, normal"})
    seed: int | None = field(default=None, metadata={"ge": 0, "doc": "noise seed; default: the world's seed"})

    def __post_init__(self) -> None:
        if self.max_range_m <= self.min_range_m:
            raise ConfigError(f"max_range_m ({self.max_range_m}) must exceed min_range_m ({self.min_range_m})")

    def intrinsics(self) -> Intrinsics:
        """The intrinsics this config describes."""
        dist = {"k1": self.k1, "k2": self.k2, "k3": self.k3, "p1": self.p1, "p2": self.p2} if self.distortion else {}
        return o3r222_intrinsics(self.width, self.height, self.fov_x_deg, self.fov_y_deg,
                                 self.principal_offset_px, **dist)


class SimCamera(Camera3D):
    """Simulated O3R222-like ToF camera rendering the shared :class:`SimWorld`.

    Each pixel's unit ray comes from
    :func:`cellcal.devices.geometry.camera_model.pixel_grid_rays` of exactly the
    camera's intrinsics and the point is ``XYZ = ray * distance``, so a frame agrees
    with its intrinsics exactly. Randomness comes from one numpy Generator per camera,
    seeded from the config's ``seed`` or the world's seed, so equal seeds give
    identical frame sequences. Frames are paced by the simulated clock: each capture
    advances it to the next frame period (``1 / frame_rate_hz``) and stamps the frame
    with the simulated time.

    Fault injection (tests): :attr:`fault_hook`, if set, is called as
    ``hook("connect", n)`` on the n-th connect and ``hook("capture", n)`` before the
    n-th frame is rendered, on the thread that captures (an emulator's server thread
    for ``o3r-emulated``, where it is the place to inject a wire fault into that very
    frame).

    Args:
        config: Backend config; None uses the defaults.
        context: Backend context (gives the shared world); None makes a private one.
        world: Use this world instead of the context's (emulators, tests).
    """

    backend_name = "sim"
    Config = SimCameraConfig

    def __init__(self, config: SimCameraConfig | None = None, context: BackendContext | None = None, *,
                 world: SimWorld | None = None) -> None:
        super().__init__()
        self.config = config or SimCameraConfig()
        self.world = world if world is not None else world_from_context(context)
        self._intr = self.config.intrinsics()
        rays = pixel_grid_rays(self._intr)
        self._rays_cam = rays.reshape(-1, 3)
        self._ray_ok = np.all(np.isfinite(self._rays_cam), axis=1)
        self._rays_safe = np.where(self._ray_ok[:, None], self._rays_cam, np.array([0.0, 0.0, 1.0]))
        self._rng = self.world.rng("camera", self.config.seed)
        self._lock = threading.Lock()
        self._sequence = 0
        self._last_frame_elapsed: float | None = None
        self._cos_grazing = math.cos(math.radians(self.config.grazing_limit_deg))
        #: Fault-injection hook ``hook(event, n)``, see the class docstring.
        self.fault_hook: Callable[[str, int], None] | None = None
        self.connects = 0

    # ------------------------------------------------------------------ rendering
    def render(self, camera_pose: Pose, *, timestamp: float | None = None, sequence: int = 0) -> Frame:
        """Render one frame from a camera pose (``T_base_camera``), without touching the arm.

        Draws noise from this camera's generator (so successive calls differ unless
        the noise is off). Usable before :meth:`connect`. The rays are rotated into the
        world by ``camera_pose``, cast against the scene, and then:

        * **noise**: the measured radial distance is the true one plus Gaussian noise
          of :func:`noise_sigma_m` (scaled by ``noise_scale``);
        * **quantisation**: the noisy distance is rounded to ``quantisation_m`` (1 mm);
        * **invalid pixels** (distance and XYZ NaN, ``valid`` False): no surface hit,
          angle between ray and surface normal above ``grazing_limit_deg``, measured
          distance outside ``[min_range_m, max_range_m]``;
        * **amplitude**: ``amplitude_at_1m · cos θ / d²`` (0 where nothing was hit);
        * **confidence**: an O3R-like uint16 image: bit 0 invalid, 8 low amplitude
          (grazing), 64 outside range.

        Args:
            camera_pose: Camera pose in the world/base frame.
            timestamp: Frame time, seconds since the epoch; None uses the simulated clock.
            sequence: Sequence number to stamp.
        """
        h, w = self._intr.height, self._intr.width
        t_true, cos_inc, hit = self._cast(camera_pose)
        d = self._measure(t_true, cos_inc, hit)
        valid, conf = self._validity(d, cos_inc, hit)
        # Amplitude falls off as cos θ / d²; 0 where nothing was hit.
        with np.errstate(divide="ignore", invalid="ignore"):
            amp = np.where(hit, self.config.amplitude_at_1m * cos_inc / np.square(t_true), 0.0)
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
        )

    def _cast(self, camera_pose: Pose) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
        """True radial distance (m, NaN where no hit), cos θ (0 where no hit) and hit mask per pixel, (H*W,)."""
        # Pixel rays, camera frame -> world frame.
        r_wc = camera_pose.rotation.as_matrix()
        dirs = self._rays_safe @ r_wc.T
        t, normal, hit = self.world.scene.raycast(camera_pose.translation, dirs)
        # Pixels without a defined ray never hit.
        hit &= self._ray_ok
        # cos θ between the ray and the surface normal (normals face the ray, rays are unit).
        cos_inc = np.where(hit, -np.einsum("ij,ij->i", normal, dirs), 0.0)
        t_true = np.where(hit, t, np.nan)
        return t_true, cos_inc, hit

    def _measure(self, t_true: NDArray[np.float64], cos_inc: NDArray[np.float64], hit: NDArray[np.bool_]
                 ) -> NDArray[np.float64]:
        """Measured radial distance, metres: truth + noise, quantised."""
        cfg = self.config
        noise_draw = self._rng.standard_normal(t_true.shape[0])  # drawn every frame: the stream stays aligned
        if cfg.noise and cfg.noise_scale > 0:
            # sigma from the true distance and incidence (1 m, normal where nothing was hit: unused)
            sigma = noise_sigma_m(np.where(hit, t_true, 1.0), np.where(hit, cos_inc, 1.0), cfg.noise_scale)
            d = t_true + sigma * noise_draw
        else:
            d = t_true
        if cfg.quantisation_m > 0:
            # round to the distance step
            d = np.round(d / cfg.quantisation_m) * cfg.quantisation_m
        return d

    def _validity(self, d: NDArray[np.float64], cos_inc: NDArray[np.float64], hit: NDArray[np.bool_]
                  ) -> tuple[NDArray[np.bool_], NDArray[np.uint16]]:
        """Validity mask and O3R-like confidence bits per pixel from the measured distance ``d`` (m)."""
        cfg = self.config
        # Grazing: angle between ray and normal above the limit (cos below its cosine).
        grazing = hit & (cos_inc < self._cos_grazing)
        with np.errstate(invalid="ignore"):
            out_of_range = ~hit | (d < cfg.min_range_m) | (d > cfg.max_range_m)
        valid = hit & ~grazing & ~out_of_range
        conf = np.zeros(d.shape[0], dtype=np.uint16)
        conf[grazing] |= CONF_LOW_AMPLITUDE
        conf[out_of_range] |= CONF_OUT_OF_RANGE
        conf[~valid] |= CONF_INVALID
        return valid, conf

    # ------------------------------------------------------------------ backend hooks
    def _connect(self, timeout: float) -> None:
        self.connects += 1
        if self.fault_hook is not None:
            self.fault_hook("connect", self.connects)

    def _close(self) -> None:
        return None

    def _info(self) -> DeviceInfo:
        return DeviceInfo(backend="sim", vendor="cellcal (simulated ifm)", model="O3R222 (simulated)",
                          serial=f"SIM-{self.world.seed:08d}", firmware="sim",
                          extra={"frame_rate_hz": self.config.frame_rate_hz, "noise": self.config.noise,
                                 "distortion": self.config.distortion})

    def _intrinsics(self) -> Intrinsics:
        return self._intr

    def _capture(self, timeout: float) -> Frame:
        if self.fault_hook is not None:
            self.fault_hook("capture", self._sequence + 1)
        with self._lock:
            period = 1.0 / self.config.frame_rate_hz
            clock = self.world.clock
            if self._last_frame_elapsed is not None:
                clock.advance_to(self._last_frame_elapsed + period)
            self._last_frame_elapsed = clock.elapsed_s
            self._sequence += 1
            return self.render(self.world.camera_pose(), sequence=self._sequence)

    def resume_state(self) -> dict[str, Any]:
        """JSON-able state of the noise stream and frame pacing (restored when a run resumes)."""
        with self._lock:
            return {"rng": self._rng.bit_generator.state, "sequence": self._sequence,
                    "last_frame_elapsed_s": self._last_frame_elapsed, "clock_elapsed_s": self.world.clock.elapsed_s}

    def restore_resume_state(self, state: dict[str, Any]) -> None:
        """Continue from :meth:`resume_state`'s output: the next frame draws the noise it would have."""
        with self._lock:
            self._rng.bit_generator.state = state["rng"]
            self._sequence = int(state["sequence"])
            last = state["last_frame_elapsed_s"]
            self._last_frame_elapsed = None if last is None else float(last)
            self.world.clock.advance_to(float(state["clock_elapsed_s"]))

    @property
    def sequence(self) -> int:
        """Sequence number of the last captured frame (0 before the first)."""
        return self._sequence

    def describe(self) -> dict[str, Any]:
        """Model parameters for reports."""
        return {"intrinsics": self._intr.to_dict(), "sigma_at_1m_m": SIGMA_AT_1M_M * self.config.noise_scale,
                "sigma_distance_exponent": SIGMA_DISTANCE_EXPONENT, "repeatability_sigmas": REPEATABILITY_SIGMAS}
