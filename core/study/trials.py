"""Monte Carlo trials of the calibration methods on the simulated cell.

A trial places the sim camera at one pose over the plane (height, inclination), with a
fresh noise seed and fresh boxes and the ToF artefacts of its level, captures one frame
and runs every method on it (:func:`run_trial`); :func:`run_study` runs every trial of
every condition, in this process or on a process pool (:mod:`cellcal.core.study.pool`).
Seeded throughout; the design and its rationale are in ADRs 0012 and 0021 (the pool).
"""

from __future__ import annotations

import importlib
import math
import zlib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cellcal.core.calibration.calibrator import build_camera
from cellcal.core.calibration.config import look_at_pose
from cellcal.core.methods.measure import ExpectedGeometry, expected_geometry, measure_frames
from cellcal.core.study.design import (
    ARTEFACT_TABLES,
    FULL_FRAME,
    GRID_METHODS,
    PAPER_INCLINATION_DEG,
    TARGET_CLUTTER,
    Condition,
    StudySettings,
)
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
    "FullFrameFit",
    "StudyResult",
    "TrialData",
    "full_frame_fitter",
    "full_frame_row",
    "grid_rows",
    "run_study",
    "run_trial",
    "study_intrinsics",
]

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


#: A worker's state for :func:`_run_in_worker`, set once per process by :func:`_init_worker`.
_WORKER: dict[str, Any] = {}


def _init_worker(settings: StudySettings, registry: Registry | None, intrinsics: Intrinsics) -> None:
    """Worker start (:func:`cellcal.core.study.pool.run_tasks`): build what every trial needs.

    ``intrinsics`` come from the parent (building the study's camera for them costs a
    second or so, once per process otherwise).
    """
    _WORKER.update(settings=settings, registry=registry, intrinsics=intrinsics,
                   fit=full_frame_fitter(settings.full_frame))


def _run_in_worker(task: tuple[Condition, int]) -> list[dict[str, Any]]:
    """One trial in a worker; its rows (the frame stays in the worker)."""
    condition, index = task
    _, rows = run_trial(_WORKER["settings"], condition, index, _WORKER["intrinsics"], _WORKER["fit"],
                        _WORKER["registry"])
    return rows


def _is_example(settings: StudySettings, condition: Condition, height_m: float, clutter: float) -> bool:
    """Whether the condition's trials may serve as the plane-fit picture's example."""
    return (condition.height_m == height_m and condition.clutter == clutter
            and condition.inclination_deg == PAPER_INCLINATION_DEG and condition.artefacts == settings.base_artefacts)


def run_study(settings: StudySettings, *, registry: Registry | None = None,
              progress: Callable[[int], Any] | None = None, jobs: int = 1) -> StudyResult:
    """Run every trial of every condition.

    With ``jobs`` > 1 the trials run on that many worker processes
    (:mod:`cellcal.core.study.pool`); the rows are the same, in the same order.

    Args:
        settings: The design.
        registry: Device registry (default: the process-wide one).
        progress: Optional factory ``total -> tqdm-like`` (``update(n)``, ``close()``).
        jobs: Worker processes; 1 runs every trial in this process.
    """
    if jobs < 1:
        raise CalibrationError(f"jobs must be >= 1, got {jobs}")
    intr = study_intrinsics(settings, registry)
    fit = full_frame_fitter(settings.full_frame)
    conditions = settings.conditions()
    example_clutter = min((c.clutter for c in conditions), key=lambda v: abs(v - TARGET_CLUTTER))
    example_height = min(c.height_m for c in conditions)
    tasks = [(c, i) for c in conditions for i in range(settings.trials_for(c))]
    candidates = [k for k, (c, _) in enumerate(tasks) if _is_example(settings, c, example_height, example_clutter)]
    bar = progress(len(tasks)) if progress else None
    trials: dict[int, TrialData] = {}
    is_candidate = set(candidates)

    def run_here(k: int) -> list[dict[str, Any]]:  # one trial in this process, its data kept if an example
        trial, trial_rows = run_trial(settings, tasks[k][0], tasks[k][1], intr, fit, registry)
        if not trials and k in is_candidate and (fit is None or trial.full_frame is not None):
            trials[k] = trial  # the first good one only (a frame is large)
        return trial_rows

    def done(k: int, trial_rows: list[dict[str, Any]]) -> None:
        if bar is not None:
            bar.update(1)

    try:
        if jobs == 1:
            per_task = []
            for k in range(len(tasks)):
                per_task.append(run_here(k))
                done(k, per_task[-1])
        else:
            from cellcal.core.study.pool import run_tasks

            first = (candidates[0], lambda _task: run_here(candidates[0])) if candidates else None
            per_task = run_tasks(tasks, jobs, _run_in_worker, done, local=first, initializer=_init_worker,
                                 initargs=(settings, registry, intr))
    finally:
        if bar is not None:
            bar.close()
    return StudyResult(settings, [row for r in per_task for row in r],
                       _example(trials, candidates, per_task, run_here), fit is not None)


def _example(trials: dict[int, TrialData], candidates: list[int], per_task: list[list[dict[str, Any]]],
             run_here: Callable[[int], Any]) -> TrialData | None:
    """The first candidate trial whose full frame succeeded (re-run here if a worker ran it)."""
    for k in candidates:
        if k in trials:
            return trials[k]
        if all(r["ok"] for r in per_task[k] if r["method"] == FULL_FRAME):
            run_here(k)  # deterministic: the same trial as the worker's
            return trials.get(k)
    return None
