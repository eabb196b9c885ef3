"""Run a hand-eye plan with the calibrate machinery and estimate the mount.

The poses are measured by :class:`~cellcal.core.calibration.calibrator.Calibrator`
(full-frame method only) with the generated or configured plan in place of its own, so
the safety envelope, the per-pose resume journal, the output lock and recording work
as for ``calibrate``; the estimate comes from the poses' full-frame planes (ADR 0018).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from cellcal.core.calibration.calibrator import Calibrator, PoseCompanion, ProgressFactory
from cellcal.core.calibration.config import CellConfig
from cellcal.core.calibration.journal import journal_path, remove_journal
from cellcal.core.calibration.outlock import OutputLock
from cellcal.core.calibration.record import PoseRecord
from cellcal.core.calibration.report import write_json_atomic
from cellcal.core.geometry.planes import Plane
from cellcal.core.handeye.estimator import ArmAccuracy, HandEyeEstimate, estimate_mount, observability
from cellcal.core.handeye.model import PlaneObservation, observation_from_pose
from cellcal.core.handeye.observability import Observability
from cellcal.core.handeye.result import HANDEYE_FILENAME, handeye_document, plane_sections
from cellcal.core.methods.fullframe import FullFrameResult
from cellcal.devices.arm_model import ArmModel
from cellcal.devices.camera import Camera3D
from cellcal.devices.errors import CalibrationQualityError, ConfigError
from cellcal.devices.pose import Pose
from cellcal.devices.safety import SafeArm
from cellcal.devices.types import Frame
from cellcal.devices.version import cellcal_version


class OtherMounts(PoseCompanion, Protocol):
    """The run's other cameras on the flange (:class:`~cellcal.core.handeye.several.FlangeCameras`): captured at
    each pose beside the driven one (a companion and a pose observer), each estimated after the plan."""

    def __call__(self, record: PoseRecord, frames: Sequence[Frame], result: FullFrameResult | None) -> None:
        """Collect this pose's captures and fit their planes."""

    def estimate_and_write(self, config: CellConfig, arm_model: ArmModel | None, out_dir: Path,
                           header: Mapping[str, Any]) -> Sequence[Any]:
        """Estimate each camera's mount and write its ``DIR/handeye-NAME.json``."""


#: Typical 1-sigma of a full-frame plane (normal, rad; offset, m) for the check before the run.
TYPICAL_NORMAL_SIGMA_RAD = 5e-5
TYPICAL_OFFSET_SIGMA_M = 2e-5


def plane_config(config: CellConfig) -> CellConfig:
    """``config`` measuring only the full-frame plane at each pose (what the estimate needs)."""
    return dataclasses.replace(config, plan=dataclasses.replace(config.plan, methods=("full_frame",)))


def reference_plane(config: CellConfig, command: str = "cellcal handeye") -> Plane:
    """The configured base-frame plane (``[reference]``), the estimate's start.

    Args:
        config: The cell.
        command: Who needs it, for the message.

    Raises:
        ConfigError: Without a ``[reference]`` table.
    """
    ref = config.reference
    if ref is None:
        raise ConfigError(f"{command} needs a [reference] plane (the start of the plane estimate)",
                          source=config.source, key="reference")
    return Plane.from_point_normal(ref.plane_point_m, ref.plane_normal)


def predicted_observations(config: CellConfig, poses: Sequence[Pose]) -> list[PlaneObservation]:
    """The observations the plan would give with the configured mount and plane (typical noise)."""
    mount, plane = config.mount.pose(), reference_plane(config)
    out = []
    for flange in poses:
        camera = flange @ mount
        n = camera.rotation.inv().apply(np.array(plane.normal))
        offset = plane.offset_m + float(np.array(plane.normal) @ camera.translation)
        sign = 1.0 if offset > 0 else -1.0  # normal toward the camera
        cov = np.zeros((4, 4))
        cov[:3, :3] = TYPICAL_NORMAL_SIGMA_RAD**2 * (np.eye(3) - np.outer(n, n))
        cov[3, 3] = TYPICAL_OFFSET_SIGMA_M**2
        out.append(PlaneObservation(flange, sign * n, abs(offset), cov))
    return out


def check_observability(config: CellConfig, poses: Sequence[Pose]) -> Observability:
    """What the plan can see, from the configured mount and plane, before anything moves.

    Raises:
        CalibrationQualityError: Gate ``observability``, naming what cannot be seen and how to fix it.
    """
    he = config.handeye
    seen = observability(predicted_observations(config, poses), config.mount.pose(), reference_plane(config),
                         given=he.given, arm_translation_sigma_m=he.arm_translation_sigma_m,
                         arm_rotation_sigma_rad=math.radians(he.arm_rotation_sigma_deg))
    if not seen.observable:
        raise CalibrationQualityError("observability", seen.rank, seen.n_parameters,
                                      f"{len(poses)} poses {seen.message()}")
    return seen


