"""The measuring plane in the robot base frame, and its consistency across poses.

Each pose's camera-frame plane goes into the base frame through the arm's reported flange
pose and the mount (:func:`plane_in_base`); the table does not move, so the poses must
agree (:func:`plane_consistency`). What the spread reveals, and when the check is blind,
is in ADR 0002. Which errors the spread's test and the consensus's interval carry (the
camera's noise, its systematic error common to the poses and its differential part, the
arm's absolute accuracy) is in ADR 0055's section "Poses combined".
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cellcal.core.geometry.planes import Plane, plane_covariance
from cellcal.devices.arm_model import ArmModel
from cellcal.devices.errors import CalibrationError
from cellcal.devices.pose import Pose

FloatArray = NDArray[np.float64]

__all__ = [
    "ARM_VARYING",
    "PlaneConsistency",
    "PosePlane",
    "noise_plane_covariance",
    "noise_shifts",
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
#: The part of the arm's stated accuracy that varies from pose to pose (the rest is common to them): the
#: hand-eye fit's random and in-step parts together (``ArmAccuracy.varying`` 0.25 and ``.trend`` 0.5 add to
#: about 0.56 in quadrature; ADR 0055).
ARM_VARYING = 0.5
#: Two-sided normal quantile of the consensus's 95 % interval.
Z95 = 1.959963984540054


def noise_plane_covariance(fit: Any) -> FloatArray:
    """The 4x4 covariance of a full-frame fit's plane from its noise alone (ADR 0055, "Poses combined").

    A full-frame fit's ``normal_covariance`` is its total: noise plus the camera's systematic
    allowance as if it were independent per pose (ADR 0059). Checks that compare poses or frames
    of one camera take the noise part (``noise_normal_covariance``, ``noise_offset_sigma_m``,
    ``noise_normal_offset_covariance``); a result without them states noise only.
    """
    cov: FloatArray = plane_covariance(getattr(fit, "noise_normal_covariance", fit.normal_covariance),
                                       getattr(fit, "noise_offset_sigma_m", fit.offset_sigma_m),
                                       getattr(fit, "noise_normal_offset_covariance", fit.normal_offset_covariance))
    return cov


def noise_shifts(source: Any) -> dict[str, tuple[FloatArray, float]]:
    """A fit's (or its JSON form's) systematic shifts: ``{term: (normal delta (3,), offset delta m)}``, camera frame.

    Each is the camera-frame plane's 1-sigma shift by one term of the camera's systematic allowance
    (``"scale"``, ``"offset"``, ``"field:<shape>"``), a coefficient common to every pose of that camera.
    Accepts ``FullFrameResult.systematic_shifts`` (tuples) or its ``to_dict`` form
    (``{"normal": [...], "offset_m": x}``); none (an older result): ``{}``.
    """
    raw = source.get("systematic_shifts") if isinstance(source, Mapping) else getattr(source, "systematic_shifts", None)
    out: dict[str, tuple[FloatArray, float]] = {}
    for key, value in (raw or {}).items():
        if isinstance(value, Mapping):
            normal, offset = value["normal"], value["offset_m"]
        else:
            normal, offset = value
        out[str(key)] = (np.asarray(normal, dtype=np.float64).reshape(3), float(offset))
    return out


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
        normal_sigma_rad: 1-sigma RMS angular uncertainty of the normal from this pose's own
            noise (random from pose to pose), or None.
        offset_sigma_m: Same for the plane's offset/height, or None.
        shifts: The camera's systematic allowance per term (``"scale"``, ``"offset"``,
            ``"field:<shape>"``): the 1-sigma shift of this pose's plane, base frame, as
            (normal delta (3,), offset delta m); its coefficient is common to every pose.
        flange_m: The flange's position, base frame, m (the lever of the arm's orientation
            error), or None (no lever).
    """

    plane_base: Plane
    anchor_m: FloatArray
    camera_rotation: Any = None
    normal_sigma_rad: float | None = None
    offset_sigma_m: float | None = None
    shifts: Mapping[str, tuple[FloatArray, float]] = field(default_factory=dict)
    flange_m: FloatArray | None = None

    @classmethod
    def from_camera(cls, plane_cam: Plane, camera_in_base: Pose, *, normal_sigma_rad: float | None = None,
                    offset_sigma_m: float | None = None,
                    shifts_cam: Mapping[str, tuple[FloatArray, float]] | None = None,
                    flange_in_base: Pose | None = None) -> PosePlane:
        """From the plane in the camera frame and ``T_base_camera``.

        The anchor is where the optical axis meets the plane (the nearest plane point to
        the camera if the axis misses it). ``shifts_cam`` (camera frame, :func:`noise_shifts`)
        go to the base frame with the plane (``n_b = R n``, ``d_b = d - n_b . t``);
        ``flange_in_base`` gives the flange's position (default: the camera's).
        """
        try:
            t = plane_cam.distance_along_optical_axis_m()
            anchor_cam = np.array([0.0, 0.0, t])
        except CalibrationError:
            anchor_cam = plane_cam.point_m
        rot, trans = camera_in_base.rotation_matrix, np.asarray(camera_in_base.translation, dtype=np.float64)
        shifts: dict[str, tuple[FloatArray, float]] = {}
        for key, (dn, dd) in (shifts_cam or {}).items():
            dn_b = rot @ np.asarray(dn, dtype=np.float64)
            shifts[key] = (dn_b, float(dd) - float(dn_b @ trans))
        flange = trans if flange_in_base is None else np.asarray(flange_in_base.translation, dtype=np.float64)
        return cls(plane_cam.transformed(camera_in_base), camera_in_base.apply(anchor_cam),
                   Pose.from_rotation_matrix(camera_in_base.rotation_matrix), normal_sigma_rad, offset_sigma_m,
                   shifts, flange.copy())


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
        expected_parts: The expected RMS deviations by source, ``{"noise" | "systematic" |
            "arm": (normal rad, height m)}``: the poses' own noise, the differential part of
            the camera's systematic allowance (each term's shift at a pose minus its mean over
            the poses) and the part of the arm's accuracy that varies per pose. Together (in
            quadrature) they are ``expected_*_rms``.
        consensus_normal_sigma_rad: 1-sigma RMS angle of the consensus normal: the poses'
            noise combined, the systematic allowance's mean shift (common to the poses) and
            the arm's common accuracy (its tilt); None when the poses gave no uncertainty.
        consensus_height_sigma_m: Same for the consensus's height at ``reference_point_m``.
        consensus_parts: Those by source, ``{"noise" | "systematic" | "arm": (rad, m)}``.
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
    expected_parts: dict[str, tuple[float, float]] = field(default_factory=dict)
    consensus_normal_sigma_rad: float | None = None
    consensus_height_sigma_m: float | None = None
    consensus_parts: dict[str, tuple[float, float]] = field(default_factory=dict)

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
            "expected_parts": {k: {"normal_rms_deg": math.degrees(n), "height_rms_m": h}
                               for k, (n, h) in self.expected_parts.items()},
            "consensus_interval": None if self.consensus_height_sigma_m is None else {
                "confidence": 0.95,
                "normal_sigma_deg": deg(self.consensus_normal_sigma_rad),
                "height_sigma_m": self.consensus_height_sigma_m,
                "normal_halfwidth_deg": deg(Z95 * (self.consensus_normal_sigma_rad or 0.0)),
                "height_halfwidth_m": Z95 * self.consensus_height_sigma_m,
                "parts": {k: {"normal_sigma_deg": math.degrees(n), "height_sigma_m": h}
                          for k, (n, h) in self.consensus_parts.items()}},
        }


