"""The plane constraints of eye-in-hand calibration: parameters, prediction, whitened residuals.

At pose ``i`` the arm reads back ``A_i = T_base_flange``; the camera sits at
``A_i @ X`` (``X = T_flange_camera``, the mount) and measures the fixed base-frame
plane ``n_B·p + c_B = 0`` in its own frame as ``n_C = R_C^T n_B``,
``c_C = c_B + n_B·t_C`` (normal toward the camera, ``c_C`` the camera's distance).
Nine parameters are small steps from the configured values (ADR 0018): the mount's
rotation about the flange axes (rad, applied on the left), its translation (m, flange
frame), the plane normal's tilts about two base-frame axes across it (rad) and its offset (m).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cellcal.core.geometry.planes import Plane, plane_covariance, tangent_basis
from cellcal.core.geometry.relative import perturb
from cellcal.devices.errors import CalibrationError
from cellcal.devices.pose import Pose

FloatArray = NDArray[np.float64]

#: The parameters, in the order of the parameter vector (names of ``[handeye] given``).
PARAMETERS: tuple[str, ...] = ("mount_rot_x", "mount_rot_y", "mount_rot_z", "mount_x", "mount_y", "mount_z",
                               "plane_tilt_a", "plane_tilt_b", "plane_offset")
#: Index ranges of the parameter blocks.
MOUNT_ROTATION = slice(0, 3)
MOUNT_TRANSLATION = slice(3, 6)
PLANE_TILT = slice(6, 8)
PLANE_OFFSET = 8


@dataclass(frozen=True)
class PlaneObservation:
    """The plane as the camera saw it at one pose.

    Attributes:
        flange: ``T_base_flange`` as the arm read it back.
        normal: Unit plane normal in the camera frame, toward the camera.
        offset_m: The plane's offset in the camera frame (the camera's distance), metres.
        covariance: 4x4 covariance of (normal x, y, z, offset), from the full-frame fit: its total,
            with the camera's systematic allowance when the fit carried one.
        noise_covariance: The part of it from the fit's noise alone (None: all of it), what weighs
            the pose: the allowance is an error common to every pose, not per-pose noise.
        systematic_shifts: Per term of the camera's systematic allowance (``scale``, ``offset``,
            ``field:<shape>``), its 1-sigma shift ``(normal_delta, offset_delta_m)`` of this plane in
            the camera frame: one coefficient common to every pose of the camera (ADR 0059, "Amended").
        budget_shifts: The plane's shift for depths 1 % long (``depth_scale_1pct``) and 1 mm long
            (``depth_offset_1mm``), from the fit's error budget (empty: the estimator's approximation,
            the offset 1 % and 1 mm longer).
    """

    flange: Pose
    normal: FloatArray
    offset_m: float
    covariance: FloatArray
    noise_covariance: FloatArray | None = None
    systematic_shifts: Mapping[str, tuple[FloatArray, float]] = field(default_factory=dict)
    budget_shifts: Mapping[str, tuple[FloatArray, float]] = field(default_factory=dict)

    @property
    def noise(self) -> FloatArray:
        """The covariance of the fit's noise alone (the total without a stated split)."""
        return self.covariance if self.noise_covariance is None else self.noise_covariance


@dataclass(frozen=True)
class PlaneModel:
    """Maps a 9-parameter vector to the mount and the base-frame plane, and predicts observations.

    Args:
        nominal_mount: The configured ``T_flange_camera`` (the zero of the parameters).
        nominal_plane: The configured plane in the base frame, normal toward the camera side.
    """

    nominal_mount: Pose
    nominal_plane: Plane

    def mount(self, p: FloatArray) -> Pose:
        """``T_flange_camera`` of the parameters ``p`` (9,)."""
        # a turn about the flange axes on the left and a shift in the flange frame (the relative poses' step)
        return perturb(self.nominal_mount, np.concatenate([p[MOUNT_ROTATION], p[MOUNT_TRANSLATION]]))

    def plane(self, p: FloatArray) -> Plane:
        """The base-frame plane of the parameters ``p`` (9,)."""
        from scipy.spatial.transform import Rotation

        axes = tangent_basis(self.nominal_plane.normal)
        turn = Rotation.from_rotvec(axes @ p[PLANE_TILT])  # tilt about the two axes across the normal
        return Plane(turn.apply(np.array(self.nominal_plane.normal)), self.nominal_plane.offset_m + p[PLANE_OFFSET])

    def predict(self, p: FloatArray, flanges: Sequence[Pose] | tuple[FloatArray, FloatArray]
                ) -> tuple[FloatArray, FloatArray]:
        """Predicted camera-frame normals (N, 3) and offsets (N,) at the flange poses.

        ``flanges`` may be given as their stacked rotation matrices (N, 3, 3) and translations (N, 3).
        """
        rot_a, t_a = flanges if isinstance(flanges, tuple) else stack_poses(flanges)
        mount, plane = self.mount(p), self.plane(p)
        r_x = mount.rotation.as_matrix()
        n_b = np.array(plane.normal)
        u = np.einsum("nji,j->ni", rot_a, n_b)  # u_i = R_A^T n_B, the normal in the flange frame
        normals = u @ r_x  # n_C = R_X^T u_i (row form)
        t_c = np.einsum("nij,j->ni", rot_a, mount.translation) + t_a  # camera origin in the base frame
        return normals, plane.offset_m + t_c @ n_b  # c_C = c_B + n_B . t_C


