"""The ``sim`` camera with ``kind = "stereo"``: an OAK-like rectified stereo pair (:class:`SimStereoCamera`).

It renders the same world as the ToF sim, but measures as a stereo matcher does: a
disparity ``d = f·B/Z`` with Gaussian noise, rounded to ``2^-subpixel_bits`` px, holes
where the other camera cannot see (the left-right check), speckle, limits of the disparity
search. Why and where the levels come from: docs/adr/0029-sim-stereo-camera.md.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from cellcal.devices.base import BackendContext
from cellcal.devices.errors import ConfigError
from cellcal.devices.measurement import MeasurementModel
from cellcal.devices.pose import Pose
from cellcal.devices.systematic import SystematicError, normalised_pixels
from cellcal.devices.types import DeviceInfo, Frame, Intrinsics

from .camera_shell import SimCameraShell
from .scene import SURFACE_NONE
from .systematic import SystematicConfig
from .tof import REFERENCE_REFLECTIVITY
from .world import SimWorld

__all__ = ["SimStereoCamera", "SimStereoConfig", "occluded_in_other_camera"]

FloatArray = NDArray[np.float64]

#: Grey level of the reference target (reflectivity 0.5) seen head-on in the mono image.
GREY_AT_REFERENCE = 128.0
#: Confidence of a valid / an invalid pixel (OAK meaning: 0 is the most confident).
CONF_VALID = 0
CONF_INVALID = 255


@dataclass(frozen=True)
class SimStereoConfig:
    """Config of the ``sim`` camera with ``kind = "stereo"`` (the ``[camera]`` table).

    Defaults: a Luxonis OAK-D at 400P (OV9282 mono pair binned to 640 x 400, 72° HFOV,
    75 mm baseline), 3 subpixel bits, the 0..95 px disparity search of its default
    (non-extended) mode, its depth aligned to the rectified right camera (depthai's
    default). Speckle and disparity noise (0.25 px) at the levels measured on real OAK frames
    (ADR 0029).
    """

    kind: Literal["stereo"] = field(default="stereo", metadata={"doc": "the sim camera's kind: stereo"})
    width: int = field(default=640, metadata={"gt": 0, "le": 4096, "doc": "image width, px"})
    height: int = field(default=400, metadata={"gt": 0, "le": 4096, "doc": "image height, px"})
    fov_x_deg: float = field(default=72.0, metadata={"gt": 1.0, "lt": 179.0,
                                                     "doc": "horizontal FoV, deg (square pixels: sets fx = fy)"})
    principal_offset_px: tuple[float, float] = field(
        default=(0.0, 0.0), metadata={"ge": -50.0, "le": 50.0, "doc": "principal point offset from the centre, px"})
    baseline_m: float = field(default=0.075, metadata={"gt": 0.0, "le": 2.0, "doc": "stereo baseline, m"})
    subpixel_bits: int = field(default=3, metadata={"ge": 0, "le": 8,
                                                    "doc": "fractional bits of the disparity (0 = integer)"})
    disparity_sigma_px: float = field(default=0.25, metadata={"ge": 0.0, "le": 10.0,
                                                             "doc": "1-sigma disparity noise before rounding, px"})
    noise: bool = field(default=True, metadata={"doc": "add disparity noise"})
    speckle_fraction: float = field(default=0.008, metadata={
        "ge": 0.0, "le": 0.5, "doc": "fraction of pixels in small blobs of wrong disparity"})
    speckle_size_px: int = field(default=3, metadata={"ge": 1, "le": 16,
                                                      "doc": "largest speckle blob side, px (sides 1..this)"})
    speckle_disparity_px: float = field(default=40.0, metadata={
        "ge": 1.0, "le": 1000.0, "doc": "largest disparity error of a speckle blob, px"})
    lr_check: bool = field(default=True, metadata={
        "doc": "left-right check: pixels the other camera cannot see are holes (false: the occluder's disparity)"})
    depth_aligned_to: Literal["right", "left"] = field(default="right", metadata={
        "doc": "rectified camera the depth image belongs to; the other is the baseline away along -x (right) "
               "or +x (left)"})
    min_disparity_px: float = field(default=1.0, metadata={"ge": 0.0, "le": 1000.0,
                                                           "doc": "smallest valid disparity, px (far limit)"})
    max_disparity_px: float = field(default=95.0, metadata={"gt": 0.0, "le": 1000.0,
                                                            "doc": "largest disparity searched, px (near limit)"})
    max_range_m: float = field(default=10.0, metadata={"gt": 0.0, "le": 100.0, "doc": "farthest valid Z-depth, m"})
    grazing_limit_deg: float = field(default=80.0, metadata={
        "gt": 0.0, "le": 90.0, "doc": "max ray/normal angle of a valid pixel (no texture to match), deg"})
    frame_rate_hz: float = field(default=30.0, metadata={"gt": 0.0, "le": 1000.0, "doc": "frame rate, Hz"})
    seed: int | None = field(default=None, metadata={"ge": 0, "doc": "noise seed; default: the world's seed"})

    def __post_init__(self) -> None:
        if self.max_disparity_px <= self.min_disparity_px:
            raise ConfigError(f"must exceed min_disparity_px ({self.min_disparity_px})", key="camera.max_disparity_px")

    @property
    def focal_px(self) -> float:
        """``f = (W/2) / tan(fov_x/2)``, px (440.4 for the defaults)."""
        return (self.width / 2.0) / math.tan(math.radians(self.fov_x_deg) / 2.0)

    @property
    def fb_px_m(self) -> float:
        """``f·B``, px·m: disparity (px) times Z-depth (m) (33.03 for the defaults)."""
        return self.focal_px * self.baseline_m

    def intrinsics(self) -> Intrinsics:
        """Rectified pinhole intrinsics (no distortion), principal point at the centre plus the offset."""
        f = self.focal_px
        return Intrinsics(width=self.width, height=self.height, fx=f, fy=f,
                          cx=(self.width - 1) / 2.0 + self.principal_offset_px[0],
                          cy=(self.height - 1) / 2.0 + self.principal_offset_px[1])


def occluded_in_other_camera(disparity_px: FloatArray, other_on_right: bool) -> NDArray[np.bool_]:
    """Pixels of the reference image the other rectified camera cannot see, (H, W).

    With the other camera the baseline away along +x a pixel at column ``u`` with
    disparity ``d`` appears there at ``u - d``; it is hidden if a pixel to its right lands
    on or left of that, ``min over u' > u of (u' - d(u')) <= u - d(u)`` (a nearer surface
    lands on it or has crossed over it). With the other camera along -x the image is mirrored. So the
    holes lie beside a nearer object on the side away from the other camera, as wide as
    the disparity step; a plane is hidden only where it turns away from the other camera.

    Args:
        disparity_px: True disparity per pixel, px (0 where nothing is seen: never hides).
        other_on_right: Whether the other camera sits at +x of the reference one.
    """
    d = disparity_px if other_on_right else disparity_px[:, ::-1]
    w = d.shape[1]
    # where each pixel lands in the other image, px (mirrored: the same rule applies)
    landed = np.arange(w, dtype=np.float64)[None, :] - d
    # the smallest landing column strictly to the right of each pixel
    right_min = np.minimum.accumulate(landed[:, ::-1], axis=1)[:, ::-1]
    ahead = np.concatenate([right_min[:, 1:], np.full((d.shape[0], 1), np.inf)], axis=1)
    hidden = ahead <= landed + 1e-9
    out: NDArray[np.bool_] = hidden if other_on_right else hidden[:, ::-1]
    return out


class SimStereoCamera(SimCameraShell):
    """Simulated OAK-like stereo camera (rectified pinhole pair) rendering the shared :class:`SimWorld`.

    Per frame (:meth:`render`), for each pixel of the reference (depth-aligned) camera:

    * **ray cast**: Z-depth ``Z`` (camera z, m) of the surface hit, from the pinhole ray;
    * **systematic error** (``[sim.systematic]``, ADR 0054): the true disparity ``f·B/Z`` becomes
      what the camera measures, ``(1 + fb_error)·d + disparity_offset_px + bow(u, v)``
      (:meth:`~cellcal.devices.systematic.SystematicError.distort`), before speckle, noise and rounding;
      the frame's ``metadata["sim_systematic"]`` carries that truth (benchmarks only);
    * **left-right check**: pixels the other camera cannot see (:func:`occluded_in_other_camera`)
      are holes; with ``lr_check = false`` they take the disparity of the nearer surface
      that hides them (what a matcher without the check reports);
    * **speckle**: square blobs (sides ``1..speckle_size_px``) covering ``speckle_fraction`` of
      the pixels take a wrong disparity, the blob's seed pixel's plus an offset of
      ``1..speckle_disparity_px`` px either way;
    * **noise**: ``d = f·B/Z + N(0, disparity_sigma_px)``, so the Z noise is
      ``Z²/(f·B)·sigma_d``, growing with the square of the depth;
    * **rounding** to ``2^-subpixel_bits`` px: ``1/Z`` lies on multiples of ``2^-bits/(f·B)``;
    * **invalid** (holes: distance and XYZ NaN): nothing hit, ray/normal angle above
      ``grazing_limit_deg``, disparity below ``min_disparity_px`` or above ``max_disparity_px``
      (nearer than the search reaches), Z beyond ``max_range_m``;
    * **XYZ** = ``((u - cx)/f, (v - cy)/f, 1)·Z`` from the rounded disparity, distance = ``|XYZ|``;
    * **amplitude**: grey level ``128·(rho/0.5)·cos`` (≤ 255) of the mono image; confidence
      0 where valid, 255 where not (OAK meaning).

    Every frame draws the same amount from the camera's stream whatever is switched off, so
    seeds and resumed runs stay aligned. The stated model is ``stereo`` with the baseline,
    ``f``, the subpixel bits and ``disparity_sigma_px`` (0 with ``noise = false``), and the
    vendor-default systematic allowance (zeros with ``[sim.systematic] enabled = false``).

    Args:
        config: Backend config; None uses the defaults.
        context: Backend context (gives the shared world); None makes a private one.
        world: Use this world instead of the context's (tests).
    """

    Config = SimStereoConfig

    def __init__(self, config: SimStereoConfig | None = None, context: BackendContext | None = None, *,
                 world: SimWorld | None = None) -> None:
        self.config = config or SimStereoConfig()
        super().__init__(context, world, self.config.seed, self.config.frame_rate_hz)
        cfg = self.config
        self._intr = cfg.intrinsics()
        h, w = cfg.height, cfg.width
        v, u = np.mgrid[0:h, 0:w].astype(np.float64)
        # pinhole rays with z = 1 (camera frame), and their unit versions for the ray cast
        self._rays_z1 = np.stack([(u - self._intr.cx) / self._intr.fx, (v - self._intr.cy) / self._intr.fy,
                                  np.ones_like(u)], axis=-1).reshape(-1, 3)
        self._ray_norm = np.linalg.norm(self._rays_z1, axis=1)
        self._rays_unit = self._rays_z1 / self._ray_norm[:, None]
        self._cos_grazing = math.cos(math.radians(cfg.grazing_limit_deg))
        sides = np.arange(1, cfg.speckle_size_px + 1)
        # chance of a pixel seeding a blob: the fraction over the mean blob area
        self._seed_chance = cfg.speckle_fraction / float(np.mean(sides**2))
        self._systematic_of: SystematicConfig | None = None
        self._systematic_cache: tuple[SystematicError, SystematicError, FloatArray] | None = None

    def systematic_error(self) -> tuple[SystematicError, SystematicError, FloatArray]:
        """The world's systematic error for this camera, its field-free part and its field image (H, W), px.

        Built once per ``[sim.systematic]`` table: ``err.distort(d, u, v)`` equals
        ``head.distort(d, u, v) + field`` (the field is additive), and the field of every pixel is
        evaluated once instead of per frame.
        """
        table = self.world.systematic
        if self._systematic_cache is None or self._systematic_of is not table:
            cfg = self.config
            err = table.stereo(cfg.width, cfg.height)
            u, v = normalised_pixels(cfg.width, cfg.height, self._intr.cx, self._intr.cy)
            head = dataclasses.replace(err, field_order=0, field_coeffs=())
            self._systematic_cache = (err, head, err.field_at(u, v))
            self._systematic_of = table
        return self._systematic_cache

    # ------------------------------------------------------------------ rendering
    def render(self, camera_pose: Pose, *, timestamp: float | None = None, sequence: int = 0,
               flange_pose: Pose | None = None) -> Frame:
        """Render one frame from a camera pose (``T_base_camera``); the steps are in the class docstring.

        The scene holds the plate the arm holds (``[sim.plate]``) at ``flange_pose`` (None: the flange's now).
        """
        cfg = self.config
        h, w = cfg.height, cfg.width
        fb = cfg.fb_px_m
        draws = self._draw(h * w)
        # ray cast: unit rays into the world, the surface hit and its incidence
        dirs = self._rays_unit @ camera_pose.rotation_matrix.T
        scene = self.world.scene_at(flange_pose)
        t, normal, hit, surface = scene.raycast_surfaces(camera_pose.translation, dirs)
        cos_inc = np.where(hit, -np.einsum("ij,ij->i", normal, dirs), 0.0)
        # Z-depth = radial distance / |ray with z = 1|; the true disparity f·B/Z (0 where nothing is hit)
        z_true = np.where(hit, t / self._ray_norm, np.inf)
        d_true = np.where(hit, fb / z_true, 0.0).reshape(h, w)
        seen = (hit & (cos_inc >= self._cos_grazing)).reshape(h, w)
        hidden = occluded_in_other_camera(d_true, other_on_right=cfg.depth_aligned_to == "left")
        d = d_true.copy()
        systematic = self.world.systematic
        if systematic.enabled:
            # what the camera measures of the true disparity (where something is seen), before noise and rounding
            err, head, field_px = self.systematic_error()
            d = np.where(d_true > 0.0, head.distort(d_true, 0.0, 0.0) + field_px, 0.0)
        if not cfg.lr_check:
            d = _fill_from_occluder(d, hidden, other_on_right=cfg.depth_aligned_to == "left")
        d = self._speckle(d, seen, draws)
        if cfg.noise:
            # Gaussian disparity noise, px
            d = d + cfg.disparity_sigma_px * draws["noise"].reshape(h, w)
        # round to the subpixel lattice 2^-bits px
        scale = float(2 ** cfg.subpixel_bits)
        d_q = np.round(d * scale) / scale
        valid = seen & (d_q >= cfg.min_disparity_px) & (d_q <= cfg.max_disparity_px) & (d_q > 0)
        if cfg.lr_check:
            valid &= ~hidden
        # Z from the measured disparity; beyond the range limit is a hole
        z = np.where(valid, fb / np.where(valid, d_q, 1.0), np.nan)
        valid &= z <= cfg.max_range_m
        z = np.where(valid, z, np.nan)
        xyz = self._rays_z1.reshape(h, w, 3) * z[..., None]
        dist = np.where(valid, self._ray_norm.reshape(h, w) * z, np.nan)
        # grey level of the mono image: the reference target head-on reads 128
        rho = scene.reflectivity(np.where(hit, surface, SURFACE_NONE)).reshape(h, w)
        grey = np.minimum(GREY_AT_REFERENCE * (rho / REFERENCE_REFLECTIVITY) * cos_inc.reshape(h, w), 255.0)
        grey = np.where(hit.reshape(h, w), grey, 0.0)
        conf = np.where(valid, CONF_VALID, CONF_INVALID).astype(np.uint8)
        metadata: dict[str, Any] = {"disparity_step_px": 1.0 / scale, "depth_aligned_to": cfg.depth_aligned_to}
        if systematic.enabled:
            metadata["sim_systematic"] = err.to_dict()  # the truth, for benchmarks; no estimator reads it
        return Frame(
            distance=dist.astype(np.float32), xyz=xyz.astype(np.float32), amplitude=grey.astype(np.float32),
            valid=valid, intrinsics=self._intr,
            timestamp=self.world.clock.now() if timestamp is None else float(timestamp),
            sequence=int(sequence), confidence=conf,
            metadata=metadata, measurement=self._measurement_model(),
        )

    def _draw(self, n: int) -> dict[str, NDArray[Any]]:
        """This frame's random numbers, the same count whatever is switched off (stream alignment)."""
        rng = self._rng
        return {"noise": rng.standard_normal(n), "seed": rng.random(n),
                "side": rng.integers(1, self.config.speckle_size_px + 1, n), "offset": rng.uniform(-1.0, 1.0, n)}

    def _speckle(self, d: FloatArray, seen: NDArray[np.bool_], draws: dict[str, NDArray[Any]]) -> FloatArray:
        """Paint the speckle blobs: each takes its seed pixel's disparity plus its offset, px."""
        cfg = self.config
        h, w = d.shape
        seeds = np.nonzero((draws["seed"] < self._seed_chance) & seen.ravel())[0]
        if seeds.size == 0:
            return d
        # the blob's offset: 1..speckle_disparity_px either way
        off = draws["offset"][seeds]
        offset = np.sign(off) * (1.0 + (cfg.speckle_disparity_px - 1.0) * np.abs(off))
        sides = draws["side"][seeds]
        owner = np.zeros((h, w), dtype=np.float32)  # 1 + index into seeds of the blob covering a pixel, 0: none
        for side in np.unique(sides):
            mark = np.zeros((h, w), dtype=np.float32)
            pick = np.nonzero(sides == side)[0]
            mark.flat[seeds[pick]] = (pick + 1).astype(np.float32)
            # grow each seed to a side x side square (dilation keeps the largest id where blobs meet)
            owner = np.maximum(owner, cv2.dilate(mark, np.ones((int(side), int(side)), np.uint8)))
        blob = (owner > 0) & seen
        k = owner[blob].astype(np.int64) - 1
        out = d.copy()
        out[blob] = d.flat[seeds[k]] + offset[k]
        return out

    # ------------------------------------------------------------------ backend hooks
    def _measurement_model(self) -> MeasurementModel:
        """Stereo: baseline, ``f``, subpixel bits and disparity sigma (0 with ``noise = false``).

        The systematic allowance is the vendor default (None) with ``[sim.systematic]`` on, zeros with it off.
        """
        cfg = self.config
        return MeasurementModel(
            kind="stereo", baseline_m=cfg.baseline_m, focal_px=cfg.focal_px, subpixel_bits=cfg.subpixel_bits,
            disparity_sigma_px=cfg.disparity_sigma_px if cfg.noise else 0.0, source="sim",
            settings={"lr_check": cfg.lr_check, "speckle_fraction": cfg.speckle_fraction,
                      "min_disparity_px": cfg.min_disparity_px, "max_disparity_px": cfg.max_disparity_px,
                      "depth_aligned_to": cfg.depth_aligned_to},
            **self.world.systematic.stated_allowance)

    def _info(self) -> DeviceInfo:
        return DeviceInfo(backend="sim", vendor="cellcal (simulated Luxonis)", model="OAK-D 400P (simulated)",
                          serial=f"SIMSTEREO-{self.world.seed:08d}", firmware="sim",
                          extra={"frame_rate_hz": self.config.frame_rate_hz, "noise": self.config.noise,
                                 "kind": "stereo", "subpixel_bits": self.config.subpixel_bits})

    def _intrinsics(self) -> Intrinsics:
        return self._intr

    def _configured_intrinsics(self) -> Intrinsics:
        return self._intr

    def describe(self) -> dict[str, Any]:
        """Model parameters for reports."""
        return {"intrinsics": self._intr.to_dict(), "measurement": self._measurement_model().to_dict()}


def _fill_from_occluder(d: FloatArray, hidden: NDArray[np.bool_], other_on_right: bool) -> FloatArray:
    """Hidden pixels take the disparity of the nearest visible pixel on the occluder's side, px."""
    if not hidden.any():
        return d
    src = d if other_on_right else d[:, ::-1]
    hid = hidden if other_on_right else hidden[:, ::-1]
    w = src.shape[1]
    # column of the nearest visible pixel at or right of each pixel (w where none)
    cols = np.where(hid, w, np.arange(w)[None, :])
    nearest = np.minimum.accumulate(cols[:, ::-1], axis=1)[:, ::-1]
    padded = np.concatenate([src, np.zeros((src.shape[0], 1))], axis=1)
    out = np.take_along_axis(padded, nearest, axis=1)
    out = np.where(hid, out, src)
    return out if other_on_right else out[:, ::-1]
