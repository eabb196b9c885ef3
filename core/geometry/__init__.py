"""Geometry of the measuring plane: plane fits, frame chains, sampling, consistency, PlaneMap, relative poses."""

from cellcal.core.geometry.consistency import (
    PlaneConsistency,
    PosePlane,
    plane_consistency,
    plane_in_base,
)
from cellcal.core.geometry.frames import (
    FrameChain,
)
from cellcal.core.geometry.planemap import (
    PlaneMap,
)
from cellcal.core.geometry.planes import (
    CameraPlaneAngles,
    Plane,
    PlaneFit,
    fit_plane_ols,
    fit_plane_tls,
    validate_points,
)
from cellcal.core.geometry.relative import (
    PlaneAgreement,
    PlaneDifference,
    PoseWithCovariance,
    plane_agreement,
    relative_pose,
    transform_plane,
)
from cellcal.core.geometry.robust_fit import (
    fit_plane_robust,
)
from cellcal.core.geometry.sampling import (
    Sample,
    sample_points,
    sample_window,
)

__all__ = [
    "CameraPlaneAngles",
    "FrameChain",
    "Plane",
    "PlaneAgreement",
    "PlaneConsistency",
    "PlaneDifference",
    "PlaneFit",
    "PlaneMap",
    "PosePlane",
    "PoseWithCovariance",
    "Sample",
    "fit_plane_ols",
    "fit_plane_robust",
    "fit_plane_tls",
    "plane_agreement",
    "plane_consistency",
    "plane_in_base",
    "relative_pose",
    "sample_points",
    "sample_window",
    "transform_plane",
    "validate_points",
]