class PlaneResiduals:
    """Whitened plane residuals over the fitted parameters (the camera on the flange's and a fixed camera's fits).

    A subclass sets ``model`` (with ``predict(p, flanges) -> (normals, offsets)``), ``free`` (the fitted
    parameters' indices into the 9), ``flanges`` (:func:`stack_poses`), ``bases`` (V, 3, 2 tangent bases of the
    measured normals), ``normals`` (V, 3), ``offsets`` (V,) and ``whiten`` (V, 3, 3 inverse Cholesky factors).
    """

    model: Any
    free: list[int]
    flanges: tuple[FloatArray, FloatArray]
    bases: FloatArray
    normals: FloatArray
    offsets: FloatArray
    whiten: FloatArray

    def full(self, x: FloatArray) -> FloatArray:
        """The 9-vector with the fitted parameters ``x`` and the others at 0."""
        p = np.zeros(len(PARAMETERS))
        p[self.free] = x
        return p

    def raw(self, x: FloatArray) -> FloatArray:
        """Unwhitened residuals (V, 3): tangent components of the normal's error, the offset's error."""
        normals, offsets = self.model.predict(self.full(x), self.flanges)
        tangent = np.einsum("nij,ni->nj", self.bases, normals - self.normals)  # predicted - measured, across
        return np.column_stack([tangent, offsets - self.offsets])

    def __call__(self, x: FloatArray) -> FloatArray:
        """Whitened residuals, flattened (3V,)."""
        white: FloatArray = np.einsum("nij,nj->ni", self.whiten, self.raw(x)).ravel()
        return white


def stack_poses(poses: Sequence[Pose]) -> tuple[FloatArray, FloatArray]:
    """Rotation matrices (N, 3, 3) and translations (N, 3) of poses."""
    return (np.stack([p.rotation.as_matrix() for p in poses]), np.stack([np.asarray(p.translation) for p in poses]))


def arm_error_jacobian(obs: PlaneObservation, mount: Pose) -> FloatArray:
    """How an error of the flange pose moves a pose's residual: 3x6, (tangent components of the normal,
    offset) over (a turn of the flange about the base axes, rad; a shift of it, m).

    The camera turns with the flange: its normal turns by the same angle across the normal and its
    offset moves by the turn times the camera's lever ``R_A t_X`` across the normal; a shift moves the
    offset by its component along the normal. Taken at the measured normal and ``mount`` (the nominal).
    """
    basis = tangent_basis(obs.normal)
    r_c = (obs.flange @ mount).rotation_matrix
    n_b = r_c @ np.asarray(obs.normal, dtype=np.float64)  # the plane's normal in the base frame
    lever = obs.flange.rotation_matrix @ np.asarray(mount.translation, dtype=np.float64)  # camera from flange, base
    cross_n = np.array([[0.0, -n_b[2], n_b[1]], [n_b[2], 0.0, -n_b[0]], [-n_b[1], n_b[0], 0.0]])
    jac = np.zeros((3, 6))
    jac[:2, :3] = -basis.T @ r_c.T @ cross_n  # the measured normal turns by -(dtheta x n_B), seen in the camera
    jac[2, :3] = -np.cross(lever, n_b)  # the measured offset grows by n_B . (dtheta x lever)
    jac[2, 3:] = -n_b  # and by n_B . dp
    return jac


def arm_accuracy_covariance(obs: PlaneObservation, mount: Pose, accuracy_m: float, accuracy_rad: float
                            ) -> FloatArray:
    """The residual's covariance (3x3) from the arm's stated absolute accuracy at this pose.

    The flange's pose error is taken as a random error of each pose, isotropic, whose RMS length is
    the stated accuracy (``accuracy_m``, ``accuracy_rad``): 1-sigma per axis ``accuracy / sqrt(3)``
    (ADR 0055).
    """
    jac = arm_error_jacobian(obs, mount)
    var = np.concatenate([np.full(3, accuracy_rad**2 / 3.0), np.full(3, accuracy_m**2 / 3.0)])
    cov: FloatArray = (jac * var) @ jac.T
    return cov


