"""``cellcal handeye`` for a fixed camera (``on = "base"``): the arm shows it the plate, the camera's pose is fitted.

The plan (:func:`fixed_plan`) puts the ``[plate]``'s face on the camera's optical axis at
``distance_m``, face-on and tilted, the flange rolled in turn (:func:`~.fixed_plan.plate_poses`).
A :class:`FixedCalibrator` drives it with the calibrate machinery (safety wrapper, arrival
check, deadlines, journal and ``--resume``, output lock) and, at each pose, fits the plate's
plane with the full-frame fit inside the face's outline predicted from the reported flange pose
and the configured camera pose (:func:`plate_region`), searching near the predicted plane. The
poses' planes go to :func:`~.fixed.estimate_fixed_camera`; ``DIR/handeye-NAME.json`` holds the
result (ADR 0061).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cellcal.core.calibration.calibrator import Calibrator, ProgressFactory
from cellcal.core.calibration.cameras import PlateSection
from cellcal.core.calibration.config import CellConfig
from cellcal.core.calibration.journal import journal_path, remove_journal
from cellcal.core.calibration.outlock import OutputLock
from cellcal.core.calibration.record import PoseRecord
from cellcal.core.calibration.region import polygon_mask
from cellcal.core.calibration.report import write_json_atomic
from cellcal.core.geometry.planes import Plane
from cellcal.core.handeye.fixed import FixedCameraEstimate, estimate_fixed_camera, fixed_observability
from cellcal.core.handeye.fixed_plan import FIXED_PARAMETERS, FixedObservability, plate_poses
from cellcal.core.handeye.model import PlaneObservation, observation_from_pose, plane_covariance
from cellcal.core.methods.fullframe.points import ExpectedPlane
from cellcal.core.methods.measure import full_frame_document, measure_full_frame
from cellcal.devices.arm_model import ArmModel
from cellcal.devices.camera import Camera3D
from cellcal.devices.errors import CalibrationError, CalibrationQualityError, ConfigError
from cellcal.devices.geometry.camera_model import project
from cellcal.devices.pose import Pose
from cellcal.devices.safety import SafeArm
from cellcal.devices.types import Intrinsics
from cellcal.devices.version import cellcal_version

__all__ = ["FIXED_SCHEMA", "FixedCalibrator", "check_fixed_plan", "check_plate_in_view", "fixed_document",
           "fixed_filename", "fixed_plan", "plate_document", "plate_plane", "plate_region", "run_fixed_handeye",
           "systematic_section"]

#: Schema of ``DIR/handeye-NAME.json``.
FIXED_SCHEMA = "cellcal.handeye-fixed/1"
#: How far the fitted plate may lie from the predicted one (the configured camera pose may be rough).
SEARCH_ANGLE_RAD = math.radians(10.0)
SEARCH_OFFSET_M = 0.05


def fixed_filename(name: str) -> str:
    """The result file of fixed camera ``name``."""
    return f"handeye-{name}.json"


def plate_plane(plate: PlateSection) -> Plane:
    """The plate's measured face in the flange frame (its normal the plate frame's -z: out of the face)."""
    pose = plate.pose()
    return Plane.from_point_normal(pose.translation, -pose.rotation_matrix[:, 2])


def _camera_base(config: CellConfig) -> Pose:
    entry = config.camera_entry
    if entry.on != "base" or entry.pose_base is None:
        raise ConfigError(f"camera {entry.name!r} is not fixed (on = \"base\")", source=config.source,
                          key="cameras")
    return entry.pose_base


def fixed_plan(config: CellConfig) -> tuple[list[Pose], list[str]]:
    """The flange poses that show ``[plate]`` to the configuration's fixed camera, inside the envelope and reach.

    Returns:
        The poses kept, and one line per pose left out (its number among those generated and the first rule
        it breaks). Each pose is checked on its own here; the moves between them are checked before and
        while the arm moves, as for every plan.
    """
    from cellcal.core.calibration.dryrun import check_moves
    from cellcal.core.calibration.reach import arm_reach

    plate, limits, reach = config.plate, config.safety_limits(), arm_reach(config)
    poses = plate_poses(_camera_base(config), distance_m=plate.distance_m, plate_flange=plate_plane(plate),
                        tilts_deg=plate.tilts_deg, plate_centre_flange_m=plate.translation_m)
    kept, dropped = [], []
    for i, pose in enumerate(poses):
        check = check_moves(limits, [pose], config.plan.speed_m_s, config.plan.acceleration_m_s2, reach=reach)[0]
        if check.ok:
            kept.append(pose)
        else:
            dropped.append(f"plate pose {i + 1} of {len(poses)} left out: {check.problems[0]}")
    if not kept:
        raise CalibrationError(f"every one of the {len(poses)} plate poses breaks the envelope or the arm's reach "
                               f"(first: {dropped[0].partition(': ')[2]}): change [plate] distance_m or tilts_deg, "
                               "or [safety]")
    return kept, dropped


def plate_region(intrinsics: Intrinsics, camera_base: Pose, flange: Pose, plate: PlateSection
                 ) -> NDArray[np.bool_]:
    """The pixels inside the face's central ``region_share`` as the camera sees it from ``camera_base``.

    Raises:
        CalibrationError: The face is behind the camera or outside the image at this pose.
    """
    corners_cam = (camera_base.inv() @ flange).apply(plate.corners_flange(plate.region_share))
    if np.any(corners_cam[:, 2] <= 0.05):
        raise CalibrationError("the plate is behind the camera or within 5 cm of it")
    mask = polygon_mask(project(intrinsics, corners_cam), (intrinsics.height, intrinsics.width))
    if int(np.count_nonzero(mask)) < 100:
        raise CalibrationError(f"the plate covers {int(np.count_nonzero(mask))} pixels of the image (needs >= 100): "
                               "outside the view, or too far")
    return mask


def check_plate_in_view(config: CellConfig, poses: Sequence[Pose], intrinsics: Intrinsics) -> None:
    """Every pose shows the plate inside the image, as the configured camera pose predicts.

    Raises:
        CalibrationError: Naming the poses whose plate is out of view (all of them: the plate and the camera
            do not face each other as configured).
    """
    camera_base = _camera_base(config)
    out = []
    for i, pose in enumerate(poses):
        try:
            plate_region(intrinsics, camera_base, pose, config.plate)
        except CalibrationError:
            out.append(i + 1)
    if len(out) == len(poses):
        raise CalibrationError(f"the plate is outside camera {config.camera_name!r}'s view at every pose of the "
                               "plan: check [cameras.pose] and [plate] (where the camera looks, where the plate is on "
                               "the flange, distance_m)")
    if out:
        raise CalibrationError(f"the plate is outside camera {config.camera_name!r}'s view at plate pose(s) "
                               f"{', '.join(map(str, out))} of {len(poses)}: lower [plate] tilts_deg or distance_m")


#: Expected 1-sigma of a plate's plane fit, for the plan's observability (a ToF camera at 0.6 m over ~5000 pixels).
NOMINAL_NORMAL_SIGMA_RAD = math.radians(0.05)
NOMINAL_OFFSET_SIGMA_M = 2e-4


def check_fixed_plan(config: CellConfig, poses: Sequence[Pose]) -> FixedObservability:
    """What the plan can see, from the plate views it predicts (before anything connects).

    Raises:
        CalibrationQualityError: Gate ``observability``, naming what the plan cannot see and the fix.
    """
    camera_base = _camera_base(config)
    plate = plate_plane(config.plate)
    views = []
    for flange in poses:
        seen = plate.transformed(camera_base.inv() @ flange).oriented_toward_origin()
        n = np.asarray(seen.normal, dtype=np.float64)
        normal_cov = NOMINAL_NORMAL_SIGMA_RAD**2 * (np.eye(3) - np.outer(n, n))   # across the normal only
        cov = plane_covariance(normal_cov, NOMINAL_OFFSET_SIGMA_M, np.zeros(3))
        views.append(PlaneObservation(flange, n, float(seen.offset_m), cov))
    result = fixed_observability(views, camera_base, plate, estimate_plate=config.plate.estimate)
    if not result.observable:
        raise CalibrationQualityError("observability", result.rank, result.n_parameters, result.message())
    return result


class FixedCalibrator(Calibrator):
    """A calibrator that shows the plate to the fixed camera at the plan's poses and fits its face at each."""

    def __init__(self, config: CellConfig, camera: Camera3D, arm: SafeArm, poses: Sequence[Pose],
                 progress: ProgressFactory | None = None, left_out: Sequence[str] = ()) -> None:
        super().__init__(config, camera, arm, progress=progress)
        self.poses = list(poses)
        #: The plan's poses left out before the run, one line each (:func:`fixed_plan`), for the result.
        self.left_out = list(left_out)
        self.camera_base = _camera_base(config)
        #: The measuring plane as the camera saw it before the first move (:meth:`_table_view`).
        self.table: dict[str, Any] | None = None

    def _check_image(self) -> None:
        """Before the first move: the plate in the camera's view at every pose; the measuring plane as it sees it."""
        t = self.camera.default_timeout_s
        intrinsics = self.guards["camera"].call(lambda: self.camera.intrinsics, t, "intrinsics")
        check_plate_in_view(self.config, self.poses, intrinsics)
        self.table = self._table_view(intrinsics)

    def _table_view(self, intrinsics: Intrinsics) -> dict[str, Any] | None:
        """The ``[reference]`` plane as the fixed camera sees it before the first move, the plate's outline (1.5x)
        left out: its ``full_frame`` section, ``{"error": ...}`` when no plane is found there, None without a
        ``[reference]``. Not journaled: a resumed run measures it again (the arm has not moved yet)."""
        import dataclasses

        ref = self.config.reference
        if ref is None:
            return None
        flange = self._flange_pose()
        t = self.config.plan.capture_timeout_s
        frames = [self.guards["camera"].call(lambda: self.camera.capture(t), t, f"capture(timeout={t:g} s)")]
        try:
            plate = plate_region(intrinsics, self.camera_base, flange,
                                 dataclasses.replace(self.config.plate, region_share=1.5))
        except CalibrationError:
            plate = np.zeros((intrinsics.height, intrinsics.width), dtype=bool)   # not in view: nothing to leave out
        expected = Plane.from_point_normal(ref.plane_point_m, ref.plane_normal).transformed(self.camera_base.inv())
        search = ExpectedPlane(expected.oriented_toward_origin(), SEARCH_ANGLE_RAD, SEARCH_OFFSET_M)
        try:
            _row, result = measure_full_frame(frames, self.config.full_frame, region=~plate, expected_plane=search)
        except CalibrationError as exc:
            return {"error": str(exc)}
        return full_frame_document(result, self.camera_base, None, expected_plane=search)

    def _measure_pose(self, index: int, target: Pose) -> PoseRecord:
        """Move (the safety wrapper confirms the arrival), capture, fit the plate inside its predicted outline."""
        frames, reported, timings = self._move_and_capture(index, target, self.config.plan.frames_per_pose)
        predicted = plate_plane(self.config.plate).transformed(self.camera_base.inv() @ reported)
        try:
            region = plate_region(frames[0].intrinsics, self.camera_base, reported, self.config.plate)
            search = ExpectedPlane(predicted.oriented_toward_origin(), SEARCH_ANGLE_RAD, SEARCH_OFFSET_M)
            row, result = measure_full_frame(frames, self.config.full_frame, region=region, expected_plane=search)
        except CalibrationQualityError as exc:
            raise CalibrationQualityError(exc.gate, exc.value, exc.threshold, f"plate pose {index + 1}",
                                          unit=exc.unit) from None
        except CalibrationError as exc:
            raise CalibrationError(f"plate pose {index + 1}: {exc}") from None
        document = full_frame_document(result, self.camera_base, None, expected_plane=search)
        return PoseRecord(index, target, reported, self.camera_base, None, [row], timings, frames[0].intrinsics,
                          document)


