"""Monte Carlo accuracy study of the calibration methods on the simulated cell.

Each *trial* places the simulated camera at one pose above the measuring plane
(height along the optical axis, inclination of the optical axis to the plane), with a
fresh noise seed and a fresh set of boxes lying on the plane, captures one frame and
runs every method on it:

``law_of_cosines``, ``plane_fit_nominal``, ``plane_fit``
    The paper's methods (:mod:`cellcal.core.methods.measure`) at every perimeter.
``full_frame``
    The robust whole-frame fit (:mod:`cellcal.core.methods.fullframe`), with its 95 %
    confidence interval on the tilt; perimeter-independent.

The truth comes from the pose the camera was placed at and the simulated plane
(``z = 0`` in the base frame, so the plane frame of ``[sim] boxes`` is the base frame).

Clutter: for a requested fraction ``f`` of the image's plane pixels (pixels whose ray
meets the plane in front of the camera) to be hidden by boxes, 1-3 boxes of random
footprint, yaw and height (3-8 cm) are centred on random visible plane points and
scaled together (bisection) until the boxes' exact ray/box occlusion covers ``f``.
The achieved fraction (exact geometry, every pixel) and the fraction observed in
the captured frame (invalid or more than 1 cm in front of the plane) are recorded.

Devices come from the registry (backend ``"sim"``) built from a configuration
document per trial; this module never imports a simulator. Everything is seeded:
the same :class:`StudySettings` give the same rows, and a condition's trials do not
depend on which other conditions are in the run.

Angles in the rows are degrees and lengths metres (a human-facing table); the
library API elsewhere is SI.
"""

from __future__ import annotations

import csv
import importlib
import io
import math
import zlib
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cellcal.core.calibration.config import look_at_pose
from cellcal.core.calibration.report import write_bytes_atomic
from cellcal.core.methods.measure import ExpectedGeometry, expected_geometry, measure_frames
from cellcal.devices.base import BackendContext
from cellcal.devices.errors import CalibrationError, CellcalError
from cellcal.devices.geometry.camera_model import pixel_grid_rays
from cellcal.devices.pose import Pose
from cellcal.devices.registry import Registry, default_registry
from cellcal.devices.types import Frame, Intrinsics

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

GRID_METHODS: tuple[str, ...] = ("law_of_cosines", "plane_fit_nominal", "plane_fit")
FULL_FRAME = "full_frame"
METHODS: tuple[str, ...] = (*GRID_METHODS, FULL_FRAME)

#: The paper's experiment: three heights along the optical axis, 80 deg inclination.
PAPER_HEIGHTS_M: tuple[float, ...] = (0.46, 0.59, 0.61)
PAPER_INCLINATION_DEG = 80.0
PAPER_PERIMETERS_PX: tuple[int, ...] = (20, 30, 40, 50)
#: The issue's targets for the full-frame method at the paper's settings.
TARGET_ERROR_DEG = 0.05
TARGET_ERROR_CLUTTER_DEG = 0.1
TARGET_CLUTTER = 0.3
TARGET_COVERAGE = (0.93, 0.97)

#: A frame pixel counts as "on a box" if it is invalid or this far in front of the plane, m.
OBSERVED_BOX_MIN_M = 0.01

#: CSV columns, in order (one row per trial x method x perimeter; full frame has no perimeter).
COLUMNS: tuple[str, ...] = (
    "trial", "seed", "height_m", "inclination_deg", "noise_scale", "clutter_target", "clutter_achieved",
    "clutter_observed", "n_boxes", "method", "perimeter_px", "ok", "true_angle_deg", "est_angle_deg",
    "angle_error_deg", "true_tilt_deg", "est_tilt_deg", "tilt_error_deg", "abs_tilt_error_deg",
    "normal_error_deg", "true_height_m", "est_height_m", "height_error_m", "sigma_tilt_deg",
    "ci_lo_deg", "ci_hi_deg", "ci_contains", "height_ci_contains", "inlier_fraction", "gates_passed", "message",
)


# ---------------------------------------------------------------------- settings
@dataclass(frozen=True)
class Condition:
    """One cell of the study's design.

    Attributes:
        height_m: Camera-to-plane distance along the optical axis, metres.
        inclination_deg: Angle between optical axis and plane, degrees (90 = looking straight down).
        noise_scale: Multiplier of the simulated camera's distance noise (1 = default).
        clutter: Requested fraction of the image's plane pixels hidden by boxes, 0..1.
    """

    height_m: float
    inclination_deg: float
    noise_scale: float
    clutter: float

    def key(self) -> str:
        """Stable text key (seeds a condition's trials)."""
        return f"{self.height_m:.4f}|{self.inclination_deg:.3f}|{self.noise_scale:.3f}|{self.clutter:.3f}"


