"""Monte Carlo trials of the calibration methods on the simulated cell.

A trial places the sim camera at one pose over the plane (height, inclination), with a
fresh noise seed and fresh boxes and the ToF artefacts of its level, captures one frame
and runs every method on it (:func:`run_trial`); :func:`run_study` runs every trial of
every condition. Seeded throughout; the design and its rationale are in ADR 0012.
"""

from __future__ import annotations

import importlib
import math
import zlib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cellcal.core.calibration.calibrator import build_camera
from cellcal.core.calibration.config import look_at_pose
from cellcal.core.methods.measure import ExpectedGeometry, expected_geometry, measure_frames
from cellcal.core.study.scene import (
    BoxSpec,
    capture_frame,
    observed_clutter,
    place_boxes,
    plane_rays,
    trial_document,
)
from cellcal.devices.errors import CalibrationError, CellcalError
from cellcal.devices.pose import Pose
from cellcal.devices.registry import Registry
from cellcal.devices.types import Frame, Intrinsics

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

__all__ = [
    "ARTEFACT_LEVELS",
    "ARTEFACT_TABLES",
    "BASE_ARTEFACTS",
    "FULL_FRAME",
    "GRID_METHODS",
    "METHODS",
    "PAPER_HEIGHTS_M",
    "PAPER_INCLINATION_DEG",
    "PAPER_PERIMETERS_PX",
    "TARGET_CLUTTER",
    "TARGET_COVERAGE",
    "TARGET_COVERAGE_CLUTTER",
    "TARGET_ERROR_CLUTTER_DEG",
    "TARGET_ERROR_DEG",
    "Condition",
    "FullFrameFit",
    "StudyResult",
    "StudySettings",
    "TrialData",
    "full_frame_fitter",
    "full_frame_row",
    "grid_rows",
    "quick_settings",
    "run_study",
    "run_trial",
    "study_intrinsics",
]

#: The methods in the study's order: the paper's three on the grid, then the full frame.
GRID_METHODS: tuple[str, ...] = ("law_of_cosines", "plane_fit_nominal", "plane_fit")
FULL_FRAME = "full_frame"
METHODS: tuple[str, ...] = (*GRID_METHODS, FULL_FRAME)

#: The paper's experiment: three heights along the optical axis, 80 deg inclination.
PAPER_HEIGHTS_M: tuple[float, ...] = (0.46, 0.59, 0.61)
PAPER_INCLINATION_DEG = 80.0
PAPER_PERIMETERS_PX: tuple[int, ...] = (20, 30, 40, 50)
#: The issues' targets for the full-frame method at the paper's settings (mean |tilt error|:
#: 0.05 deg in the first study, 0.01 deg once the sim has the ToF artefacts, issue 15).
TARGET_ERROR_DEG = 0.01
TARGET_ERROR_CLUTTER_DEG = 0.1
TARGET_CLUTTER = 0.3
TARGET_COVERAGE = (0.93, 0.97)
#: Clutter range over which the interval coverage must hold (issue 15).
TARGET_COVERAGE_CLUTTER = (0.0, 0.4)

#: The ToF artefact levels of the study: the ``[sim.artefacts]`` table of each (ADR 0014).
ARTEFACT_TABLES: dict[str, dict[str, bool]] = {
    "off": {"mixed_pixels": False, "multipath": False, "amplitude_noise": False, "temperature_drift": False},
    "all-but-multipath": {"multipath": False},
    "all": {},
}
ARTEFACT_LEVELS: tuple[str, ...] = tuple(ARTEFACT_TABLES)
#: The level of the inclination and noise sweeps and of the headline figures.
BASE_ARTEFACTS = "all-but-multipath"


# ---------------------------------------------------------------------- settings
@dataclass(frozen=True)
class Condition:
    """One cell of the study's design.

    Attributes:
        height_m: Camera-to-plane distance along the optical axis, metres.
        inclination_deg: Angle between optical axis and plane, degrees (90 = looking straight down).
        noise_scale: Multiplier of the simulated camera's distance noise (1 = default).
        clutter: Requested fraction of the image's plane pixels hidden by boxes, 0..1.
        artefacts: ToF artefact level, a key of :data:`ARTEFACT_TABLES`.
    """

    height_m: float
    inclination_deg: float
    noise_scale: float
    clutter: float
    artefacts: str = BASE_ARTEFACTS

    def key(self) -> str:
        """Stable text key without the artefact level: seeds a condition's trials, so that the
        levels of one condition see the same poses, boxes and noise draws (paired trials)."""
        return f"{self.height_m:.4f}|{self.inclination_deg:.3f}|{self.noise_scale:.3f}|{self.clutter:.3f}"

    def ident(self) -> str:
        """Key with the artefact level (tells conditions apart)."""
        return f"{self.key()}|{self.artefacts}"