def arm_accuracy(model: ArmModel | None) -> ArmAccuracy | None:
    """What the hand-eye fit takes from an arm's stated model: its absolute accuracy (None: no model)."""
    return None if model is None else ArmAccuracy(model.accuracy_m, model.accuracy_rad, model.source)


def estimate_from_document(config: CellConfig, document: Mapping[str, Any],
                           arm_model: ArmModel | None = None, mount: Pose | None = None) -> HandEyeEstimate:
    """The plane method's estimate from a ``calibrate``-style result document of the plan.

    ``arm_model``: the arm's stated accuracy, in the weights and intervals (None: the read-back noise of
    ``[handeye]`` alone). ``mount``: the camera's configured ``T_flange_camera``, the estimate's start (None:
    the configuration's ``[mount]``; another camera on the flange gives its own, ADR 0061).
    """
    he = config.handeye
    observations = [observation_from_pose(pose) for pose in document["poses"]]
    nominal = config.mount.pose() if mount is None else mount
    return estimate_mount(observations, nominal, reference_plane(config), given=he.given,
                          given_sigma=he.given_sigma, arm_translation_sigma_m=he.arm_translation_sigma_m,
                          arm_rotation_sigma_rad=math.radians(he.arm_rotation_sigma_deg), confidence=he.confidence,
                          noise_test_level=he.noise_test_level, max_interval_scale=he.max_interval_scale,
                          arm_accuracy=arm_accuracy(arm_model))


def mount_covariance(estimate: HandEyeEstimate) -> np.ndarray:
    """The 6x6 covariance of the mount (turn about the flange axes, rad; translation, m) the intervals use."""
    return estimate.covariance[:6, :6]


def plan_calibrator(config: CellConfig, camera: Camera3D, arm: SafeArm, poses: Sequence[Pose],
                    progress: ProgressFactory | None = None, others: OtherMounts | None = None) -> Calibrator:
    """A calibrator measuring the full-frame plane at ``poses`` instead of its own plan.

    ``others``: the cell's other cameras on the flange, captured at each pose beside the driven one (ADR 0061).
    """
    calibrator = Calibrator(plane_config(config), camera, arm, progress=progress, observer=others, companion=others)
    calibrator.poses = list(poses)
    return calibrator


def handeye_result(config: CellConfig, estimate: HandEyeEstimate, flanges: Sequence[Pose], configured: Pose,
                   header: Mapping[str, Any]) -> dict[str, Any]:
    """The ``handeye.json`` document of one camera's plane-method estimate (``configured``: its ``[mount]``)."""
    return handeye_document(estimate.mount, mount_covariance(estimate), estimate.confidence, configured,
                            header=header, sections=plane_sections(estimate, flanges), z=estimate.z,
                            interval_scale=estimate.interval_scale)


def run_handeye(calibrator: Calibrator, out_dir: str | Path, *, plan_kind: str, resume: bool = False,
                others: OtherMounts | None = None) -> dict[str, Any]:
    """Measure the plan (journal beside the output), estimate, write ``DIR/handeye.json`` atomically.

    With ``others`` (the calibrator's companion) each other camera on the flange is estimated from its own
    poses and written to ``DIR/handeye-NAME.json`` first (:meth:`OtherMounts.estimate_and_write`; one
    that cannot be estimated is said in ``others.outcomes``), so they are there even when the driven
    camera's estimate fails.

    Raises:
        CellcalError, KeyboardInterrupt: As :meth:`Calibrator.run`; CalibrationQualityError
            (gate ``observability``) if the measured poses leave a parameter unobservable, (gate
            ``noise_model``) if their residuals are far beyond the stated noise.
    """
    out = Path(out_dir) / HANDEYE_FILENAME
    journal = journal_path(out)
    config = calibrator.config
    with OutputLock.for_directory(out.parent):
        measured = calibrator.run(journal=journal, resume=resume)
        arm_model = calibrator.arm.arm_model()
        header = {"cellcal_version": cellcal_version(), "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
                  "config_source": config.source, "camera": config.camera_name, "plan": plan_kind, "method": "plane",
                  "commanded_flange_poses": [p.to_dict() for p in calibrator.poses],
                  "arm_model": arm_model.to_dict(),
                  **({"resumed_poses": measured["resumed_poses"]} if "resumed_poses" in measured else {})}
        if others is not None:
            others.estimate_and_write(config, arm_model, out.parent, header)
        estimate = estimate_from_document(config, measured, arm_model)
        flanges = [Pose.from_dict(p["reported_flange_pose"]) for p in measured["poses"]]
        document = handeye_result(config, estimate, flanges, config.mount.pose(), header)
        write_json_atomic(out, document)
        remove_journal(journal)
    return document


__all__ = ["arm_accuracy", "check_observability", "estimate_from_document", "handeye_result", "plan_calibrator",
           "plane_config", "predicted_observations", "reference_plane", "run_handeye"]
