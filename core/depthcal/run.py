"""Run the ``cellcal depthcal`` plan with the calibrate machinery and fit the camera's systematic depth error.

The poses are driven by a :class:`~cellcal.core.calibration.calibrator.Calibrator` whose
per-pose measurement is only: move (through the safety wrapper, which confirms the
arrival), settle, capture the raw frames, read the flange pose back. So the safety
envelope, the arm-class check, the deadlines, the output lock, recording and replay work
as for ``calibrate``. Each pose's frames are kept in ``DIR/depthcal.frames/`` (written
before the pose enters the resume journal, so ``--resume`` finds every journaled pose's
frames); both go once ``DIR/depthcal.json`` is written (ADR 0057).
"""

from __future__ import annotations

import io
import json
import shutil
from collections.abc import Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from cellcal.core.calibration.calibrator import Calibrator, ProgressFactory
from cellcal.core.calibration.config import CellConfig
from cellcal.core.calibration.journal import journal_path, remove_journal
from cellcal.core.calibration.outlock import OutputLock
from cellcal.core.calibration.record import PoseRecord
from cellcal.core.calibration.report import write_bytes_atomic, write_json_atomic
from cellcal.core.depthcal.plan import PlanView, plan_coverage
from cellcal.devices.arm_model import ArmModel
from cellcal.devices.camera import Camera3D
from cellcal.devices.errors import CalibrationError
from cellcal.devices.pose import Pose
from cellcal.devices.recording.codec import decode_model, encode_model
from cellcal.devices.safety import SafeArm
from cellcal.devices.types import Frame, Intrinsics
from cellcal.devices.version import cellcal_version

__all__ = ["DEPTHCAL_FILENAME", "FRAMES_DIRNAME", "DepthcalCalibrator", "load_frames", "raw_camera", "run_depthcal",
           "save_frames"]

#: The result file in the output directory.
DEPTHCAL_FILENAME = "depthcal.json"
#: The directory of the measured poses' frames, beside the result, while the run is not finished.
FRAMES_DIRNAME = "depthcal.frames"
_ARRAYS = ("distance", "xyz", "amplitude", "valid", "confidence")


def raw_camera(camera: Camera3D) -> Camera3D:
    """The camera without a ``[camera.correction]`` (its ``raw`` camera), else ``camera`` itself.

    A depth calibration fits what the sensor measures: a correction applied before it would
    be fitted again on top of itself.
    """
    raw = getattr(camera, "raw", None)
    return raw if isinstance(raw, Camera3D) and raw is not camera else camera


def save_frames(path: Path, frames: Sequence[Frame]) -> None:
    """Write ``frames`` to one ``.npz`` file atomically (arrays as they are; the rest as JSON)."""
    arrays: dict[str, Any] = {}
    meta = []
    for k, f in enumerate(frames):
        for name in _ARRAYS:
            value = getattr(f, name)
            if value is not None:
                arrays[f"{k}_{name}"] = value
        meta.append({"timestamp": float(f.timestamp), "sequence": int(f.sequence), "intrinsics": f.intrinsics.to_dict(),
                     "metadata": f.metadata, "measurement": encode_model(f.measurement) if f.measurement.known
                     else None})
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode("utf-8"), dtype=np.uint8)
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    write_bytes_atomic(path, buffer.getvalue())


def load_frames(path: Path) -> list[Frame]:
    """The frames :func:`save_frames` wrote.

    Raises:
        CalibrationError: If the file is missing or damaged.
    """
    try:
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(bytes(data["meta"]).decode("utf-8"))
            frames = []
            for k, m in enumerate(meta):
                arrays = {name: data[f"{k}_{name}"] for name in _ARRAYS if f"{k}_{name}" in data}
                frames.append(Frame(intrinsics=Intrinsics(**m["intrinsics"]), timestamp=float(m["timestamp"]),
                                    sequence=int(m["sequence"]), metadata=dict(m["metadata"]),
                                    measurement=decode_model(m["measurement"], "frame.measurement"), **arrays))
    except FileNotFoundError:
        raise CalibrationError(f"{path}: the frames of a journaled pose are missing; run without --resume to "
                               "start afresh") from None
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise CalibrationError(f"{path}: the saved frames are damaged ({type(exc).__name__}); run without --resume "
                               "to start afresh") from None
    return frames


class DepthcalCalibrator(Calibrator):
    """A calibrator that moves to the depthcal plan's poses and keeps each pose's raw frames.

    Args:
        config: The cell.
        camera: The camera (raw: see :func:`raw_camera`).
        arm: The arm behind the safety wrapper.
        views: The plan (:func:`~cellcal.core.depthcal.plan.depthcal_plan`).
        frames_dir: Where each pose's frames are written before it is journaled.
        progress: Optional progress-bar factory.
    """

    def __init__(self, config: CellConfig, camera: Camera3D, arm: SafeArm, views: Sequence[PlanView],
                 frames_dir: Path, progress: ProgressFactory | None = None) -> None:
        super().__init__(config, camera, arm, progress=progress)
        self.views = list(views)
        self.poses = [v.pose for v in self.views]
        self.frames_dir = frames_dir
        #: Each pose's frames, by plan index (those measured by this run; resumed ones are read back).
        self.frames: dict[int, list[Frame]] = {}

    def frames_path(self, index: int) -> Path:
        """The file of plan pose ``index``'s frames."""
        return self.frames_dir / f"pose-{index + 1:03d}.npz"

    def _check_image(self) -> None:
        """No check: the ``[plan]`` grid is not measured here."""

    def _measure_and_journal(self, index: int) -> tuple[PoseRecord, dict[str, Any]]:
        """Measure pose ``index``, check the arm, write its frames, then journal it."""
        record = self._measure_pose(index, self.poses[index])
        self._check_arm_ready(f"after plan pose {index + 1}")
        data = record.to_dict()
        if self.journal_writer is not None:
            save_frames(self.frames_path(index), self.frames[index])
            self.journal_writer.append(index, data, self._device_state())
        return record, data

    def _measure_pose(self, index: int, target: Pose) -> PoseRecord:
        """Move (the safety wrapper confirms the arrival), settle, capture the frames, read the flange back."""
        frames, reported, timings = self._move_and_capture(index, target, self.config.depthcal.frames_per_pose)
        self.frames[index] = frames
        return PoseRecord(index, target, reported, reported @ self.config.mount.pose(), None, [],
                          timings, frames[0].intrinsics, None)