def whitening(obs: PlaneObservation, arm_translation_sigma_m: float, arm_rotation_sigma_rad: float,
              lever_m: float, extra: FloatArray | None = None) -> tuple[FloatArray, FloatArray]:
    """The measured normal's tangent basis (3x2) and the inverse Cholesky factor (3x3) of its residual.

    The residual of a pose is (tangent components of the normal's error, offset error); its
    covariance is the full-frame fit's noise (:attr:`PlaneObservation.noise`: without the camera's
    systematic allowance, common to the poses and taken apart by the estimator), plus the arm's
    read-back noise: a translation error moves the offset by its component along the normal, a rotation error turns the
    normal and moves the offset by the rotation times the mount's lever ``lever_m``;
    plus ``extra`` (3x3, e.g. :func:`arm_accuracy_covariance`) when given.

    Raises:
        CalibrationError: If the covariance is not positive definite.
    """
    basis = tangent_basis(obs.normal)
    m = np.zeros((3, 4))
    m[:2, :3] = basis.T  # tangent components of the normal
    m[2, 3] = 1.0  # the offset
    cov = m @ obs.noise @ m.T
    cov[:2, :2] += np.eye(2) * arm_rotation_sigma_rad**2
    cov[2, 2] += arm_translation_sigma_m**2 + (arm_rotation_sigma_rad * lever_m) ** 2
    if extra is not None:
        cov = cov + extra
    try:
        chol = np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        raise CalibrationError("a pose's plane covariance is not positive definite") from None
    return basis, np.linalg.inv(chol)


def observation_from_pose(record: dict[str, object]) -> PlaneObservation:
    """The observation of one pose entry of a ``calibrate`` result document (its ``full_frame`` section).

    Raises:
        CalibrationError: If the pose has no full-frame result.
    """
    ff = record.get("full_frame")
    if not isinstance(ff, dict):
        raise CalibrationError(f"plan pose {int(record.get('index', -1)) + 1} has no full-frame plane")  # type: ignore[call-overload]
    plane = ff["plane_cam"]
    cov = plane_covariance(np.asarray(ff["normal_covariance"], dtype=np.float64), float(plane["offset_sigma_m"]),
                           # normal-offset correlation (zero when the document lacks it)
                           np.asarray(ff.get("normal_offset_covariance", np.zeros(3)), dtype=np.float64))
    noise = None
    if ff.get("noise_normal_covariance") is not None and ff.get("noise_offset_sigma_m") is not None:
        noise = plane_covariance(np.asarray(ff["noise_normal_covariance"], dtype=np.float64),
                                 float(ff["noise_offset_sigma_m"]),
                                 np.asarray(ff.get("noise_normal_offset_covariance", np.zeros(3)), dtype=np.float64))
    flange = Pose.from_dict(record["reported_flange_pose"])  # type: ignore[arg-type]
    return PlaneObservation(flange, np.asarray(plane["normal"], dtype=np.float64), float(plane["offset_m"]), cov,
                            noise, _shifts(ff.get("systematic_shifts"), "normal"), _budget_shifts(ff))


def _shifts(table: object, normal_key: str) -> dict[str, tuple[FloatArray, float]]:
    """``{term: (normal_delta, offset_delta_m)}`` of a document's shifts (``{}`` without them)."""
    if not isinstance(table, Mapping):
        return {}
    out = {}
    for key, entry in table.items():
        if isinstance(entry, Mapping) and entry.get(normal_key) is not None and entry.get("offset_m") is not None:
            out[str(key)] = (np.asarray(entry[normal_key], dtype=np.float64), float(entry["offset_m"]))
    return out


def _budget_shifts(ff: Mapping[str, Any]) -> dict[str, tuple[FloatArray, float]]:
    """The fit's error budget's 1 % depth scale and 1 mm depth offset as plane shifts (``{}`` without it)."""
    budget = ff.get("error_budget")
    if not isinstance(budget, Mapping):
        return {}
    return _shifts({k: budget.get(k) for k in ("depth_scale_1pct", "depth_offset_1mm")}, "normal_cam")


__all__ = ["MOUNT_ROTATION", "MOUNT_TRANSLATION", "PARAMETERS", "PLANE_OFFSET", "PLANE_TILT", "PlaneModel",
           "PlaneObservation", "PlaneResiduals", "arm_accuracy_covariance", "arm_error_jacobian",
           "observation_from_pose", "plane_covariance", "stack_poses", "tangent_basis", "whitening"]