def _weights(variances: Sequence[float | None]) -> FloatArray:
    """Inverse-variance weights when every variance is known and positive, else equal weights."""
    if all(v is not None and v > 0 and math.isfinite(v) for v in variances):
        w = np.array([1.0 / float(v) for v in variances if v is not None])
    else:
        w = np.ones(len(variances))
    out: FloatArray = w / w.sum()
    return out


def _expected_var(var: FloatArray, weights: FloatArray) -> FloatArray:
    """Per pose, the variance of its deviation from a weighted mean from independent per-pose variances."""
    # var(x_i - sum_j w_j x_j) = s_i^2 (1 - 2 w_i) + sum_j w_j^2 s_j^2
    out: FloatArray = np.maximum(var * (1.0 - 2.0 * weights) + float(weights**2 @ var), 0.0)
    return out


def _orientation_span(rotations: Sequence[Any]) -> float | None:
    if any(r is None for r in rotations):
        return None
    return max((a.angle_to(b) for a, b in itertools.combinations(rotations, 2)), default=0.0)


def _arm_varying(poses: Sequence[PosePlane], normals: FloatArray, anchor: FloatArray, arm: ArmModel | None,
                 varying: float) -> tuple[FloatArray, FloatArray]:
    """Per pose, the variance the arm's varying part puts on its normal (rad^2, both tilts) and height (m^2).

    The flange's error is isotropic with RMS ``varying x accuracy`` (1-sigma per axis over sqrt 3, as the
    hand-eye fit reads it): a turn tilts the normal about its two axes across it and moves the plane at
    the anchor by the turn times the lever from the flange; a shift moves it along the normal.
    """
    n = len(poses)
    if arm is None or not (arm.accuracy_m or arm.accuracy_rad):
        return np.zeros(n), np.zeros(n)
    var_r, var_t = (varying * arm.accuracy_rad) ** 2 / 3.0, (varying * arm.accuracy_m) ** 2 / 3.0
    lever = np.array([0.0 if p.flange_m is None else float(np.linalg.norm(np.cross(anchor - p.flange_m, normals[i])))
                      for i, p in enumerate(poses)])
    return np.full(n, 2.0 * var_r), var_t + var_r * lever**2