@dataclass(frozen=True)
class StudySettings:
    """What the study runs.

    The design is one factor at a time around the paper's setting, each at every
    height: clutter levels (paper inclination, default noise), inclinations (no
    clutter, default noise) and noise scales (no clutter, paper inclination).

    Attributes:
        trials: Trials per condition.
        seed: Root seed.
        heights_m: Heights along the optical axis, metres.
        inclinations_deg: Inclinations of the optical axis to the plane, degrees.
        noise_scales: Noise multipliers of the simulated camera.
        clutter_fractions: Requested fractions of the plane pixels hidden by boxes.
        perimeters_px: Perimeters of the paper's methods, pixels.
        window_px: Sampling window of the paper's methods, pixels (odd).
        max_boxes: At most this many boxes per cluttered trial (at least 1).
        box_height_m: Range of box heights, metres.
        target_m: Plane point the optical axis hits, base frame, metres.
        camera: Extra keys for the ``sim`` camera section (e.g. ``{"distortion": False}``).
        full_frame: Keyword arguments for ``FullFrameSettings`` (empty: its defaults).
        headline_factor: The headline conditions (paper inclination, default noise,
            no clutter and 30 % clutter) run this many times ``trials``, to pin the
            interval coverage down.
    """

    trials: int = 50
    seed: int = 0
    heights_m: tuple[float, ...] = PAPER_HEIGHTS_M
    inclinations_deg: tuple[float, ...] = (60.0, 70.0, PAPER_INCLINATION_DEG, 85.0)
    noise_scales: tuple[float, ...] = (0.5, 1.0, 2.0, 4.0)
    clutter_fractions: tuple[float, ...] = (0.0, 0.1, 0.2, 0.3, 0.4)
    perimeters_px: tuple[int, ...] = PAPER_PERIMETERS_PX
    window_px: int = 3
    max_boxes: int = 3
    box_height_m: tuple[float, float] = (0.03, 0.08)
    target_m: tuple[float, float, float] = (0.3, 0.0, 0.0)
    camera: Mapping[str, Any] = field(default_factory=dict)
    full_frame: Mapping[str, Any] = field(default_factory=dict)
    headline_factor: int = 4

    def __post_init__(self) -> None:
        if self.trials < 1:
            raise CalibrationError(f"trials must be >= 1, got {self.trials}")
        if self.seed < 0:
            raise CalibrationError(f"seed must be >= 0, got {self.seed}")
        if any(not 0.0 <= c < 0.9 for c in self.clutter_fractions):
            raise CalibrationError(f"clutter fractions must be in [0, 0.9), got {self.clutter_fractions}")
        if self.max_boxes < 1:
            raise CalibrationError(f"max_boxes must be >= 1, got {self.max_boxes}")
        if self.headline_factor < 1:
            raise CalibrationError(f"headline_factor must be >= 1, got {self.headline_factor}")

    def trials_for(self, condition: Condition) -> int:
        """Trials of one condition (``trials``, times ``headline_factor`` for a headline condition)."""
        headline = (condition.inclination_deg == PAPER_INCLINATION_DEG and condition.noise_scale == 1.0
                    and condition.clutter in (0.0, TARGET_CLUTTER))
        return self.trials * (self.headline_factor if headline else 1)

    def conditions(self) -> list[Condition]:
        """The design's conditions, without duplicates, in a stable order."""
        base_noise = 1.0 if 1.0 in self.noise_scales or not self.noise_scales else self.noise_scales[0]
        incl = PAPER_INCLINATION_DEG if PAPER_INCLINATION_DEG in self.inclinations_deg else self.inclinations_deg[0]
        out: dict[str, Condition] = {}
        for h in self.heights_m:
            cells = [Condition(h, incl, base_noise, c) for c in self.clutter_fractions or (0.0,)]
            cells += [Condition(h, i, base_noise, 0.0) for i in self.inclinations_deg]
            cells += [Condition(h, incl, n, 0.0) for n in self.noise_scales]
            for c in cells:
                out.setdefault(c.key(), c)
        return list(out.values())


def quick_settings(trials: int = 8, seed: int = 0) -> StudySettings:
    """A small design for CI: the paper's heights and inclination, no clutter and 30 %."""
    return StudySettings(trials=trials, seed=seed, inclinations_deg=(PAPER_INCLINATION_DEG,),
                         noise_scales=(1.0,), clutter_fractions=(0.0, TARGET_CLUTTER), headline_factor=1)