def estimate_from_poses(config: CellConfig, measured: dict[str, Any], arm_model: ArmModel | None
                        ) -> FixedCameraEstimate:
    """The fixed camera's estimate from the measured poses' plate planes."""
    from cellcal.core.handeye.run import arm_accuracy

    observations = [observation_from_pose(pose) for pose in measured["poses"]]
    return estimate_fixed_camera(observations, _camera_base(config), plate_plane(config.plate),
                                 estimate_plate=config.plate.estimate, arm_accuracy=arm_accuracy(arm_model),
                                 confidence=config.handeye.confidence,
                                 noise_test_level=config.handeye.noise_test_level,
                                 max_interval_scale=config.handeye.max_interval_scale)


def fixed_document(config: CellConfig, estimate: FixedCameraEstimate, header: dict[str, Any]) -> dict[str, Any]:
    """The JSON result of a fixed camera's calibration (SI; the pose's roll, pitch, yaw also in degrees)."""
    rpy, sigma = estimate.rpy_and_sigma_deg()
    return {"schema": FIXED_SCHEMA, **header, "camera": config.camera_name, "on": "base",
            **estimate.to_dict(),
            "camera_base_rpy_deg": [float(v) for v in rpy], "camera_base_rpy_sigma_deg": [float(v) for v in sigma],
            "configured_camera_base": _camera_base(config).to_dict(),
            "residuals": [{"pose": i + 1, "normal_rad": r.normal_rad, "offset_m": r.offset_m,
                           "whitened": [float(w) for w in r.whitened], "chi2": r.chi2}
                          for i, r in enumerate(estimate.residuals)],
            "systematic": systematic_section(estimate),
            "arm_common_covariance": None if estimate.arm_common_covariance is None
            else estimate.arm_common_covariance.tolist()}


