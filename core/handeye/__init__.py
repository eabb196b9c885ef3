"""Hand-eye estimation: the camera mount from the measuring plane, with a ChArUco cross-check (ADR 0018)."""

from cellcal.core.handeye.estimator import HandEyeEstimate, PoseResidual, estimate_mount, observability
from cellcal.core.handeye.fixed import FixedCameraEstimate, ViewResidual, estimate_fixed_camera
from cellcal.core.handeye.fixed_plan import FIXED_PARAMETERS, FixedObservability, MeasuringPlaneView, plate_poses
from cellcal.core.handeye.model import PARAMETERS, PlaneModel, PlaneObservation, observation_from_pose
from cellcal.core.handeye.observability import Observability, UnseenDirection, analyse
from cellcal.core.handeye.plan import arm_reach, auto_plan, check_plan, plan_poses, view_pose
from cellcal.core.handeye.result import (
    HANDEYE_FILENAME,
    HANDEYE_SCHEMA,
    format_report,
    handeye_document,
    mount_difference,
    mount_section,
    mount_table,
    plane_sections,
)
from cellcal.core.handeye.run import (
    check_observability,
    estimate_from_document,
    plan_calibrator,
    predicted_observations,
    run_handeye,
)

__all__ = [
    "FIXED_PARAMETERS",
    "HANDEYE_FILENAME",
    "HANDEYE_SCHEMA",
    "PARAMETERS",
    "FixedCameraEstimate",
    "FixedObservability",
    "HandEyeEstimate",
    "MeasuringPlaneView",
    "Observability",
    "PlaneModel",
    "PlaneObservation",
    "PoseResidual",
    "UnseenDirection",
    "ViewResidual",
    "analyse",
    "arm_reach",
    "auto_plan",
    "check_observability",
    "check_plan",
    "estimate_fixed_camera",
    "estimate_from_document",
    "estimate_mount",
    "format_report",
    "handeye_document",
    "mount_difference",
    "mount_section",
    "mount_table",
    "observability",
    "observation_from_pose",
    "plan_calibrator",
    "plan_poses",
    "plane_sections",
    "plate_poses",
    "predicted_observations",
    "run_handeye",
    "view_pose",
]
