"""Does the camera's view follow the arm? Names a camera that is not on the arm that moves (ADR 0045).

Between two samples (the arm's flange pose and the plane the camera measured in its own
frame) a camera on the arm moves by ``T = (A_i X)^-1 (A_j X)`` (``A`` the flange poses,
``X`` the configured mount), so the plane ``(n_i, c_i)`` it saw must become
``(R_T^T n_i, c_i + n_i . t_T)``: the normal turns with the flange (by
``2 asin(sin(theta/2) sin(phi))``, ``theta`` the flange's turn, ``phi`` the angle of its axis
to the normal in the flange frame) and the offset changes by the camera's travel along the
normal. A camera that does not move with the arm sees ``(n_i, c_i)`` again.

The mount is known only roughly (it may be what ``cellcal handeye`` is about to find), so
the change that decides is the least one any mount within :data:`MOUNT_TOLERANCE_RAD` and
:data:`MOUNT_TOLERANCE_M` of the configured one predicts: a turn about (nearly) the plane
normal or a travel along the plane predicts none, whatever the mount. Changes are measured in
sigmas of the difference of the two measured planes (their fit covariances plus the arm's
read-back noise). A pair decides once that least change is :data:`MIN_PREDICTED_SIGMAS`; its
view is static when the measured change is at most :data:`MAX_STATIC_FRACTION` of it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from cellcal.core.geometry.planes import tangent_basis
from cellcal.devices.errors import CalibrationQualityError
from cellcal.devices.pose import Pose

FloatArray = NDArray[np.float64]

__all__ = ["GATE", "MAX_STATIC_FRACTION", "MIN_PREDICTED_SIGMAS", "ViewChange", "ViewFollowsArm", "ViewSample",
           "not_on_arm_error", "view_change"]

#: Name of the quality gate in the error.
GATE = "view_follows_arm"
#: A pair of samples decides only when the least predicted change is this many sigmas of the measurement noise.
MIN_PREDICTED_SIGMAS = 100.0
#: How far the true mount's rotation (rad) and translation (m) may be from the configured ones: a mount set by
#: hand or from a drawing is within a few degrees and centimetres (the hand-eye sim's is 1 deg and 6 mm off).
MOUNT_TOLERANCE_RAD = math.radians(10.0)
MOUNT_TOLERANCE_M = 0.05
#: The view is static when its measured change (in sigmas) is at most this fraction of the least predicted one.
#: At the smallest deciding change that is 10 sigmas: a static camera's noise (chi with 3 degrees of freedom)
#: stays below it with probability 1 - 1e-20, while a camera on the arm sees at least the whole least change.
MAX_STATIC_FRACTION = 0.1
#: Samples kept to compare later ones with (the first ones; a decision needs one pair).
KEEP = 8


@dataclass(frozen=True)
class ViewSample:
    """The plane one camera frame showed, and where the arm was.

    Attributes:
        label: How messages name it, e.g. ``"1"`` (a plan pose) or ``"12 (t=1.2 s)"`` (a frame).
        flange: ``T_base_flange`` as the arm read it back (m, base frame).
        normal: Unit plane normal in the camera frame, toward the camera.
        offset_m: The plane's offset in the camera frame (the camera's distance), m.
        covariance: 4x4 covariance of (normal x, y, z, offset) from the fit (rad^2, m^2).
    """

    label: str
    flange: Pose
    normal: FloatArray
    offset_m: float
    covariance: FloatArray = field(repr=False)


@dataclass(frozen=True)
class ViewChange:
    """How much the plane changed between two samples, and how much an arm-mounted camera predicts.

    Attributes:
        first, second: The samples' labels.
        arm_travel_m: Distance between the two flange positions, m.
        arm_turn_rad: Angle between the two flange orientations, rad.
        predicted_turn_rad, predicted_shift_m: The plane's turn (rad) and offset change (m) a camera on
            the arm would see, with the configured mount.
        least_turn_rad, least_shift_m: The least turn (rad) and |offset change| (m) any mount within the
            tolerances predicts.
        measured_turn_rad, measured_shift_m: What the camera saw.
        predicted_sigmas, least_sigmas, measured_sigmas: The predicted, least and measured changes in
            sigmas of the noise: ``hypot(turn / sigma_turn, shift / sigma_shift)``.
    """

    first: str
    second: str
    arm_travel_m: float
    arm_turn_rad: float
    predicted_turn_rad: float
    predicted_shift_m: float
    least_turn_rad: float
    least_shift_m: float
    measured_turn_rad: float
    measured_shift_m: float
    predicted_sigmas: float
    least_sigmas: float
    measured_sigmas: float

    @property
    def decisive(self) -> bool:
        """Whether the arm moved enough for this pair to tell a static view from a following one."""
        return self.least_sigmas >= MIN_PREDICTED_SIGMAS

    @property
    def fraction(self) -> float:
        """The measured change over the least predicted one, both in sigmas (at least about 1 on the arm)."""
        return self.measured_sigmas / self.least_sigmas if self.least_sigmas > 0 else math.inf

    @property
    def static(self) -> bool:
        """Whether this pair decides that the view did not follow the arm."""
        return self.decisive and self.fraction <= MAX_STATIC_FRACTION


def _angle(a: FloatArray, b: FloatArray) -> float:
    """Angle between two vectors, rad (exact for small angles too)."""
    return float(math.atan2(np.linalg.norm(np.cross(a, b)), float(a @ b)))


def _sigmas(a: ViewSample, b: ViewSample, basis: FloatArray, arm_translation_sigma_m: float,
            arm_rotation_sigma_rad: float, lever_m: float) -> tuple[float, float]:
    """1-sigma of the difference of the two planes: the normal's turn (rad, its worst direction) and the offset (m).

    Each sample adds its fit's covariance and the arm's read-back noise (a flange turn turns the
    normal and, through the mount's lever, moves the offset). The normal-offset correlation is left
    out: the turn and the shift are judged as lengths, so a change cannot hide in it.
    """
    cov = np.asarray(a.covariance, dtype=np.float64) + np.asarray(b.covariance, dtype=np.float64)
    turn_var = float(np.linalg.eigvalsh(basis.T @ cov[:3, :3] @ basis)[-1]) + 2.0 * arm_rotation_sigma_rad**2
    shift_var = float(cov[3, 3]) + 2.0 * (arm_translation_sigma_m**2 + (arm_rotation_sigma_rad * lever_m) ** 2)
    return math.sqrt(max(turn_var, 0.0)) + 1e-15, math.sqrt(max(shift_var, 0.0)) + 1e-15  # finite for noise-free fits


def _least_change(a: ViewSample, b: ViewSample, mount: Pose, n_a: FloatArray) -> tuple[float, float]:
    """The least turn (rad) and |offset change| (m) of the plane any mount within the tolerances predicts."""
    rotvec = a.flange.rotvec_to(b.flange)  # the flange's turn, in flange a's frame
    theta = float(np.linalg.norm(rotvec))
    u = mount.rotation_matrix @ n_a  # the normal in the flange frame
    phi = math.acos(min(1.0, abs(float(u @ rotvec)) / theta)) if theta > 0 else 0.0  # angle to the axis line
    half = math.sin(0.5 * theta)
    turn = 2.0 * math.asin(min(1.0, half * math.sin(max(0.0, phi - MOUNT_TOLERANCE_RAD))))
    chord = 2.0 * half * math.sin(min(0.5 * math.pi, phi + MOUNT_TOLERANCE_RAD))  # the normal's largest step
    travel = b.flange.translation - a.flange.translation
    along = abs(float(a.flange.rotation_matrix @ u @ travel))  # the flange's travel along the normal
    lever = float(np.linalg.norm(mount.translation)) + MOUNT_TOLERANCE_M
    shift = along - 2.0 * math.sin(0.5 * MOUNT_TOLERANCE_RAD) * float(np.linalg.norm(travel)) - chord * lever
    return turn, max(0.0, shift)


def view_change(a: ViewSample, b: ViewSample, mount: Pose, *, arm_translation_sigma_m: float = 0.0,
                arm_rotation_sigma_rad: float = 0.0) -> ViewChange:
    """The plane's change from sample ``a`` to ``b``, measured and as a camera on the arm would see it.

    Args:
        a, b: The two samples.
        mount: The configured ``T_flange_camera`` (m).
        arm_translation_sigma_m: 1-sigma of the arm's position read-back per axis, m.
        arm_rotation_sigma_rad: 1-sigma of its orientation read-back per axis, rad.
    """
    n_a = np.asarray(a.normal, dtype=np.float64)
    n_a = n_a / np.linalg.norm(n_a)
    n_b = np.asarray(b.normal, dtype=np.float64)
    n_b = n_b / np.linalg.norm(n_b)
    motion = (a.flange @ mount).inv() @ (b.flange @ mount)  # camera b in camera a's frame
    n_pred = motion.rotation_matrix.T @ n_a
    shift_pred = float(n_a @ motion.translation)
    sigma_turn, sigma_shift = _sigmas(a, b, tangent_basis(n_a), arm_translation_sigma_m, arm_rotation_sigma_rad,
                                      float(np.linalg.norm(mount.translation)))
    turn_pred = _angle(n_a, n_pred)
    least_turn, least_shift = _least_change(a, b, mount, n_a)
    turn_seen, shift_seen = _angle(n_a, n_b), float(b.offset_m - a.offset_m)

    def sigmas(turn: float, shift: float) -> float:
        return math.hypot(turn / sigma_turn, shift / sigma_shift)

    return ViewChange(a.label, b.label, a.flange.distance_to(b.flange), a.flange.angle_to(b.flange),
                      turn_pred, shift_pred, least_turn, least_shift, turn_seen, shift_seen,
                      sigmas(turn_pred, shift_pred), sigmas(least_turn, least_shift), sigmas(turn_seen, shift_seen))


def not_on_arm_error(change: ViewChange, what: str = "poses") -> CalibrationQualityError:
    """The error naming a camera whose view did not follow the arm (gate :data:`GATE`).

    Args:
        change: The deciding pair.
        what: How the samples are called in the message (``"poses"``, ``"frames"``).
    """
    c = change
    return CalibrationQualityError(
        GATE, float(f"{c.fraction:.3g}"), MAX_STATIC_FRACTION,
        f"the camera's view did not change while the arm moved {c.arm_travel_m:.3f} m and turned "
        f"{math.degrees(c.arm_turn_rad):.1f} deg between {what} {c.first} and {c.second} (plane moved "
        f"{c.measured_shift_m * 1e3:.2f} mm, turned {math.degrees(c.measured_turn_rad):.3f} deg; on the arm: "
        f"{c.predicted_shift_m * 1e3:.1f} mm, {math.degrees(c.predicted_turn_rad):.2f} deg): the camera is not on "
        "the arm that moves (check the rig, [camera]/[arm], or that the emulator's scene follows the arm)")


class ViewFollowsArm:
    """Feeds samples in order and stops at the first pair that decides (a run's check).

    Each new sample is compared with the first :data:`KEEP` samples. When some pairs are
    decisive: if none of them shows the view following the arm, :meth:`add` raises; else the
    check is done (:attr:`decided`) and later samples are not looked at.

    Args:
        mount: The configured ``T_flange_camera``.
        arm_translation_sigma_m, arm_rotation_sigma_rad: The arm's read-back noise (m, rad per axis).
        what: How the samples are called in the message (``"poses"``, ``"frames"``).
    """

    def __init__(self, mount: Pose, *, arm_translation_sigma_m: float = 0.0, arm_rotation_sigma_rad: float = 0.0,
                 what: str = "poses") -> None:
        self.mount = mount
        self.arm_translation_sigma_m = arm_translation_sigma_m
        self.arm_rotation_sigma_rad = arm_rotation_sigma_rad
        self.what = what
        self.kept: list[ViewSample] = []
        #: The decisive pair that showed the view following the arm (None: not decided yet).
        self.decided: ViewChange | None = None

    def add(self, sample: ViewSample) -> ViewChange | None:
        """Compare ``sample`` with the kept ones; the deciding pair once the view is seen to follow the arm.

        Raises:
            CalibrationQualityError: Gate :data:`GATE`, when every decisive pair shows a static view.
        """
        if self.decided is not None:
            return self.decided
        changes = [view_change(k, sample, self.mount, arm_translation_sigma_m=self.arm_translation_sigma_m,
                               arm_rotation_sigma_rad=self.arm_rotation_sigma_rad) for k in self.kept]
        decisive = [c for c in changes if c.decisive]
        if decisive:
            following = [c for c in decisive if not c.static]
            if not following:
                raise not_on_arm_error(max(decisive, key=lambda c: c.least_sigmas), self.what)
            self.decided = max(following, key=lambda c: c.least_sigmas)
            self.kept.clear()
            return self.decided
        if len(self.kept) < KEEP:
            self.kept.append(sample)
        return None