def systematic_section(estimate: FixedCameraEstimate) -> dict[str, Any]:
    """The camera's systematic allowance in the result: its terms, their 6x6 part of the camera pose's covariance
    and each pose parameter's share of its variance (1: all of it; 0 without terms)."""
    total = np.diag(estimate.covariance)
    sys_cov = estimate.systematic_covariance
    part = np.zeros(6) if sys_cov is None else np.diag(sys_cov)
    share = np.divide(part, total, out=np.zeros(6), where=total > 0)      # variance fractions, unitless
    return {"terms": list(estimate.systematic_terms), "covariance": None if sys_cov is None else sys_cov.tolist(),
            "variance_share": {k: float(v) for k, v in zip(FIXED_PARAMETERS[:6], share, strict=True)}}


def measuring_plane_section(table: dict[str, Any] | None, estimate: FixedCameraEstimate) -> dict[str, Any] | None:
    """The measuring plane the fixed camera saw, in the base frame through its estimated pose, with covariance.

    Its ``(tilt a, tilt b, offset)`` covariance (about the base plane's tangent basis) carries the frame's fit
    and the camera pose's; it is what ``plane_agreement`` compares with the other cameras' planes. None
    without a view; ``{"error": ...}`` when the camera found no plane there.
    """
    from cellcal.core.geometry.planes import tangent_basis
    from cellcal.core.geometry.relative import PoseWithCovariance, transform_plane

    if table is None or "error" in table:
        return table
    obs = observation_from_pose({"full_frame": table, "reported_flange_pose": Pose.identity().to_dict()})
    cov4 = obs.covariance   # the fit's total (noise and the allowance): one view
    basis = tangent_basis(obs.normal)
    jac = np.zeros((3, 4))
    jac[:2, :3], jac[2, 3] = basis.T, 1.0                   # (normal, offset) -> (tilt a, tilt b, offset)
    plane_cam = Plane(obs.normal, obs.offset_m)
    plane, cov = transform_plane(plane_cam, jac @ cov4 @ jac.T,
                                 PoseWithCovariance(estimate.camera_base, estimate.covariance))
    return {"plane_base": plane.to_dict(), "covariance": cov.tolist(),
            "covariance_parameters": ["tilt_a_rad", "tilt_b_rad", "offset_m"], "plane_cam": plane_cam.to_dict()}