# ---------------------------------------------------------------------- geometry of a trial
@dataclass(frozen=True)
class BoxSpec:
    """One box on the plane ``z = 0`` (base frame == plane frame).

    Attributes:
        center_xy_m: Footprint centre, metres.
        half_xy_m: Half edge lengths of the footprint, metres.
        yaw_rad: Rotation about the plane normal, rad.
        height_m: Height, metres.
    """

    center_xy_m: tuple[float, float]
    half_xy_m: tuple[float, float]
    yaw_rad: float
    height_m: float

    def to_table(self) -> dict[str, Any]:
        """The ``[[sim.boxes]]`` entry."""
        return {"center_xy_m": [float(v) for v in self.center_xy_m],
                "size_m": [2.0 * self.half_xy_m[0], 2.0 * self.half_xy_m[1], float(self.height_m)],
                "yaw_deg": math.degrees(self.yaw_rad)}


@dataclass(frozen=True)
class PlaneRays:
    """The pixels' rays against the plane ``z = 0`` for one camera pose.

    Attributes:
        origin_m: Camera centre, base frame, metres.
        ground_m: Where each pixel's ray meets the plane, (H, W, 3), metres (NaN if never).
        on_plane: (H, W) True where the ray meets the plane in front of the camera.
        distance_m: Radial distance from the camera to ``ground_m``, (H, W), metres.
    """

    origin_m: FloatArray
    ground_m: FloatArray
    on_plane: BoolArray
    distance_m: FloatArray