@dataclass(frozen=True)
class StudySettings:
    """What the study runs.

    The design is one factor at a time around the paper's setting, each at every
    height: clutter levels at every artefact level (paper inclination, default noise),
    inclinations (no clutter, default noise) and noise scales (no clutter, paper
    inclination), these two at ``base_artefacts``.

    Attributes:
        trials: Trials per condition.
        seed: Root seed.
        heights_m: Heights along the optical axis, metres.
        inclinations_deg: Inclinations of the optical axis to the plane, degrees.
        noise_scales: Noise multipliers of the simulated camera.
        clutter_fractions: Requested fractions of the plane pixels hidden by boxes.
        artefact_levels: ToF artefact levels of the clutter sweep (keys of :data:`ARTEFACT_TABLES`).
        base_artefacts: Artefact level of the other sweeps and of the headline figures.
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
    artefact_levels: tuple[str, ...] = ARTEFACT_LEVELS
    base_artefacts: str = BASE_ARTEFACTS
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
        unknown = [a for a in (*self.artefact_levels, self.base_artefacts) if a not in ARTEFACT_TABLES]
        if unknown or not self.artefact_levels:
            raise CalibrationError(f"artefact levels must be some of {', '.join(ARTEFACT_LEVELS)}, "
                                   f"got {', '.join(unknown) or 'none'}")

    def trials_for(self, condition: Condition) -> int:
        """Trials of one condition (``trials``, times ``headline_factor`` for a headline condition)."""
        headline = (condition.inclination_deg == PAPER_INCLINATION_DEG and condition.noise_scale == 1.0
                    and condition.clutter in (0.0, TARGET_CLUTTER) and condition.artefacts == self.base_artefacts)
        return self.trials * (self.headline_factor if headline else 1)

    def conditions(self) -> list[Condition]:
        """The design's conditions, without duplicates, in a stable order."""
        base_noise = 1.0 if 1.0 in self.noise_scales or not self.noise_scales else self.noise_scales[0]
        incl = PAPER_INCLINATION_DEG if PAPER_INCLINATION_DEG in self.inclinations_deg else self.inclinations_deg[0]
        base = self.base_artefacts
        out: dict[str, Condition] = {}
        for h in self.heights_m:
            cells = [Condition(h, incl, base_noise, c, a) for a in self.artefact_levels
                     for c in self.clutter_fractions or (0.0,)]
            cells += [Condition(h, i, base_noise, 0.0, base) for i in self.inclinations_deg]
            cells += [Condition(h, incl, n, 0.0, base) for n in self.noise_scales]
            for c in cells:
                out.setdefault(c.ident(), c)
        return list(out.values())


def quick_settings(trials: int = 8, seed: int = 0, artefact_levels: tuple[str, ...] = (BASE_ARTEFACTS,)
                   ) -> StudySettings:
    """A small design for CI: the paper's heights and inclination, no clutter and 30 %, the base artefacts."""
    return StudySettings(trials=trials, seed=seed, inclinations_deg=(PAPER_INCLINATION_DEG,),
                         noise_scales=(1.0,), clutter_fractions=(0.0, TARGET_CLUTTER), headline_factor=1,
                         artefact_levels=artefact_levels)


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
        clutter_observed: The fraction the frame shows
            (see :func:`~cellcal.core.study.scene.observed_clutter`).
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


def _trial_seed(root: int, condition: Condition, index: int) -> np.random.SeedSequence:
    return np.random.SeedSequence([root, zlib.crc32(condition.key().encode()), index])


def _empty_row(trial: TrialData, method: str, perimeter: int | None) -> dict[str, Any]:
    c, t = trial.condition, trial.truth
    angle = math.degrees(t.angle_rad)
    return {
        "trial": trial.index, "seed": trial.seed, "height_m": c.height_m, "inclination_deg": c.inclination_deg,
        "noise_scale": c.noise_scale, "clutter_target": c.clutter, "artefacts": c.artefacts,
        "clutter_achieved": trial.clutter_achieved,
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



# ---------------------------------------------------------------------- full frame
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
        rows: One dict per trial x method x perimeter, keys
            :data:`~cellcal.core.study.table.COLUMNS`.
        example: The first trial at the paper's lowest height with the clutter closest
            to 30 % at the base artefact level (None if the run has no such trial).
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
    doc = trial_document(pose, boxes, seed, condition.noise_scale, settings.camera,
                         ARTEFACT_TABLES[condition.artefacts])
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
    camera = build_camera(doc, registry, source="<study>")
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
                        and cond.inclination_deg == PAPER_INCLINATION_DEG and cond.artefacts == settings.base_artefacts
                        and (fit is None or trial.full_frame is not None)):
                    example = trial
                if bar is not None:
                    bar.update(1)
    finally:
        if bar is not None:
            bar.close()
    return StudyResult(settings, rows, example, fit is not None)