def run_fixed_handeye(calibrator: FixedCalibrator, out_dir: str | Path, *, resume: bool = False) -> dict[str, Any]:
    """Measure the plate plan (journal beside the output), estimate, write ``DIR/handeye-NAME.json`` atomically.

    Raises:
        CellcalError, KeyboardInterrupt: As :meth:`Calibrator.run`, and the estimate's refusals (gates
            ``observability`` and ``noise_model``); the journal stays for ``--resume``.
    """
    out = Path(out_dir) / fixed_filename(calibrator.config.camera_name)
    journal = journal_path(out)
    with OutputLock.for_directory(out.parent):
        measured = calibrator.run(journal=journal, resume=resume)
        document = plate_document(calibrator, measured)
        write_json_atomic(out, document)
        remove_journal(journal)
    return document


def plate_document(calibrator: FixedCalibrator, measured: dict[str, Any], method: str = "plate") -> dict[str, Any]:
    """The result document of the plate plan ``calibrator`` measured (``measured``: :meth:`Calibrator.run`'s).

    Raises:
        CalibrationQualityError: The estimate's refusals (gates ``observability`` and ``noise_model``).
    """
    config = calibrator.config
    arm_model = calibrator.arm.arm_model()
    estimate = estimate_from_poses(config, measured, arm_model)
    header = {"cellcal_version": cellcal_version(), "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
              "config_source": config.source, "method": method,
              "commanded_flange_poses": [p.to_dict() for p in calibrator.poses],
              "reported_flange_poses": [p["reported_flange_pose"] for p in measured["poses"]],
              "arm_model": arm_model.to_dict(), "left_out": list(calibrator.left_out),
              **({"resumed_poses": measured["resumed_poses"]} if "resumed_poses" in measured else {})}
    document = fixed_document(config, estimate, header)
    document["measuring_plane"] = measuring_plane_section(calibrator.table, estimate)
    return document
