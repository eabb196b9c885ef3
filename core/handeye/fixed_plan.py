"""The geometry of a fixed camera's plan: its parameters, what a view predicts, what the poses can see.

A camera fixed in the cell (issue #40, ``on = "base"``) is found from a flat plate the arm shows it
(:mod:`.fixed`, whose parameters and equations are stated there). :class:`FixedModel` predicts
the views and :func:`whiten_view` with the covariances of the arm's error and the measuring plane
weighs them. The camera's pose is seen through the plate's normals: a turn of the camera about the
plate normal, and a shift of it parallel to the plate, change nothing the camera measures. So the
plate must be shown tilted about two axes (normals out of one plane of directions) and, when its
plane in the flange is estimated too, at several flange orientations. :func:`analyse_fixed`
names what a plan leaves unseen, from the whitened Jacobian at the configured values (structural,
before any fit); :func:`plate_poses` builds flange poses that see every parameter.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cellcal.core.geometry.planes import Plane, tangent_basis
from cellcal.core.geometry.relative import cross_matrix
from cellcal.core.handeye.model import (
    MOUNT_ROTATION,
    MOUNT_TRANSLATION,
    PLANE_OFFSET,
    PLANE_TILT,
    PlaneModel,
    PlaneObservation,
)
from cellcal.core.handeye.observability import ACROSS_COS, BLOCK_SHARE, PARALLEL_COS, UNOBSERVABLE_SIGMA, axis_text
from cellcal.devices.errors import CalibrationError
from cellcal.devices.pose import Pose

FloatArray = NDArray[np.float64]

#: The parameters of a fixed camera's fit, in the order of the parameter vector: the camera's turn about the
#: base x, y, z axes (rad; roll/pitch/yaw-like), its translation along them (m), the plate's tilts about the
#: two axes across its configured normal in the flange frame (rad) and its offset (m).
FIXED_PARAMETERS: tuple[str, ...] = ("rot_x", "rot_y", "rot_z", "tx", "ty", "tz",
                                     "plate_tilt_a", "plate_tilt_b", "plate_offset")
# the flange camera's mount and plane blocks (PlaneModel's steps), with the base and the flange as parents
CAMERA_ROTATION = MOUNT_ROTATION
CAMERA_TRANSLATION = MOUNT_TRANSLATION
PLATE_TILT = PLANE_TILT
PLATE_OFFSET = PLANE_OFFSET
#: Plane views below which no plan can fix a camera pose (each view gives 3 numbers, with 2 normals only 5 dof).
MIN_VIEWS = 3

FIX_SECOND_AXIS = "tilt the plate about a second axis"
FIX_TOWARD = "tilt the plate toward that axis (normals out of one plane of directions) or let the camera see " \
             "the measuring plane"
FIX_FLANGE = "show the plate at more flange orientations (roll it about its normal), or give the plate " \
             "(estimate_plate=False)"
FIX_VIEWS = "show the plate at 3 or more orientations, tilted about two axes (plate_poses)"


@dataclass(frozen=True)
class FixedObservability:
    """Rank, condition and the unseen directions of a fixed camera's plan.

    Attributes:
        rank: Directions the data determine.
        n_parameters: Parameters estimated (6, or 9 with the plate).
        n_views: Plane views (plate poses, plus the measuring plane when seen).
        condition: Largest over smallest singular value of the whitened Jacobian (inf if singular).
        singular_values: Of the whitened Jacobian, descending (per rad / per m).
        unseen: Each direction the data cannot determine as ``(what, fix)`` in words.
    """

    rank: int
    n_parameters: int
    n_views: int
    condition: float
    singular_values: tuple[float, ...]
    unseen: tuple[tuple[str, str], ...]

    @property
    def observable(self) -> bool:
        """Whether every estimated parameter is determined."""
        return self.rank == self.n_parameters

    def message(self) -> str:
        """One line: what cannot be seen and what would fix it."""
        if self.observable:
            return f"all {self.n_parameters} parameters observable (condition {self.condition:.3g})"
        few = (f"{self.n_views} plane view(s) cannot fix {self.n_parameters} parameters ({FIX_VIEWS}); "
               if self.n_views < MIN_VIEWS else "")
        return (few + f"cannot see {self.n_parameters - self.rank} of {self.n_parameters} parameters: "
                + "; ".join(f"{what}: {fix}" for what, fix in self.unseen))

    def to_dict(self) -> dict[str, Any]:
        """JSON form."""
        return {"rank": self.rank, "n_parameters": self.n_parameters, "n_views": self.n_views,
                "observable": self.observable,
                "condition": self.condition if math.isfinite(self.condition) else None,
                "singular_values": list(self.singular_values),
                "unobservable": [{"what": what, "fix": fix} for what, fix in self.unseen]}


@dataclass(frozen=True)
class MeasuringPlaneView:
    """The measuring plane as the fixed camera saw it, and where it is in the base frame.

    Attributes:
        normal: Unit plane normal in the camera frame, toward the camera.
        offset_m: The plane's offset in the camera frame (the camera's distance), m.
        covariance: 4x4 covariance of (normal x, y, z, offset) of the camera's fit.
        plane_base: The measuring plane in the base frame (the arm camera's calibration or ``[reference]``).
        plane_covariance: 3x3 covariance of ``plane_base`` as (tilt about the first, tilt about the second
            axis of :func:`~cellcal.core.geometry.planes.tangent_basis` of its normal, rad; offset, m):
            the hand-eye estimate's ``plane_tilt_a``, ``plane_tilt_b``, ``plane_offset`` block.
    """

    normal: FloatArray
    offset_m: float
    covariance: FloatArray
    plane_base: Plane
    plane_covariance: FloatArray


@dataclass(frozen=True)
class FixedModel:
    """Maps the 9 parameter steps to the camera's pose and the plate, and predicts the views."""

    nominal_camera: Pose
    nominal_plate: Plane
    measuring: Plane | None  # the measuring plane in the base frame, normal toward the camera

    def camera(self, p: FloatArray) -> Pose:
        """``T_base_camera`` of the parameters ``p`` (9,): turned about the base axes, shifted in the base frame.

        The steps are the flange camera's mount's (:meth:`PlaneModel.mount`), with the base as the parent.
        """
        return PlaneModel(self.nominal_camera, self.nominal_plate).mount(p)

    def plate(self, p: FloatArray) -> Plane:
        """The plate's plane in the flange frame of the parameters ``p`` (9,), as :meth:`PlaneModel.plane` steps."""
        return PlaneModel(self.nominal_camera, self.nominal_plate).plane(p)

    def predict(self, p: FloatArray, flanges: tuple[FloatArray, FloatArray]) -> tuple[FloatArray, FloatArray]:
        """Camera-frame normals (V, 3) and offsets (V,): the plate at each flange, then the measuring plane."""
        camera, plate = self.camera(p), self.plate(p)
        r_x, t_x = camera.rotation_matrix, camera.translation
        rot_f, t_f = flanges
        n_b = np.einsum("nij,j->ni", rot_f, plate.normal)  # the plate normal in the base frame
        normals = n_b @ r_x  # n_C = R_X^T n_B (row form)
        offsets = plate.offset_m - np.einsum("ni,ni->n", n_b, t_f - t_x)  # c_C = c_f - n_B . (t_F - t_X)
        if self.measuring is not None:
            m = self.measuring
            normals = np.vstack([normals, m.normal @ r_x])
            offsets = np.append(offsets, m.offset_m + float(m.normal @ t_x))  # c_C = c_B + n_B . t_X
        return normals, offsets


def whiten_view(normal: FloatArray, covariance: FloatArray, extra: FloatArray) -> FloatArray:
    """Inverse Cholesky factor (3x3) of a view's residual: its covariance across the normal, plus ``extra``.

    Raises:
        CalibrationError: If the covariance is not positive definite.
    """
    m = np.zeros((3, 4))
    m[:2, :3] = tangent_basis(normal).T  # tangent components of the normal
    m[2, 3] = 1.0  # the offset
    try:
        chol = np.linalg.cholesky(m @ covariance @ m.T + extra)
    except np.linalg.LinAlgError:
        raise CalibrationError("a view's plane covariance is not positive definite") from None
    out: FloatArray = np.linalg.inv(chol)
    return out


def arm_plate_covariance(obs: PlaneObservation, camera: Pose, position_m: float, rotation_rad: float) -> FloatArray:
    """The residual's covariance (3x3) from a random flange error (RMS ``position_m``, ``rotation_rad``) at a pose.

    The plate turns with the flange about the flange's origin: its normal by the same angle, its
    offset seen from the camera by the turn times the lever from the camera to the flange, across
    the normal; a shift moves the offset by its component along the normal. Isotropic: 1-sigma per
    axis the RMS over sqrt(3); taken at the measured normal and the configured camera.
    """
    r_x = camera.rotation_matrix
    n_b = r_x @ obs.normal  # the plate normal in the base frame
    lever = obs.flange.translation - camera.translation  # camera to flange, base frame
    jac = np.zeros((3, 6))
    jac[:2, :3] = -tangent_basis(obs.normal).T @ r_x.T @ cross_matrix(n_b)  # the normal turns by dtheta x n_B
    jac[2, :3] = -np.cross(n_b, lever)  # the offset by -(dtheta x n_B) . lever
    jac[2, 3:] = -n_b  # and by -n_B . dp
    var = np.concatenate([np.full(3, rotation_rad**2 / 3.0), np.full(3, position_m**2 / 3.0)])
    cov: FloatArray = (jac * var) @ jac.T
    return cov


def measuring_covariance(view: MeasuringPlaneView, plane: Plane, camera: Pose) -> FloatArray:
    """The residual's covariance (3x3) from the measuring plane's base-frame uncertainty (at the configured camera).

    ``plane`` is ``view.plane_base`` with its normal toward the camera (the same or its opposite).
    """
    r_x = camera.rotation_matrix
    axes = tangent_basis(view.plane_base.normal)  # the axes of its covariance's tilts
    sign = 1.0 if float(plane.normal @ view.plane_base.normal) > 0 else -1.0
    jac = np.zeros((3, 3))
    jac[:2, :2] = -tangent_basis(view.normal).T @ r_x.T @ cross_matrix(plane.normal) @ axes  # n_B turns by tilt x n_B
    jac[2, :2] = axes.T @ np.cross(plane.normal, camera.translation)  # c_C moves by (tilt x n_B) . t_X
    jac[2, 2] = sign  # and with the plane's offset
    cov: FloatArray = jac @ view.plane_covariance @ jac.T
    return cov


def _dirs(block: FloatArray) -> FloatArray:
    """Orthonormal directions (columns) of a parameter block that take part in the null space (rows: block)."""
    if block.shape[1] == 0:
        return np.zeros((block.shape[0], 0))
    u, s, _ = np.linalg.svd(block, full_matrices=False)
    return u[:, s > BLOCK_SHARE]


def _line(axis: FloatArray) -> FloatArray:
    """A line's direction with its largest component positive (an SVD's sign depends on the BLAS)."""
    k = int(np.argmax(np.abs(axis)))
    out: FloatArray = -axis if axis[k] < 0 else axis
    return out


def _rotation_text(dirs: FloatArray, normals: FloatArray, traded: bool) -> tuple[str, str]:
    """Name an unseen subspace (columns) of the camera's turn; ``normals``: the plate's in the base frame."""
    with_plate = " (traded with the plate's tilt)" if traded else ""
    if dirs.shape[1] == 1:
        a = _line(dirs[:, 0])
        normal = bool(np.all(np.abs(normals @ a) > PARALLEL_COS))  # the plate normal at every pose
        what = f"camera rotation about {axis_text(a, 'base')}" + (" (the plate normal)" if normal else "")
        return what + with_plate, FIX_SECOND_AXIS if normal or not traded else FIX_FLANGE
    if dirs.shape[1] == 2:
        b = _line(np.cross(dirs[:, 0], dirs[:, 1]))
        return f"camera rotation about axes across {axis_text(b, 'base')}{with_plate}", FIX_FLANGE
    return f"camera rotation about any axis{with_plate}", FIX_VIEWS


def _translation_text(dirs: FloatArray, offset_axis: FloatArray | None, normals: FloatArray
                      ) -> list[tuple[str, str]]:
    """Name an unseen subspace (columns) of the camera's translation; ``offset_axis`` trades with the plate's offset."""
    out = []
    if offset_axis is not None:
        out.append((f"camera translation along {axis_text(_line(offset_axis), 'base')} vs the plate's offset",
                    FIX_FLANGE))
        dirs = dirs - np.outer(offset_axis, offset_axis @ dirs)  # what is left across it
        dirs = _dirs(dirs)
    if dirs.shape[1] == 0:
        return out
    flat = bool(np.max(np.abs(normals @ dirs)) < ACROSS_COS)  # every pose sees them edge-on
    along = " (parallel to the plate at every pose)" if flat else ""
    if dirs.shape[1] == 1:
        what = f"camera translation along {axis_text(_line(dirs[:, 0]), 'base')}{along}"
    elif dirs.shape[1] == 2:
        what = f"camera translation across {axis_text(_line(np.cross(dirs[:, 0], dirs[:, 1])), 'base')}{along}"
    else:
        what = "camera translation in every direction"
    out.append((what, FIX_TOWARD if dirs.shape[1] == 1 else FIX_SECOND_AXIS))
    return out


def analyse_fixed(jacobian: FloatArray, free: Sequence[int], normals_base: FloatArray, n_views: int
                  ) -> FixedObservability:
    """Rank, condition and named unseen directions of a fixed camera's whitened Jacobian.

    Args:
        jacobian: Whitened residuals by free parameters (per rad / per m), shape (3 n_views, len(free)).
        free: Indices into :data:`FIXED_PARAMETERS` of its columns.
        normals_base: The plate normal in the base frame at every pose (N, 3).
        n_views: Plane views (plate poses plus the measuring plane when seen).
    """
    _, s, vt = np.linalg.svd(jacobian, full_matrices=True)
    s_full = np.zeros(len(free))
    s_full[:len(s)] = s  # fewer residuals than parameters: the missing singular values are 0
    # a direction whose 1-sigma exceeds 0.1 rad or m is unseen (or 1e-10 of the best seen: rounding)
    threshold = max(1.0 / UNOBSERVABLE_SIGMA, (s_full[0] if len(s_full) else 0.0) * 1e-10)
    seen = s_full >= threshold
    null = np.zeros((len(FIXED_PARAMETERS), int((~seen).sum())))
    null[list(free)] = vt[~seen].T  # the unseen directions in the full parameter space
    unseen: list[tuple[str, str]] = []
    rot = _dirs(null[CAMERA_ROTATION])
    if rot.shape[1]:
        unseen.append(_rotation_text(rot, normals_base, bool(np.abs(null[PLATE_TILT]).max() > BLOCK_SHARE)))
    trans = _dirs(null[CAMERA_TRANSLATION])
    if trans.shape[1]:
        with_offset = null[CAMERA_TRANSLATION] @ null[PLATE_OFFSET]  # the shift that moves with the plate's offset
        norm = float(np.linalg.norm(with_offset))
        unseen += _translation_text(trans, with_offset / norm if norm > BLOCK_SHARE else None, normals_base)
    if not unseen and null.shape[1]:  # only the plate itself is undetermined
        unseen.append(("the plate's tilt or offset in the flange frame", FIX_FLANGE))
    condition = float(s_full[0] / s_full[-1]) if len(s_full) and s_full[-1] > 0 else math.inf
    return FixedObservability(int(seen.sum()), len(free), n_views, condition, tuple(float(v) for v in s_full),
                              tuple(unseen))


def _facing_frame(normal: FloatArray, reference: FloatArray, roll_rad: float) -> FloatArray:
    """A right-handed frame (columns: two axes across ``normal``, then ``normal``) rolled about the normal.

    The first axis is ``reference`` made perpendicular to the normal, turned by ``roll_rad`` about it.
    """
    a = reference - (reference @ normal) * normal
    a /= np.linalg.norm(a)
    b = np.cross(normal, a)
    first = math.cos(roll_rad) * a + math.sin(roll_rad) * b  # rolled about the normal
    return np.column_stack([first, np.cross(normal, first), normal])


def plate_poses(camera_base: Pose, *, distance_m: float, plate_flange: Plane,
                tilts_deg: Sequence[float] = (0.0, 20.0, 30.0),
                azimuths_deg: Sequence[float] = (0.0, 45.0, 90.0, 135.0, 180.0, 225.0, 270.0, 315.0),
                rolls_deg: Sequence[float] = (0.0, 90.0, -90.0, 180.0),
                plate_centre_flange_m: Sequence[float] | None = None) -> list[Pose]:
    """Flange poses that show the plate to a fixed camera, every tilt at every azimuth.

    Each pose puts the plate's centre on the camera's optical axis at ``distance_m`` and turns
    the plate's face toward the camera, tilted by the tilt about an axis across the optical axis
    at the azimuth (measured in the camera's x-y plane from its x axis; a zero tilt is shown
    once); the flange is rolled about the plate normal by ``rolls_deg`` in turn, pose by pose.
    The face shown is the one ``plate_flange``'s normal points out of (the measured face's outward
    normal, in the flange frame). Two azimuths 90 deg apart and a nonzero tilt see the camera's pose;
    the rolls separate the plate's plane in the flange from it. Pure geometry: no reach check.

    Args:
        camera_base: ``T_base_camera`` (OpenCV camera frame: z along the optical axis).
        distance_m: Distance of the plate's centre from the camera along the optical axis, m.
        plate_flange: The plate's plane in the flange frame.
        tilts_deg: Angles between the plate normal and the optical axis, deg, each in [0, 80).
        azimuths_deg: Directions of the tilt axis in the camera's x-y plane, deg.
        rolls_deg: Rolls of the flange about the plate normal, deg, used in turn.
        plate_centre_flange_m: The plate's centre in the flange frame, m, on the plate (default: the
            plate's point closest to the flange origin).

    Raises:
        CalibrationError: A distance <= 0, a tilt outside [0, 80), no azimuth or roll, or a centre
            more than 1 mm off the plate.
    """
    from scipy.spatial.transform import Rotation

    if not math.isfinite(distance_m) or distance_m <= 0:
        raise CalibrationError(f"distance_m must be finite and > 0, got {distance_m}")
    if not tilts_deg or not all(0.0 <= t < 80.0 for t in tilts_deg) or not azimuths_deg or not rolls_deg:
        raise CalibrationError(f"plate_poses needs tilts in [0, 80) deg, azimuths and rolls, got {list(tilts_deg)}, "
                               f"{list(azimuths_deg)}, {list(rolls_deg)}")
    plate = plate_flange  # its normal is the face's outward normal: the face shown to the camera
    centre = plate.point_m if plate_centre_flange_m is None else np.asarray(plate_centre_flange_m, dtype=np.float64)
    if abs(float(plate.signed_distance(centre))) > 1e-3:
        raise CalibrationError(f"plate_centre_flange_m is {1000 * abs(float(plate.signed_distance(centre))):.3g} mm "
                               "off the plate's plane")
    r_c = camera_base.rotation_matrix
    target = camera_base.translation + distance_m * r_c[:, 2]  # on the optical axis, base frame
    flange_frame = np.column_stack([tangent_basis(plate.normal), plate.normal])  # right-handed, normal last
    faces = [(tilt, az) for tilt in tilts_deg for az in (azimuths_deg if tilt > 0 else azimuths_deg[:1])]
    out = []
    for k, (tilt, azimuth) in enumerate(faces):
        axis = math.cos(math.radians(azimuth)) * r_c[:, 0] + math.sin(math.radians(azimuth)) * r_c[:, 1]
        normal = Rotation.from_rotvec(math.radians(tilt) * axis).apply(-r_c[:, 2])  # toward the camera, tilted
        base_frame = _facing_frame(normal, r_c[:, 0], math.radians(rolls_deg[k % len(rolls_deg)]))
        rot = base_frame @ flange_frame.T  # takes the plate's flange frame onto the facing frame
        out.append(Pose.from_rotation_matrix(rot, target - rot @ centre))  # the centre lands on the target
    return out


__all__ = ["CAMERA_ROTATION", "CAMERA_TRANSLATION", "FIXED_PARAMETERS", "MIN_VIEWS", "PLATE_OFFSET", "PLATE_TILT",
           "FixedModel", "FixedObservability", "MeasuringPlaneView", "analyse_fixed", "arm_plate_covariance",
           "measuring_covariance", "plate_poses", "whiten_view"]