def _systematic(poses: Sequence[PosePlane], flip: FloatArray, normals: FloatArray, n_bar: FloatArray,
                anchor: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Each systematic term's shift per pose: of the normal across ``n_bar`` (K, N, 3) and the height (K, N), m.

    A term a pose does not state (a field shape another pose took as its worst) shifts it by nothing.
    """
    keys = sorted({k for p in poses for k in p.shifts})
    dn = np.zeros((len(keys), len(poses), 3))
    dh = np.zeros((len(keys), len(poses)))
    for k, key in enumerate(keys):
        for i, p in enumerate(poses):
            if key not in p.shifts:
                continue
            d_normal, d_offset = p.shifts[key]
            d_normal = np.asarray(d_normal, dtype=np.float64) * flip[i]
            d_offset = float(d_offset) * flip[i]
            dn[k, i] = d_normal - float(d_normal @ n_bar) * n_bar
            # the height along n_bar at the anchor: s = -(n . a + d) / (n . n_bar), to first order
            dh[k, i] = -(float(d_normal @ anchor) + d_offset) / float(normals[i] @ n_bar)
    return dn, dh


def plane_consistency(poses: Sequence[PosePlane], *, normal_tolerance_rad: float = DEFAULT_NORMAL_TOLERANCE_RAD,
                      height_tolerance_m: float = DEFAULT_HEIGHT_TOLERANCE_M,
                      reference_point_m: ArrayLike | None = None, arm: ArmModel | None = None,
                      arm_varying: float = ARM_VARYING) -> PlaneConsistency:
    """Consensus plane and spread of the poses' base-frame planes.

    The spread is judged against what varies from pose to pose: each pose's noise, the
    differential part of the camera's systematic allowance (a term's shift at a pose minus
    its weighted mean: a common error moves every pose alike and is no spread) and the part
    of the arm's accuracy that varies per pose (``arm_varying``). The consensus's interval
    carries the noise combined over the poses, the allowance's mean shift per term (common
    to the poses: it does not average out) and the arm's common accuracy (ADR 0055).

    Args:
        poses: One :class:`PosePlane` per pose (at least one).
        normal_tolerance_rad: Normal spread (max deviation) accepted beyond
            ``NOISE_FACTOR`` x the noise level.
        height_tolerance_m: Height spread (peak-to-peak) accepted beyond the noise level.
        reference_point_m: Where to compare heights (base frame); default the mean of
            the poses' anchors (the centre of the measured area).
        arm: The arm's stated accuracy (None: the arm's error is not counted).
        arm_varying: The part of the arm's accuracy that varies from pose to pose.

    Returns:
        The figures and a verdict; ``"inconsistent"`` means the hand-eye transform or the
        arm's calibration is off (see ADR 0002).

    Raises:
        CalibrationError: No poses, or planes whose normals point to opposite sides.
    """
    if not poses:
        raise CalibrationError("plane consistency needs at least one pose")
    normals, offsets, flip = _aligned_planes(poses)
    anchor = (np.mean([p.anchor_m for p in poses], axis=0) if reference_point_m is None
              else np.asarray(reference_point_m, dtype=np.float64))
    if anchor.shape != (3,) or not np.all(np.isfinite(anchor)):
        raise CalibrationError(f"reference_point_m must be 3 finite numbers, got {anchor}")
    arm_n, arm_h = _arm_varying(poses, normals, anchor, arm, arm_varying)
    noise_known = all(s is not None and math.isfinite(s) for p in poses
                      for s in (p.normal_sigma_rad, p.offset_sigma_m))
    stated = noise_known or any(p.shifts for p in poses) or bool(np.any(arm_h > 0))
    noise_n = np.array([float(p.normal_sigma_rad or 0.0) ** 2 for p in poses])
    noise_h = np.array([float(p.offset_sigma_m or 0.0) ** 2 for p in poses])
    # weights: the parts independent from pose to pose (noise and the arm's varying part)
    unknown: list[float | None] = [None] * len(poses)
    w_n = _weights(list(noise_n + arm_n) if noise_known else unknown)
    w_h = _weights(list(noise_h + arm_h) if noise_known else unknown)
    # consensus normal: the weighted mean of the unit normals, renormalised
    n_bar = w_n @ normals
    n_bar /= np.linalg.norm(n_bar)
    # height of each pose's plane above the anchor along n_bar: n_i . (a + s n_bar) + d_i = 0
    s = -(normals @ anchor + offsets) / (normals @ n_bar)
    # the consensus plane passes through the weighted mean height; deviations are about it
    ref = anchor + float(w_h @ s) * n_bar
    consensus = Plane.from_point_normal(ref, n_bar)
    heights = s - float(w_h @ s)
    dev = np.arccos(np.clip(normals @ n_bar, -1.0, 1.0))  # angle of each normal to the consensus, rad
    # the systematic allowance: its mean shift is common (the consensus's), the rest differs per pose
    sys_n, sys_h = _systematic(poses, flip, normals, n_bar, anchor)
    mean_n = np.einsum("i,kij->kj", w_n, sys_n)  # (K, 3)
    mean_h = sys_h @ w_h  # (K,)
    diff_n = float(np.mean(np.sum((sys_n - mean_n[:, None, :]) ** 2, axis=(0, 2)))) if len(sys_n) else 0.0
    diff_h = float(np.mean(np.sum((sys_h - mean_h[:, None]) ** 2, axis=0))) if len(sys_h) else 0.0
    parts = {"noise": (float(np.mean(_expected_var(noise_n, w_n))), float(np.mean(_expected_var(noise_h, w_h)))),
             "systematic": (diff_n, diff_h),
             "arm": (float(np.mean(_expected_var(arm_n, w_n))), float(np.mean(_expected_var(arm_h, w_h))))}
    exp_n = math.sqrt(sum(v[0] for v in parts.values())) if stated else None
    exp_h = math.sqrt(sum(v[1] for v in parts.values())) if stated else None
    cons_n = cons_h = None
    cons_parts: dict[str, tuple[float, float]] = {}
    if stated:
        acc_m = 0.0 if arm is None else arm.accuracy_m
        acc_r = 0.0 if arm is None else arm.accuracy_rad
        cons_parts = {"noise": (math.sqrt(float(w_n**2 @ noise_n)), math.sqrt(float(w_h**2 @ noise_h))),
                      "systematic": (math.sqrt(float(np.sum(mean_n**2))), math.sqrt(float(np.sum(mean_h**2)))),
                      # the arm's error common to the poses, in the base frame (as the hand-eye fit's plane):
                      # its turn tilts the plane, its shift along the normal moves it; plus the varying part averaged
                      "arm": (math.sqrt(2.0 * acc_r**2 / 3.0 + float(w_n**2 @ arm_n)),
                              math.sqrt(acc_m**2 / 3.0 + float(w_h**2 @ arm_h)))}
        cons_n = math.sqrt(sum(v[0] ** 2 for v in cons_parts.values()))
        cons_h = math.sqrt(sum(v[1] ** 2 for v in cons_parts.values()))
    span = _orientation_span([p.camera_rotation for p in poses])
    # tolerances: the configured margin on top of NOISE_FACTOR x the expected noise spread
    n_tol = normal_tolerance_rad + NOISE_FACTOR * (exp_n or 0.0)
    h_tol = height_tolerance_m + 2.0 * NOISE_FACTOR * (exp_h or 0.0)  # peak-to-peak ~ 2x a deviation
    n_spread, h_spread = float(dev.max()), float(heights.max() - heights.min())
    verdict, text = _verdict(len(poses), n_spread, n_tol, h_spread, h_tol, span)
    return PlaneConsistency(consensus, ref, tuple(float(v) for v in dev), tuple(float(v) for v in heights),
                            n_spread, float(math.sqrt(np.mean(dev**2))), h_spread,
                            float(math.sqrt(np.mean(heights**2))), exp_n, exp_h, span, n_tol, h_tol,
                            verdict, text,
                            {k: (math.sqrt(n), math.sqrt(h)) for k, (n, h) in parts.items()} if stated else {},
                            cons_n, cons_h, cons_parts)


def _aligned_planes(poses: Sequence[PosePlane]) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The poses' unit normals (N, 3) and offsets (N,), every normal on the first one's side, and the signs (N,).

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
    return normals, offsets, np.where(flip, -1.0, 1.0)


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
