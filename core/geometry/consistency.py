"""The measuring plane in the robot base frame, and its consistency across poses.

Each pose's camera-frame plane goes into the base frame through the arm's reported flange
pose and the mount (:func:`plane_in_base`); the table does not move, so the poses must
agree (:func:`plane_consistency`). What the spread reveals, and when the check is blind,
is in ADR 0002.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cellcal.core.geometry.planes import Plane
from cellcal.devices.errors import CalibrationError
from cellcal.devices.pose import Pose

FloatArray = NDArray[np.float64]

__all__ = [
    "PlaneConsistency",
    "PosePlane",
    "plane_consistency",
    "plane_in_base",
]

#: Normal-angle spread (rad) tolerated on top of the noise level before the verdict is "inconsistent".
DEFAULT_NORMAL_TOLERANCE_RAD = math.radians(0.05)
#: Height spread (m) tolerated on top of the noise level.
DEFAULT_HEIGHT_TOLERANCE_M = 0.0005
#: Multiple of the expected (noise) spread that still counts as noise.
NOISE_FACTOR = 3.0
#: Below this span of camera orientations (rad) the check cannot see a mount error.
MIN_ORIENTATION_SPAN_RAD = math.radians(5.0)


def plane_in_base(plane_cam: Plane, flange_in_base: Pose, mount: Pose) -> Plane:
    """The plane measured in the camera frame, in the base frame.

    Args:
        plane_cam: Plane in the camera frame.
        flange_in_base: The arm's reported ``T_base_flange``.
        mount: The hand-eye transform ``T_flange_camera``.
    """
    return plane_cam.transformed(flange_in_base @ mount)


@dataclass(frozen=True, eq=False)
class PosePlane:
    """One pose's plane in the base frame, with where it was measured.

    Attributes:
        plane_base: The plane in the base frame (normal toward the camera).
        anchor_m: A point of the measured area on this plane, base frame, metres
            (where the optical axis meets it).
        camera_rotation: The camera's orientation in the base frame (for the span check):
            a :class:`~cellcal.devices.pose.Pose` (its translation unused), or None.
        normal_sigma_rad: 1-sigma RMS angular uncertainty of the normal, or None.
        offset_sigma_m: 1-sigma uncertainty of the plane's offset/height, or None.
    """

    plane_base: Plane
    anchor_m: FloatArray
    camera_rotation: Any = None
    normal_sigma_rad: float | None = None
    offset_sigma_m: float | None = None

    @classmethod
    def from_camera(cls, plane_cam: Plane, camera_in_base: Pose, *, normal_sigma_rad: float | None = None,
                    offset_sigma_m: float | None = None) -> PosePlane:
        """From the plane in the camera frame and ``T_base_camera``.

        The anchor is where the optical axis meets the plane (the nearest plane point to
        the camera if the axis misses it).
        """
        try:
            t = plane_cam.distance_along_optical_axis_m()
            anchor_cam = np.array([0.0, 0.0, t])
        except CalibrationError:
            anchor_cam = plane_cam.point_m
        return cls(plane_cam.transformed(camera_in_base), camera_in_base.apply(anchor_cam),
                   Pose.from_rotation_matrix(camera_in_base.rotation_matrix), normal_sigma_rad, offset_sigma_m)


@dataclass(frozen=True, eq=False)
class PlaneConsistency:
    """How well the poses agree on the plane in the base frame.

    Attributes:
        consensus: The consensus plane, base frame.
        reference_point_m: Point of the consensus plane where heights are compared, metres.
        normal_deviation_rad: Per pose, angle between its normal and the consensus normal.
        height_deviation_m: Per pose, its plane's height above the consensus plane along
            the consensus normal at ``reference_point_m`` (signed), metres.
        normal_spread_rad: Largest normal deviation, rad.
        normal_rms_rad: RMS normal deviation, rad.
        height_spread_m: Peak-to-peak of the height deviations, metres.
        height_rms_m: RMS height deviation, metres.
        expected_normal_rms_rad: RMS normal deviation expected from the poses' own
            uncertainty, or None when they gave none.
        expected_height_rms_m: Same for the height, or None.
        orientation_span_rad: Largest angle between two poses' camera orientations, or None.
        normal_tolerance_rad: The normal spread accepted as consistent.
        height_tolerance_m: The height spread accepted as consistent.
        verdict: ``"consistent"``, ``"inconsistent"``, ``"blind"`` (one orientation) or
            ``"single pose"``.
        interpretation: One sentence saying what the figures mean.
    """

    consensus: Plane
    reference_point_m: FloatArray
    normal_deviation_rad: tuple[float, ...]
    height_deviation_m: tuple[float, ...]
    normal_spread_rad: float
    normal_rms_rad: float
    height_spread_m: float
    height_rms_m: float
    expected_normal_rms_rad: float | None
    expected_height_rms_m: float | None
    orientation_span_rad: float | None
    normal_tolerance_rad: float
    height_tolerance_m: float
    verdict: str
    interpretation: str

    @property
    def n_poses(self) -> int:
        """Number of poses compared."""
        return len(self.normal_deviation_rad)

    @property
    def consistent(self) -> bool:
        """False only when the spread exceeds the tolerances."""
        return self.verdict != "inconsistent"

    def to_dict(self) -> dict[str, Any]:
        """JSON form (degrees for angles, metres)."""
        def deg(v: float | None) -> float | None:
            return None if v is None else math.degrees(v)

        return {
            "n_poses": self.n_poses,
            "consensus_plane_base": self.consensus.to_dict(),
            "reference_point_m": self.reference_point_m.tolist(),
            "normal_deviation_deg": [math.degrees(v) for v in self.normal_deviation_rad],
            "height_deviation_m": list(self.height_deviation_m),
            "normal_spread_deg": math.degrees(self.normal_spread_rad),
            "normal_rms_deg": math.degrees(self.normal_rms_rad),
            "height_spread_m": self.height_spread_m,
            "height_rms_m": self.height_rms_m,
            "expected_normal_rms_deg": deg(self.expected_normal_rms_rad),
            "expected_height_rms_m": self.expected_height_rms_m,
            "orientation_span_deg": deg(self.orientation_span_rad),
            "normal_tolerance_deg": math.degrees(self.normal_tolerance_rad),
            "height_tolerance_m": self.height_tolerance_m,
            "verdict": self.verdict,
            "interpretation": self.interpretation,
        }


def _weights(sigmas: Sequence[float | None]) -> FloatArray:
    """Inverse-variance weights when every sigma is known and positive, else equal weights."""
    if all(s is not None and s > 0 and math.isfinite(s) for s in sigmas):
        w = np.array([1.0 / float(s) ** 2 for s in sigmas if s is not None])
    else:
        w = np.ones(len(sigmas))
    out: FloatArray = w / w.sum()
    return out


def _expected_rms(sigmas: Sequence[float | None], weights: FloatArray) -> float | None:
    """RMS deviation from a weighted mean expected from independent per-pose 1-sigmas."""
    if not all(s is not None and math.isfinite(s) for s in sigmas):
        return None
    s2 = np.array([float(s) ** 2 for s in sigmas if s is not None])
    # var(x_i - sum_j w_j x_j) = s_i^2 (1 - 2 w_i) + sum_j w_j^2 s_j^2
    var = s2 * (1.0 - 2.0 * weights) + float(weights**2 @ s2)
    return math.sqrt(float(np.mean(np.maximum(var, 0.0))))


def _orientation_span(rotations: Sequence[Any]) -> float | None:
    if any(r is None for r in rotations):
        return None
    return max((a.angle_to(b) for a, b in itertools.combinations(rotations, 2)), default=0.0)


def plane_consistency(poses: Sequence[PosePlane], *, normal_tolerance_rad: float = DEFAULT_NORMAL_TOLERANCE_RAD,
                      height_tolerance_m: float = DEFAULT_HEIGHT_TOLERANCE_M,
                      reference_point_m: ArrayLike | None = None) -> PlaneConsistency:
    """Consensus plane and spread of the poses' base-frame planes.

    Args:
        poses: One :class:`PosePlane` per pose (at least one).
        normal_tolerance_rad: Normal spread (max deviation) accepted beyond
            ``NOISE_FACTOR`` x the noise level.
        height_tolerance_m: Height spread (peak-to-peak) accepted beyond the noise level.
        reference_point_m: Where to compare heights (base frame); default the mean of
            the poses' anchors (the centre of the measured area).

    Returns:
        The figures and a verdict; ``"inconsistent"`` means the hand-eye transform or the
        arm's calibration is off (see ADR 0002).

    Raises:
        CalibrationError: No poses, or planes whose normals point to opposite sides.
    """
    if not poses:
        raise CalibrationError("plane consistency needs at least one pose")
    normals, offsets = _aligned_planes(poses)
    w_n = _weights([p.normal_sigma_rad for p in poses])
    w_h = _weights([p.offset_sigma_m for p in poses])
    # consensus normal: the weighted mean of the unit normals, renormalised
    n_bar = w_n @ normals
    n_bar /= np.linalg.norm(n_bar)
    anchor = (np.mean([p.anchor_m for p in poses], axis=0) if reference_point_m is None
              else np.asarray(reference_point_m, dtype=np.float64))
    if anchor.shape != (3,) or not np.all(np.isfinite(anchor)):
        raise CalibrationError(f"reference_point_m must be 3 finite numbers, got {anchor}")
    # height of each pose's plane above the anchor along n_bar: n_i . (a + s n_bar) + d_i = 0
    s = -(normals @ anchor + offsets) / (normals @ n_bar)
    # the consensus plane passes through the weighted mean height; deviations are about it
    ref = anchor + float(w_h @ s) * n_bar
    consensus = Plane.from_point_normal(ref, n_bar)
    heights = s - float(w_h @ s)
    dev = np.arccos(np.clip(normals @ n_bar, -1.0, 1.0))  # angle of each normal to the consensus, rad
    exp_n = _expected_rms([p.normal_sigma_rad for p in poses], w_n)
    exp_h = _expected_rms([p.offset_sigma_m for p in poses], w_h)
    span = _orientation_span([p.camera_rotation for p in poses])
    # tolerances: the configured margin on top of NOISE_FACTOR x the expected noise spread
    n_tol = normal_tolerance_rad + NOISE_FACTOR * (exp_n or 0.0)
    h_tol = height_tolerance_m + 2.0 * NOISE_FACTOR * (exp_h or 0.0)  # peak-to-peak ~ 2x a deviation
    n_spread, h_spread = float(dev.max()), float(heights.max() - heights.min())
    verdict, text = _verdict(len(poses), n_spread, n_tol, h_spread, h_tol, span)
    return PlaneConsistency(consensus, ref, tuple(float(v) for v in dev), tuple(float(v) for v in heights),
                            n_spread, float(math.sqrt(np.mean(dev**2))), h_spread,
                            float(math.sqrt(np.mean(heights**2))), exp_n, exp_h, span, n_tol, h_tol,
                            verdict, text)


def _aligned_planes(poses: Sequence[PosePlane]) -> tuple[FloatArray, FloatArray]:
    """The poses' unit normals (N, 3) and offsets (N,), every normal on the first one's side.

    Raises:
        CalibrationError: Two planes more than 60 deg apart (not one plane).
    """
    normals = np.array([p.plane_base.normal for p in poses])
    offsets = np.array([p.plane_base.offset_m for p in poses])
    flip = normals @ normals[0] < 0  # (n, d) and (-n, -d) are the same plane
    normals[flip] *= -1.0
    offsets[flip] *= -1.0
    if np.any(normals @ normals[0] < math.cos(math.radians(60.0))):
        raise CalibrationError("the poses' planes differ by more than 60 deg; they are not one plane")
    return normals, offsets


def _verdict(n_poses: int, n_spread: float, n_tol: float, h_spread: float, h_tol: float,
             span: float | None) -> tuple[str, str]:
    """The verdict and its one-sentence interpretation (spreads and tolerances in rad and metres)."""
    figures = (f"normal spread {math.degrees(n_spread):.3f} deg (accepted {math.degrees(n_tol):.3f}), "
               f"height spread {h_spread * 1e3:.2f} mm (accepted {h_tol * 1e3:.2f})")
    if n_poses == 1:
        return "single pose", "one pose only: nothing to compare; plan several poses to check the mount"
    if n_spread > n_tol or h_spread > h_tol:
        return "inconsistent", (f"{figures}: the poses disagree on where the plane is, so the hand-eye transform "
                                "([mount]) or the arm's calibration is off")
    if span is not None and span < MIN_ORIENTATION_SPAN_RAD:
        return "blind", (f"{figures}, but every pose has the same camera orientation (span "
                         f"{math.degrees(span):.1f} deg), so a mount error would not show; vary the orientation")
    return "consistent", f"{figures}: hand-eye transform and arm agree with the camera"
