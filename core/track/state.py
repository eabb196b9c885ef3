"""What the tracker is told and what it reports: its settings, a frame's step, the state, a change.

:class:`TrackSettings` weigh the frames, test the stated noise and tune the change detector;
a :class:`TrackStep` says what one frame did; the :class:`TrackState` is the current mount and
base-frame plane with intervals for what the work has shown; a :class:`ChangeEvent` is a
detected change of the mount or the plane. The estimate itself is
:class:`~cellcal.core.track.estimator.Tracker` (ADR 0040). SI units (metres, radians,
seconds) unless a name says ``_deg``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cellcal.core.geometry.planes import Plane
from cellcal.core.handeye.estimator import ArmAccuracy
from cellcal.core.handeye.noise import NoiseCheck
from cellcal.devices.pose import Pose

FloatArray = NDArray[np.float64]

__all__ = ["ChangeEvent", "TrackSettings", "TrackState", "TrackStep"]


@dataclass(frozen=True)
class TrackSettings:
    """How the tracker weighs frames, tests its noise and detects changes.

    Attributes:
        arm_translation_sigma_m: 1-sigma of the arm's position read-back per axis, m (as ``[handeye]``).
        arm_rotation_sigma_rad: 1-sigma of its orientation read-back per axis, rad.
        confidence: Level of the intervals.
        prior_sigma: How far (rad and m alike: an isotropic prior, so it moves no direction the
            frames do not see) the mount and plane may be from the configured ones.
        detector_reference, detector_clip, detector_threshold: The CUSUM (:class:`.detector.Cusum`).
        noise_window: Frames of the chi2 test of the stated noise (normalised innovations).
        noise_test_level: Level of each tail of that test.
        max_interval_scale: Above this Birge ratio the intervals are withheld (the model is wrong).
        change_window: Frames after a change kept to tell mount from plane and restart from.
        min_change_frames: Frames after a change before "neither block alone" is concluded.
        accept_level, reject_level: A change hypothesis fits at p >= accept_level, is ruled out below reject_level.
        normals_kept: Flange-frame plane normals kept for naming the unseen directions.
        iterations: Gauss-Newton iterations per frame and per batch step (relinearisations).
        window: Latest accepted frames kept and relinearised about the estimate in each batch step;
            older ones are held as a quadratic prior linearised when they left.
        relinearise_every: Accepted frames between batch steps.
        arm_accuracy: The arm's stated absolute accuracy: its part common to the frames is added to the
            reported intervals as the hand-eye fit adds it (None: not counted; never in the weights, ADR 0055).
    """

    arm_translation_sigma_m: float = 2.5e-5
    arm_rotation_sigma_rad: float = 0.0
    confidence: float = 0.95
    prior_sigma: float = 0.05
    detector_reference: float = 8.0
    detector_clip: float = 40.0
    detector_threshold: float = 120.0
    noise_window: int = 900
    noise_test_level: float = 0.01
    max_interval_scale: float = 10.0
    change_window: int = 900
    min_change_frames: int = 10
    accept_level: float = 1e-3
    reject_level: float = 1e-6
    normals_kept: int = 256
    iterations: int = 2
    window: int = 900
    relinearise_every: int = 30
    arm_accuracy: ArmAccuracy | None = None


@dataclass(frozen=True)
class ChangeEvent:
    """A detected change of the mount or the plane.

    Attributes:
        detected_at_s: Time of the frame that raised the alarm, s.
        kind: ``"mount"``, ``"plane"`` or ``"mount or plane"`` (not told apart yet, or both).
        size: How large: ``rotation_deg``, ``translation_m`` (mount), ``plane_tilt_deg``,
            ``plane_offset_m``, ``plane_shift_m`` (along the normal, toward the camera) (plane), once
            the frames after it have been fitted; at detection
            ``innovation_chi2``.
        resolved_at_s: When the restarted estimate saw again every parameter it saw before (None: not yet).
        started_at_s: Time of the first frame after the estimated change point, s.
    """

    detected_at_s: float
    kind: str
    size: dict[str, float] = field(default_factory=dict)
    resolved_at_s: float | None = None
    started_at_s: float | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON form."""
        return {"detected_at_s": self.detected_at_s, "kind": self.kind, "size": dict(self.size),
                "resolved_at_s": self.resolved_at_s, "started_at_s": self.started_at_s}


@dataclass(frozen=True)
class TrackStep:
    """What one frame did.

    Attributes:
        t_s: Frame time, s.
        residual: The frame's innovation whitened by its predicted covariance (3,) (normal across, offset).
        chi2: Its squared norm (3 dof when the model holds).
        accepted: Whether the frame updated the estimate.
        event: A change event detected, classified or resolved at this frame (else None).
        note: Why the frame was not accepted ("" when it was).
    """

    t_s: float
    residual: FloatArray
    chi2: float
    accepted: bool
    event: ChangeEvent | None = None
    note: str = ""


@dataclass(frozen=True)
class TrackState:
    """The current estimate, what the work has shown and the changes seen.

    Attributes:
        mount: ``T_flange_camera``; plane: the plane in the base frame (normal toward the camera).
        mount_translation_sigma_m: (3,) 1-sigma, flange frame, m (NaN where not observable).
        mount_rpy_sigma_deg: (3,) 1-sigma of ``rpy_deg`` as in ``[mount]`` (NaN where not observable).
        plane_tilt_sigma_deg: (2,) 1-sigma of the plane's tilts about its two axes across the normal (NaN: unseen).
        plane_offset_sigma_m: 1-sigma of its offset, m (NaN: unseen).
        observable: Per parameter of ``PARAMETERS``, whether the work has shown it.
        unseen: What the work has not shown yet, in words (with what would show it).
        frames_used: Frames that updated the estimate.
        events: Changes detected.
        change_unresolved: Whether a change is not resolved (detected and not re-estimated yet).
        interval_z: Half-width of the 95 % (``confidence``) intervals in sigmas.
        interval_scale: Factor the residuals put on the stated noise's sigmas (already in the sigmas).
        noise: The chi2 test of the stated noise over the window (None before any frame).
        parameters: The nine parameter steps from the configured values (unseen ones 0).
        covariance: 9x9 covariance of ``parameters`` as the intervals use it (NaN rows/columns unseen).
        confidence: Level of the intervals.
        intervals_withheld: Why no intervals are given ("" when they are).
        interval_notes: What the intervals carry besides the noise (the camera's systematic allowance and the
            arm's accuracy, common to the frames: ADR 0055), in words.
    """

    mount: Pose
    plane: Plane
    mount_translation_sigma_m: FloatArray
    mount_rpy_sigma_deg: FloatArray
    plane_tilt_sigma_deg: FloatArray
    plane_offset_sigma_m: float
    observable: dict[str, bool]
    unseen: list[str]
    frames_used: int
    events: list[ChangeEvent]
    change_unresolved: bool
    interval_z: float
    interval_scale: float
    noise: NoiseCheck | None
    parameters: FloatArray
    covariance: FloatArray
    confidence: float
    intervals_withheld: str = ""
    interval_notes: tuple[str, ...] = ()

    @property
    def mount_rpy_deg(self) -> FloatArray:
        """The mount's ``rpy_deg`` as in ``[mount]``."""
        rpy: FloatArray = np.degrees(self.mount.as_xyz_rpy()[3:])
        return rpy