def plane_rays(camera_in_base: Pose, intrinsics: Intrinsics) -> PlaneRays:
    """Intersect every pixel's ray (distortion honoured) with the plane ``z = 0``."""
    rays = pixel_grid_rays(intrinsics)
    dirs = rays @ camera_in_base.rotation.as_matrix().T
    o = np.asarray(camera_in_base.translation, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -o[2] / dirs[..., 2]
    on_plane = np.isfinite(t) & (t > 0)
    t = np.where(on_plane, t, np.nan)
    return PlaneRays(o, o + t[..., None] * dirs, on_plane, t)


def occluded(rays: PlaneRays, boxes: Sequence[BoxSpec], scale: float = 1.0,
             pixels: tuple[slice, slice] | None = None) -> BoolArray:
    """Which pixels' rays hit a box before the plane (boxes' footprints scaled by ``scale``).

    A box is a vertical prism on the plane; the ray toward ground point ``g`` crosses
    heights ``[0, h]`` along the plane segment ``g -> g + (h / o_z) (o - g)``, so it
    hits the box iff that segment meets the footprint (2D slab test, vectorised).

    Args:
        rays: Output of :func:`plane_rays`.
        boxes: The boxes.
        scale: Multiplier of every footprint about its centre.
        pixels: Optional (rows, cols) slices to evaluate a subsampled image.
    """
    sl = pixels or (slice(None), slice(None))
    g = rays.ground_m[sl][..., :2]
    ok = rays.on_plane[sl]
    g = np.where(ok[..., None], g, 0.0)
    out = np.zeros(ok.shape, dtype=bool)
    o = rays.origin_m
    for b in boxes:
        c, s = math.cos(b.yaw_rad), math.sin(b.yaw_rad)
        rot = np.array([[c, s], [-s, c]])  # world -> box local
        p0 = (g - np.asarray(b.center_xy_m)) @ rot.T
        d = (o[:2] - g) @ rot.T * (b.height_m / o[2])
        t_lo = np.zeros(ok.shape)
        t_hi = np.ones(ok.shape)
        for axis, half in enumerate(b.half_xy_m):
            hs = half * scale
            da, pa = d[..., axis], p0[..., axis]
            with np.errstate(divide="ignore", invalid="ignore"):
                t1, t2 = (-hs - pa) / da, (hs - pa) / da
            parallel = da == 0
            inside = np.abs(pa) <= hs
            t_lo = np.maximum(t_lo, np.where(parallel, np.where(inside, -np.inf, np.inf), np.minimum(t1, t2)))
            t_hi = np.minimum(t_hi, np.where(parallel, np.where(inside, np.inf, -np.inf), np.maximum(t1, t2)))
        out |= t_lo <= t_hi
    out &= ok
    return out


def place_boxes(rng: np.random.Generator, rays: PlaneRays, fraction: float, *, max_boxes: int = 3,
                height_m: tuple[float, float] = (0.03, 0.08), tolerance: float = 0.004
                ) -> tuple[list[BoxSpec], BoolArray]:
    """Boxes hiding ``fraction`` of the image's plane pixels.

    Draws 1..``max_boxes`` boxes (centres on random plane points seen by the central
    70 % of the image, random aspect, yaw and height), then scales their footprints
    together by bisection on a 4x-subsampled image until the occluded fraction is
    within ``tolerance`` of the request.

    Returns:
        The boxes and the (H, W) mask of the pixels they hide (full resolution).
    """
    if fraction <= 0:
        return [], np.zeros(rays.on_plane.shape, dtype=bool)
    h, w = rays.on_plane.shape
    n_plane = int(np.count_nonzero(rays.on_plane))
    if n_plane == 0:
        raise CalibrationError("no pixel sees the plane; cannot place boxes")
    k = int(rng.integers(1, max_boxes + 1))
    rows = rng.integers(int(0.15 * h), int(0.85 * h), size=4 * k)
    cols = rng.integers(int(0.15 * w), int(0.85 * w), size=4 * k)
    centres = [rays.ground_m[r, c, :2] for r, c in zip(rows, cols, strict=True) if rays.on_plane[r, c]][:k]
    if not centres:
        raise CalibrationError("no plane point near the image centre; cannot place boxes")
    span = float(np.nanmedian(rays.distance_m)) * 0.25
    boxes = []
    for centre in centres:
        aspect = float(rng.uniform(0.5, 2.0))
        base = span * float(rng.uniform(0.6, 1.4))
        boxes.append(BoxSpec((float(centre[0]), float(centre[1])), (base * math.sqrt(aspect), base / math.sqrt(aspect)),
                             float(rng.uniform(0.0, math.pi)), float(rng.uniform(*height_m))))
    sub = (slice(1, None, 4), slice(1, None, 4))
    n_sub = max(int(np.count_nonzero(rays.on_plane[sub])), 1)

    def frac(scale: float) -> float:
        return float(np.count_nonzero(occluded(rays, boxes, scale, sub))) / n_sub

    lo, hi = 0.0, 1.0
    while frac(hi) < fraction and hi < 64.0:
        lo, hi = hi, hi * 2.0
    scale = hi
    for _ in range(30):
        scale = 0.5 * (lo + hi)
        f = frac(scale)
        if abs(f - fraction) <= tolerance:
            break
        lo, hi = (scale, hi) if f < fraction else (lo, scale)
    boxes = [BoxSpec(b.center_xy_m, (b.half_xy_m[0] * scale, b.half_xy_m[1] * scale), b.yaw_rad, b.height_m)
             for b in boxes]
    return boxes, occluded(rays, boxes)


def observed_clutter(frame: Frame, rays: PlaneRays, camera_in_base: Pose) -> float:
    """Fraction of the plane pixels the frame shows as not the plane.

    A plane pixel counts if it is invalid or its point lies more than
    :data:`OBSERVED_BOX_MIN_M` in front of the plane (boxes' bottom centimetre is missed).
    """
    on = rays.on_plane
    n = int(np.count_nonzero(on))
    if n == 0:
        return math.nan
    pts = frame.xyz[on].astype(np.float64)
    z = pts @ camera_in_base.rotation.as_matrix()[2] + camera_in_base.translation[2]
    valid = frame.valid[on]
    with np.errstate(invalid="ignore"):
        box = ~valid | (z > OBSERVED_BOX_MIN_M)
    return float(np.count_nonzero(box)) / n


# ---------------------------------------------------------------------- one trial
@dataclass
class TrialData:
    """One trial's inputs, frame and truth (kept for the example figure).

    Attributes:
        index: Trial index within its condition.
        seed: The trial's noise seed (``[cell] seed`` of its document).
        condition: Its condition.
        camera_in_base: True camera pose, base frame.
        boxes: The boxes placed.
        clutter_achieved: Exact occluded fraction of the plane pixels.
        clutter_observed: The fraction the frame shows (see :func:`observed_clutter`).
        frame: The captured frame.
        truth: Expected geometry.
        occluded_mask: (H, W) pixels whose ray hits a box.
        full_frame: The full-frame result object (None if that method failed or is absent).
    """

    index: int
    seed: int
    condition: Condition
    camera_in_base: Pose
    boxes: list[BoxSpec]
    clutter_achieved: float
    clutter_observed: float
    frame: Frame
    truth: ExpectedGeometry
    occluded_mask: BoolArray
    full_frame: Any = None


def trial_document(camera_in_base: Pose, boxes: Sequence[BoxSpec], seed: int, noise_scale: float,
                   camera: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The configuration document of one trial: a ``sim`` camera whose (identity-mounted)
    flange starts at the camera pose, over the plane ``z = 0`` with the boxes."""
    xyz_rpy = camera_in_base.as_xyz_rpy()
    section = {"backend": "sim", **dict(camera or {}), "noise_scale": float(noise_scale),
               "noise": bool(noise_scale > 0)}
    return {
        "cell": {"name": "study", "seed": int(seed)},
        "camera": section,
        "arm": {"backend": "sim"},
        "mount": {"translation_m": [0.0, 0.0, 0.0], "rpy_deg": [0.0, 0.0, 0.0]},
        "sim": {"plane_point_m": [0.0, 0.0, 0.0], "plane_normal": [0.0, 0.0, 1.0],
                "boxes": [b.to_table() for b in boxes],
                "initial_flange_translation_m": [float(v) for v in xyz_rpy[:3]],
                "initial_flange_rpy_deg": [math.degrees(float(v)) for v in xyz_rpy[3:]]},
    }


def capture_frame(document: Mapping[str, Any], registry: Registry | None = None,
                  timeout_s: float = 5.0) -> Frame:
    """Build the document's camera from the registry, connect, capture one frame, close."""
    registry = registry or default_registry()
    seed = int(document.get("cell", {}).get("seed", 0))
    ctx = BackendContext(source="<study>", section="camera", document=document, shared={}, seed=seed)
    camera = registry.create_camera(document["camera"], ctx)
    with camera.connect(timeout_s):
        return camera.capture(timeout_s)


def _trial_seed(root: int, condition: Condition, index: int) -> np.random.SeedSequence:
    return np.random.SeedSequence([root, zlib.crc32(condition.key().encode()), index])


def _empty_row(trial: TrialData, method: str, perimeter: int | None) -> dict[str, Any]:
    c, t = trial.condition, trial.truth
    angle = math.degrees(t.angle_rad)
    return {
        "trial": trial.index, "seed": trial.seed, "height_m": c.height_m, "inclination_deg": c.inclination_deg,
        "noise_scale": c.noise_scale, "clutter_target": c.clutter, "clutter_achieved": trial.clutter_achieved,
        "clutter_observed": trial.clutter_observed, "n_boxes": len(trial.boxes), "method": method,
        "perimeter_px": perimeter, "ok": False, "true_angle_deg": angle, "est_angle_deg": math.nan,
        "angle_error_deg": math.nan, "true_tilt_deg": 90.0 - angle, "est_tilt_deg": math.nan,
        "tilt_error_deg": math.nan, "abs_tilt_error_deg": math.nan, "normal_error_deg": math.nan,
        "true_height_m": t.height_m, "est_height_m": math.nan, "height_error_m": math.nan,
        "sigma_tilt_deg": math.nan, "ci_lo_deg": math.nan, "ci_hi_deg": math.nan, "ci_contains": None,
        "height_ci_contains": None, "inlier_fraction": math.nan, "gates_passed": None, "message": "",
    }


def _fill(row: dict[str, Any], truth: ExpectedGeometry, angle_rad: float, height_m: float,
          normal: FloatArray | None) -> dict[str, Any]:
    est = math.degrees(angle_rad)
    err = est - row["true_angle_deg"]
    row.update(ok=True, est_angle_deg=est, angle_error_deg=err, est_tilt_deg=90.0 - est, tilt_error_deg=-err,
               abs_tilt_error_deg=abs(err), est_height_m=height_m, height_error_m=height_m - truth.height_m)
    if normal is not None:
        cos = abs(float(np.dot(normal, truth.plane_cam.normal)))
        row["normal_error_deg"] = math.degrees(math.acos(min(1.0, cos)))
    return row


def grid_rows(trial: TrialData, perimeters_px: Sequence[int], window_px: int) -> list[dict[str, Any]]:
    """Rows of the paper's three methods at every perimeter (a failure is a row with ok=False)."""
    rows: list[dict[str, Any]] = []
    try:
        measured = measure_frames([trial.frame], perimeters_px=perimeters_px, methods=GRID_METHODS,
                                  window_px=window_px)
    except CalibrationError:
        measured = []
        for p in perimeters_px:  # narrow down, so that one failure costs only its own estimate
            try:
                measured += measure_frames([trial.frame], perimeters_px=[p], methods=GRID_METHODS,
                                           window_px=window_px)
                continue
            except CalibrationError:
                pass
            for name in GRID_METHODS:
                try:
                    measured += measure_frames([trial.frame], perimeters_px=[p], methods=[name], window_px=window_px)
                except CalibrationError as exc:
                    row = _empty_row(trial, name, p)
                    row["message"] = str(exc)
                    rows.append(row)
    for m in measured:
        row = _empty_row(trial, m.method, m.perimeter_px)
        normal = None if m.plane is None else m.plane.normal
        _fill(row, trial.truth, m.angle_rad, m.height_m, normal)
        if m.angle_sigma_rad is not None:
            row["sigma_tilt_deg"] = math.degrees(m.angle_sigma_rad)
        rows.append(row)
    return rows


# ---------------------------------------------------------------------- full frame (helper A's module)
FullFrameFit = Callable[[Frame], Any]


def full_frame_fitter(options: Mapping[str, Any] | None = None) -> FullFrameFit | None:
    """``frame -> FullFrameResult`` from :mod:`cellcal.core.methods.fullframe`, or None if absent."""
    try:
        fullframe = importlib.import_module("cellcal.core.methods.fullframe")
    except ModuleNotFoundError as exc:
        if exc.name != "cellcal.core.methods.fullframe":
            raise
        return None
    settings = fullframe.FullFrameSettings(**dict(options or {}))

    def fit(frame: Frame) -> Any:
        return fullframe.fit_full_frame([frame], settings)

    return fit


def full_frame_row(trial: TrialData, fit: FullFrameFit) -> dict[str, Any]:
    """The full-frame row of a trial (stores the result on ``trial.full_frame``)."""
    row = _empty_row(trial, FULL_FRAME, None)
    try:
        res = fit(trial.frame)
    except CellcalError as exc:
        row["message"] = str(exc)
        return row
    trial.full_frame = res
    _fill(row, trial.truth, float(res.angle_rad), float(res.height_m), res.plane.normal)
    row["sigma_tilt_deg"] = math.degrees(float(res.angle_sigma_rad))
    lo, hi = (math.degrees(float(v)) for v in res.angle_ci_rad)  # interval of the angle -> of the tilt
    row["ci_lo_deg"], row["ci_hi_deg"] = 90.0 - hi, 90.0 - lo
    row["ci_contains"] = bool(row["ci_lo_deg"] <= row["true_tilt_deg"] <= row["ci_hi_deg"])
    h_lo, h_hi = (float(v) for v in res.height_ci_m)
    row["height_ci_contains"] = bool(h_lo <= trial.truth.height_m <= h_hi)
    row["inlier_fraction"] = float(res.inlier_fraction)
    row["gates_passed"] = bool(res.passed)
    return row


# ---------------------------------------------------------------------- the study
@dataclass
class StudyResult:
    """Rows of a study run and one example trial for the plane-fit picture.

    Attributes:
        settings: What was run.
        rows: One dict per trial x method x perimeter, keys :data:`COLUMNS`.
        example: The first trial at the paper's lowest height with the clutter closest
            to 30 % (None if the run has no such trial).
        full_frame_available: Whether :mod:`cellcal.core.methods.fullframe` was found.
    """

    settings: StudySettings
    rows: list[dict[str, Any]]
    example: TrialData | None
    full_frame_available: bool


def run_trial(settings: StudySettings, condition: Condition, index: int, intrinsics: Intrinsics,
              fit: FullFrameFit | None, registry: Registry | None = None) -> tuple[TrialData, list[dict[str, Any]]]:
    """Place, capture and measure one trial; returns the trial and its rows."""
    rng = np.random.default_rng(_trial_seed(settings.seed, condition, index))
    seed = int(rng.integers(0, 2**31 - 1))
    pose = look_at_pose(np.asarray(settings.target_m, dtype=np.float64), np.array([0.0, 0.0, 1.0]),
                        condition.height_m, math.radians(condition.inclination_deg), "x")
    rays = plane_rays(pose, intrinsics)
    boxes, mask = place_boxes(rng, rays, condition.clutter, max_boxes=settings.max_boxes,
                              height_m=settings.box_height_m)
    achieved = float(np.count_nonzero(mask)) / max(int(np.count_nonzero(rays.on_plane)), 1)
    doc = trial_document(pose, boxes, seed, condition.noise_scale, settings.camera)
    frame = capture_frame(doc, registry)
    truth = expected_geometry(pose, (0.0, 0.0, 0.0), (0.0, 0.0, 1.0))
    trial = TrialData(index, seed, condition, pose, boxes, achieved,
                      observed_clutter(frame, rays, pose) if boxes else 0.0, frame, truth, mask)
    rows = grid_rows(trial, settings.perimeters_px, settings.window_px)
    if fit is not None:
        rows.append(full_frame_row(trial, fit))
    return trial, rows


def study_intrinsics(settings: StudySettings, registry: Registry | None = None) -> Intrinsics:
    """The intrinsics of the study's camera (from a camera built like the trials')."""
    doc = trial_document(look_at_pose(np.asarray(settings.target_m, dtype=np.float64), np.array([0.0, 0.0, 1.0]),
                                      0.5, math.pi / 2, "x"), [], 0, 1.0, settings.camera)
    registry = registry or default_registry()
    ctx = BackendContext(source="<study>", section="camera", document=doc, shared={}, seed=0)
    camera = registry.create_camera(doc["camera"], ctx)
    with camera.connect(5.0):
        return camera.intrinsics


def run_study(settings: StudySettings, *, registry: Registry | None = None,
              progress: Callable[[int], Any] | None = None) -> StudyResult:
    """Run every trial of every condition.

    Args:
        settings: The design.
        registry: Device registry (default: the process-wide one).
        progress: Optional factory ``total -> tqdm-like`` (``update(n)``, ``close()``).
    """
    intr = study_intrinsics(settings, registry)
    fit = full_frame_fitter(settings.full_frame)
    conditions = settings.conditions()
    example_clutter = min((c.clutter for c in conditions), key=lambda v: abs(v - TARGET_CLUTTER))
    example_height = min(c.height_m for c in conditions)
    bar = progress(sum(settings.trials_for(c) for c in conditions)) if progress else None
    rows: list[dict[str, Any]] = []
    example: TrialData | None = None
    try:
        for cond in conditions:
            for i in range(settings.trials_for(cond)):
                trial, trial_rows = run_trial(settings, cond, i, intr, fit, registry)
                rows += trial_rows
                if (example is None and cond.height_m == example_height and cond.clutter == example_clutter
                        and cond.inclination_deg == PAPER_INCLINATION_DEG
                        and (fit is None or trial.full_frame is not None)):
                    example = trial
                if bar is not None:
                    bar.update(1)
    finally:
        if bar is not None:
            bar.close()
    return StudyResult(settings, rows, example, fit is not None)


# ---------------------------------------------------------------------- output
def _cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return "" if math.isnan(value) else repr(value)
    return str(value)


def rows_to_csv(rows: Iterable[Mapping[str, Any]]) -> str:
    """The rows as CSV text (columns :data:`COLUMNS`; NaN and None as empty cells)."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(COLUMNS)
    for r in rows:
        writer.writerow([_cell(r.get(c)) for c in COLUMNS])
    return buf.getvalue()


def write_text_atomic(path: str | Path, text: str) -> Path:
    """Write UTF-8 text atomically (temp file in the same directory, fsync, rename).

    Raises:
        CalibrationError: If the file cannot be written.
    """
    return write_bytes_atomic(path, text.encode("utf-8"))


def write_csv(path: str | Path, rows: Iterable[Mapping[str, Any]]) -> Path:
    """Write the rows to ``path`` atomically; returns the path."""
    return write_text_atomic(path, rows_to_csv(rows))


_BOOL_COLUMNS = ("ci_contains", "height_ci_contains", "gates_passed")


def _parse_cell(column: str, text: str) -> Any:
    if text == "":
        return None if column in _BOOL_COLUMNS else (math.nan if column not in ("method", "message") else "")
    if column in ("method", "message"):
        return text
    if column in _BOOL_COLUMNS or column == "ok":
        return text == "true"
    if column in ("trial", "seed", "n_boxes", "perimeter_px"):
        return int(text)
    return float(text)


def read_csv(path: str | Path) -> list[dict[str, Any]]:
    """Read a study CSV back into rows (inverse of :func:`write_csv`).

    Raises:
        CalibrationError: If the file is missing or lacks a column.
    """
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as exc:
        raise CalibrationError(f"cannot read {path}: {exc.strerror or exc}") from None
    reader = csv.DictReader(io.StringIO(text))
    missing = [c for c in COLUMNS if c not in (reader.fieldnames or [])]
    if missing:
        raise CalibrationError(f"{path}: not a study CSV (missing column(s) {', '.join(missing)})")
    rows = []
    for r in reader:
        row = {c: _parse_cell(c, r[c]) for c in COLUMNS}
        if row["perimeter_px"] is not None and isinstance(row["perimeter_px"], float):
            row["perimeter_px"] = None
        rows.append(row)
    return rows


# ---------------------------------------------------------------------- headline figures
def select(rows: Iterable[Mapping[str, Any]], **match: Any) -> list[Mapping[str, Any]]:
    """Rows whose columns equal the given values (floats compared to 1e-9; a tuple means any of)."""
    def ok(row: Mapping[str, Any]) -> bool:
        for k, want in match.items():
            have = row.get(k)
            options = want if isinstance(want, tuple) else (want,)
            if not any(_same(have, w) for w in options):
                return False
        return True
    return [r for r in rows if ok(r)]


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, float) and isinstance(b, (int, float)) and not isinstance(b, bool):
        return abs(a - float(b)) <= 1e-9
    return bool(a == b)


@dataclass(frozen=True)
class Headline:
    """The issue's figures at the paper's settings (heights 0.46/0.59/0.61 m, 80 deg, default noise).

    Errors are mean absolute tilt errors in degrees over all trials (and, for the
    paper's methods, all perimeters); a failed estimate counts as missing and is
    reported in the ``*_failures`` counts. Coverage is the fraction of full-frame
    fits whose 95 % interval holds the truth. The height figures are for the
    full frame without clutter (mean |error| in metres, interval coverage). None
    where the run had no such trials.
    """

    n_trials: int
    n_trials_clutter: int
    full_frame_error_deg: float | None
    full_frame_error_clutter_deg: float | None
    full_frame_coverage: float | None
    full_frame_coverage_clutter: float | None
    full_frame_failures: int
    full_frame_failures_clutter: int
    nominal_error_deg: float | None
    plane_fit_error_deg: float | None
    law_of_cosines_error_deg: float | None
    nominal_error_clutter_deg: float | None
    clutter_achieved_mean: float | None
    full_frame_height_error_m: float | None = None
    full_frame_height_coverage: float | None = None

    @property
    def meets_error(self) -> bool | None:
        """Full-frame error without clutter <= 0.05 deg."""
        e = self.full_frame_error_deg
        return None if e is None else e <= TARGET_ERROR_DEG

    @property
    def meets_error_clutter(self) -> bool | None:
        """Full-frame error with 30 % clutter <= 0.1 deg."""
        e = self.full_frame_error_clutter_deg
        return None if e is None else e <= TARGET_ERROR_CLUTTER_DEG

    @property
    def meets_coverage(self) -> bool | None:
        """95 % interval coverage (no clutter) within 93-97 %."""
        c = self.full_frame_coverage
        return None if c is None else TARGET_COVERAGE[0] <= c <= TARGET_COVERAGE[1]

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (with the target checks)."""
        out = {k: getattr(self, k) for k in self.__dataclass_fields__}
        out.update(meets_error=self.meets_error, meets_error_clutter=self.meets_error_clutter,
                   meets_coverage=self.meets_coverage)
        return out


def _mean_of(values: Sequence[float]) -> float | None:
    return float(np.mean(values)) if len(values) else None


def _mean_abs(rows: Sequence[Mapping[str, Any]]) -> float | None:
    vals = [r["abs_tilt_error_deg"] for r in rows if r.get("ok")]
    return float(np.mean(vals)) if vals else None


def _coverage(rows: Sequence[Mapping[str, Any]]) -> float | None:
    vals = [bool(r["ci_contains"]) for r in rows if r.get("ok") and r.get("ci_contains") is not None]
    return float(np.mean(vals)) if vals else None


def headline(rows: Sequence[Mapping[str, Any]]) -> Headline:
    """The issue's headline figures from study rows (see :class:`Headline`)."""
    paper = select(rows, height_m=PAPER_HEIGHTS_M, inclination_deg=PAPER_INCLINATION_DEG, noise_scale=1.0)
    clean = select(paper, clutter_target=0.0)
    clut = select(paper, clutter_target=TARGET_CLUTTER)
    ff, ffc = select(clean, method=FULL_FRAME), select(clut, method=FULL_FRAME)
    trials_clean = {(r["height_m"], r["trial"]) for r in clean}
    trials_clut = {(r["height_m"], r["trial"]) for r in clut}
    achieved = list({(r["height_m"], r["trial"]): r["clutter_achieved"] for r in clut}.values())
    return Headline(
        n_trials=len(trials_clean), n_trials_clutter=len(trials_clut),
        full_frame_error_deg=_mean_abs(ff), full_frame_error_clutter_deg=_mean_abs(ffc),
        full_frame_coverage=_coverage(ff), full_frame_coverage_clutter=_coverage(ffc),
        full_frame_failures=sum(1 for r in ff if not r["ok"]),
        full_frame_failures_clutter=sum(1 for r in ffc if not r["ok"]),
        nominal_error_deg=_mean_abs(select(clean, method="plane_fit_nominal")),
        plane_fit_error_deg=_mean_abs(select(clean, method="plane_fit")),
        law_of_cosines_error_deg=_mean_abs(select(clean, method="law_of_cosines")),
        nominal_error_clutter_deg=_mean_abs(select(clut, method="plane_fit_nominal")),
        clutter_achieved_mean=float(np.mean(achieved)) if achieved else None,
        full_frame_height_error_m=_mean_of([abs(r["height_error_m"]) for r in ff if r["ok"]]),
        full_frame_height_coverage=_mean_of([bool(r["height_ci_contains"]) for r in ff
                                             if r["ok"] and r["height_ci_contains"] is not None]),
    )


def summary_table(rows: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """Per method and clutter level at the paper's settings: n, failures, mean/median/p95 |error| (deg),
    interval coverage and the fraction of fits passing the quality gates (full frame)."""
    paper = select(rows, height_m=PAPER_HEIGHTS_M, inclination_deg=PAPER_INCLINATION_DEG, noise_scale=1.0)
    out = []
    for clutter in sorted({r["clutter_target"] for r in paper}):
        for method in METHODS:
            sel = select(paper, method=method, clutter_target=clutter)
            if not sel:
                continue
            err = np.array([r["abs_tilt_error_deg"] for r in sel if r["ok"]])
            out.append({"method": method, "clutter": clutter, "n": len(sel), "failed": len(sel) - err.size,
                        "mean_deg": float(err.mean()) if err.size else math.nan,
                        "median_deg": float(np.median(err)) if err.size else math.nan,
                        "p95_deg": float(np.percentile(err, 95)) if err.size else math.nan,
                        "coverage": _coverage(sel),
                        "gates_passed": _mean_of([bool(r["gates_passed"]) for r in sel
                                                  if r["ok"] and r.get("gates_passed") is not None])})
    return out