def _views(calibrator: DepthcalCalibrator, measured: dict[str, Any]) -> list[Any]:
    """One :class:`DepthcalView` per frame of every measured pose, in plan order (resumed frames read back)."""
    from cellcal.core.depthcal.view import DepthcalView

    views = []
    for pose in measured["poses"]:
        index = int(pose["index"])
        frames = calibrator.frames.get(index)
        if frames is None:
            frames = load_frames(calibrator.frames_path(index))
        flange = Pose.from_dict(pose["reported_flange_pose"])
        for k, frame in enumerate(frames):
            name = f"pose {index + 1}" + (f" frame {k + 1}" if len(frames) > 1 else "")
            views.append(DepthcalView(frame, flange, name))
    return views


def fit_plan(config: CellConfig, views: Sequence[Any], arm_model: ArmModel | None = None) -> Any:
    """The fit of the measured views (:func:`cellcal.core.depthcal.fit.fit_depthcal`) with ``[depthcal]``'s settings.

    ``arm_model``: the arm's stated accuracy, in the intervals (None: the reported flanges as exact). A
    ToF camera's wiggling is fitted at ``[depthcal] wiggle_period_m``, else at the period its
    measurement model states when it allows for a wiggle (the default 1 mm at c/(8 * 60 MHz)).
    """
    from cellcal.core.depthcal.fit import fit_depthcal
    from cellcal.core.handeye.run import arm_accuracy

    dc = config.depthcal
    model = views[0].frame.measurement
    period = dc.wiggle_period_m
    if period is None and model.kind == "tof" and model.wiggle[0] > 0.0:
        period = model.wiggle[1]
    return fit_depthcal(views, mount=config.mount.pose(), model=model,
                        field_orders=tuple(range(dc.field_max_order + 1)),
                        holdout_every=dc.holdout_every * dc.frames_per_pose,
                        max_points_per_view=dc.max_points_per_view, wiggle_period_m=period,
                        seed=config.cell.seed, arm_accuracy=arm_accuracy(arm_model))


def run_depthcal(calibrator: DepthcalCalibrator, out_dir: str | Path, *, resume: bool = False
                 ) -> tuple[dict[str, Any], Any, list[Any]]:
    """Measure the plan (journal and frames beside the output), fit, write ``DIR/depthcal.json`` atomically.

    Returns:
        The document written, the fit (``DepthcalResult``) and the views it was fitted on.

    Raises:
        CellcalError, KeyboardInterrupt: As :meth:`Calibrator.run`, and the fit's refusals; the journal
            and the frames stay for ``--resume``.
    """
    out = Path(out_dir) / DEPTHCAL_FILENAME
    journal = journal_path(out)
    config = calibrator.config
    with OutputLock.for_directory(out.parent):
        if not resume:  # a fresh run: frames of an older interrupted one are not this run's
            shutil.rmtree(calibrator.frames_dir, ignore_errors=True)
        calibrator.frames_dir.mkdir(parents=True, exist_ok=True)
        measured = calibrator.run(journal=journal, resume=resume)
        views = _views(calibrator, measured)
        result = fit_plan(config, views, calibrator.arm.arm_model())
        document = {**{k: v for k, v in result.to_dict().items() if k != "elapsed_s"},
                    "timings_s": {"fit": result.elapsed_s},  # what a replay does not reproduce
                    "cellcal_version": cellcal_version(),
                    "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
                    "config_source": config.source,
                    "coverage": plan_coverage(config, calibrator.views).message(),
                    "plan": [{"label": v.label(), "height_m": v.height_m, "inclination_deg": v.inclination_deg,
                              "roll_deg": v.roll_deg, "target_m": list(v.target_m),
                              "commanded_flange_pose": v.pose.to_dict(),
                              "reported_flange_pose": measured["poses"][i]["reported_flange_pose"]}
                             for i, v in enumerate(calibrator.views)],
                    **({"resumed_poses": measured["resumed_poses"]} if "resumed_poses" in measured else {})}
        if config.depthcal.frames_per_pose > 1:  # held out by view: a held-out frame's pose-mates were fitted
            document["notes"] = [*document.get("notes", []), "each pose's frames are views of their own: a held-out "
                                 "frame's other frames were fitted, so the held-out error is optimistic "
                                 "(frames_per_pose = 1 gives an honest one)"]
        write_json_atomic(out, document)
        remove_journal(journal)
        shutil.rmtree(calibrator.frames_dir, ignore_errors=True)
    return document, result, views
