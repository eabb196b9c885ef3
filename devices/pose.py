"""Rigid transforms (poses) in SI units; rotations are :mod:`scipy.spatial.transform` objects.

A :class:`Pose` ``T_a_b`` maps coordinates expressed in frame *b* into frame *a*:
``p_a = T_a_b.apply(p_b)``. Composition follows matrix order, so
``T_a_c = T_a_b @ T_b_c``. Translations are metres; :attr:`Pose.rotation` is a
:class:`scipy.spatial.transform.Rotation` (no hand-rolled quaternion or Euler code
anywhere in cellcal).

The pose keeps its rotation as a 3x3 matrix and builds the scipy object on first use:
composing, inverting and applying poses, and rotation vectors (``cv2.Rodrigues``), need
neither scipy nor its 0.3 s import, which stays off ``cellcal calibrate``'s start-up
(ADR 0021).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import CalibrationError

if TYPE_CHECKING:
    from scipy.spatial.transform import Rotation

FloatArray = NDArray[np.float64]

__all__ = ["Pose"]

_COS_30_DEG = math.sqrt(3.0) / 2.0


def _as_vector3(value: ArrayLike, what: str) -> FloatArray:
    try:
        arr = np.array(value, dtype=np.float64)  # always a fresh copy
    except (TypeError, ValueError) as exc:
        raise CalibrationError(f"{what} must be 3 numbers, got {value!r}") from exc
    if arr.shape != (3,):
        raise CalibrationError(f"{what} must have shape (3,), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise CalibrationError(f"{what} must be finite, got {arr.tolist()}")
    return arr


def _frozen(arr: FloatArray) -> FloatArray:
    arr.setflags(write=False)
    return arr


def _rotvec_matrix(rotvec: FloatArray) -> FloatArray:
    """The rotation matrix of a rotation vector (axis * angle, rad), by Rodrigues' formula (OpenCV)."""
    m, _ = cv2.Rodrigues(rotvec.reshape(3, 1))
    return np.asarray(m, dtype=np.float64)


def _matrix_rotvec(matrix: FloatArray) -> FloatArray:
    """The rotation vector (rad) of a rotation matrix, exact to about 1e-15 rad at every angle.

    The angle is ``atan2`` of the skew part's length (its sine) and the trace (its
    cosine). The axis comes from the skew part below 30 deg, and above from the symmetric
    part ``(1 - cos) n n^T`` as its leading eigenvector (numpy), signed by the skew part.
    (``cv2.Rodrigues`` finds the angle from its cosine alone: zero below 1e-5 rad, and
    within 1e-5 rad of a half turn up to 2e-5 rad off with the axis' sign lost.)
    """
    skew = matrix - matrix.T                                      # 2 sin(angle) [axis]x
    w = 0.5 * np.array([skew[2, 1], skew[0, 2], skew[1, 0]])      # sin(angle) * axis
    sin_angle = float(np.linalg.norm(w))
    cos_angle = 0.5 * (float(np.trace(matrix)) - 1.0)
    angle = math.atan2(sin_angle, cos_angle)
    if cos_angle > _COS_30_DEG:                                   # a small turn: the axis from the skew part
        return w if sin_angle == 0.0 else w * (angle / sin_angle)
    sym = 0.5 * (matrix + matrix.T) - cos_angle * np.eye(3)       # (1 - cos) axis axis^T, eigenvalues (1 - cos, 0, 0)
    axis = np.linalg.eigh(sym)[1][:, -1]                          # the eigenvector of the largest eigenvalue
    if float(np.dot(axis, w)) < 0.0:                              # its sign: that of sin(angle) * axis
        axis = -axis
    return axis * angle


def _scipy_rotation() -> Any:
    from scipy.spatial.transform import Rotation  # 0.3 s to import: only where a scipy object is wanted

    return Rotation


class Pose:
    """A rigid transform: rotation then translation (metres). Immutable.

    Args:
        rotation: A single :class:`scipy.spatial.transform.Rotation` (default: identity).
        translation: Translation, shape (3,), metres (default: zero).

    Attributes:
        translation: Translation part, shape (3,), metres (read-only array).
    """

    __slots__ = ("_matrix", "_rotation", "translation")
    translation: FloatArray
    _matrix: FloatArray
    _rotation: Rotation | None

    def __init__(self, rotation: Rotation | None = None, translation: ArrayLike | None = None) -> None:
        if rotation is None:
            matrix = np.eye(3)
        elif getattr(rotation, "single", False) is True and hasattr(rotation, "as_matrix"):
            matrix = np.array(rotation.as_matrix(), dtype=np.float64)
        else:
            raise CalibrationError("Pose.rotation must be a single scipy Rotation")
        t = np.zeros(3) if translation is None else _as_vector3(translation, "Pose.translation")
        self._set(matrix, t, rotation)

    def _set(self, matrix: FloatArray, translation: FloatArray, rotation: Rotation | None) -> None:
        object.__setattr__(self, "_matrix", _frozen(matrix))
        object.__setattr__(self, "translation", _frozen(translation))
        object.__setattr__(self, "_rotation", rotation)

    @classmethod
    def _of(cls, matrix: FloatArray, translation: FloatArray) -> Pose:
        """A pose from a rotation matrix known to be proper and a translation known to be finite."""
        pose = cls.__new__(cls)
        pose._set(matrix, translation, None)
        return pose

    def __setattr__(self, name: str, value: Any) -> None:
        raise AttributeError(f"Pose is immutable: cannot set {name!r}")

    def __delattr__(self, name: str) -> None:
        raise AttributeError(f"Pose is immutable: cannot delete {name!r}")

    def __reduce__(self) -> tuple[Any, ...]:
        return (Pose._of, (np.array(self._matrix), np.array(self.translation)))

    @property
    def rotation(self) -> Rotation:
        """The rotation part as a :class:`scipy.spatial.transform.Rotation` (built on first use)."""
        if self._rotation is None:
            object.__setattr__(self, "_rotation", _scipy_rotation().from_matrix(self._matrix))
        return self._rotation  # type: ignore[return-value]

    @property
    def rotation_matrix(self) -> FloatArray:
        """The rotation part as a 3x3 matrix (read-only)."""
        return self._matrix

    # ------------------------------------------------------------------ constructors
    @classmethod
    def identity(cls) -> Pose:
        """The identity transform."""
        return cls._of(np.eye(3), np.zeros(3))

    @classmethod
    def from_matrix(cls, matrix: ArrayLike) -> Pose:
        """Build from a 4x4 homogeneous matrix (translation in metres).

        Raises:
            CalibrationError: If the matrix is not 4x4, not finite, or its last row is not
                ``[0, 0, 0, 1]``, or its 3x3 block is not a proper rotation.
        """
        m = np.asarray(matrix, dtype=np.float64)
        if m.shape != (4, 4):
            raise CalibrationError(f"a homogeneous transform must be 4x4, got shape {m.shape}")
        if not np.all(np.isfinite(m)):
            raise CalibrationError("a homogeneous transform must be finite")
        if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
            raise CalibrationError(f"last row of a homogeneous transform must be 0 0 0 1, got {m[3]}")
        r = m[:3, :3]
        error = float(np.abs(r @ r.T - np.eye(3)).max())
        if not error <= 1e-6 or np.linalg.det(r) <= 0:
            raise CalibrationError("3x3 block of the transform is not a proper rotation")
        if error > 1e-12:  # kept bit for bit when it is a rotation to float precision
            u, _, vt = np.linalg.svd(r)
            r = u @ vt  # else the nearest rotation matrix
        return cls._of(r.copy(), m[:3, 3].copy())

    @classmethod
    def from_rotation_matrix(cls, rotation: ArrayLike, translation_m: ArrayLike | None = None) -> Pose:
        """Build from a 3x3 rotation matrix and a translation (m; default zero).

        Raises:
            CalibrationError: If the matrix is not a finite proper rotation (to 1e-6).
        """
        m = np.eye(4)
        try:
            m[:3, :3] = np.asarray(rotation, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise CalibrationError(f"a rotation matrix must be 3x3 numbers, got {rotation!r}") from exc
        m[:3, 3] = np.zeros(3) if translation_m is None else _as_vector3(translation_m, "Pose.translation")
        return cls.from_matrix(m)

    @classmethod
    def from_xyz_rotvec(cls, xyz_m: ArrayLike, rotvec_rad: ArrayLike) -> Pose:
        """Build from a translation (m) and a rotation vector (axis * angle, rad)."""
        rotvec = _as_vector3(rotvec_rad, "rotation vector")
        return cls._of(_rotvec_matrix(rotvec), _as_vector3(xyz_m, "Pose.translation"))

    @classmethod
    def from_xyz_rpy(cls, xyz_m: ArrayLike, rpy_rad: ArrayLike) -> Pose:
        """Build from a translation (m) and fixed-axis roll, pitch, yaw (rad).

        The rotation is ``Rz(yaw) @ Ry(pitch) @ Rx(roll)`` (extrinsic x-y-z), the
        convention of REP 103 and of most robot controllers.
        """
        roll, pitch, yaw = _as_vector3(rpy_rad, "roll/pitch/yaw")
        # each factor is the rotation about one base axis; the product applies roll first
        matrix = (_rotvec_matrix(np.array([0.0, 0.0, yaw])) @ _rotvec_matrix(np.array([0.0, pitch, 0.0]))
                  @ _rotvec_matrix(np.array([roll, 0.0, 0.0])))
        return cls._of(matrix, _as_vector3(xyz_m, "Pose.translation"))

    # ------------------------------------------------------------------ algebra
    def __matmul__(self, other: Pose) -> Pose:
        if not isinstance(other, Pose):
            return NotImplemented
        return Pose._of(self._matrix @ other._matrix, self._matrix @ other.translation + self.translation)

    def inv(self) -> Pose:
        """The inverse transform."""
        r_inv = self._matrix.T.copy()  # a rotation's inverse is its transpose
        return Pose._of(r_inv, -(r_inv @ self.translation))

    def apply(self, points: ArrayLike) -> FloatArray:
        """Transform points (shape (3,) or (N, 3), metres) from the source to the target frame."""
        p = np.asarray(points, dtype=np.float64)
        if p.shape[-1:] != (3,) or p.ndim > 2:
            raise CalibrationError(f"points must have shape (3,) or (N, 3), got {p.shape}")
        out: FloatArray = p @ self._matrix.T + self.translation
        return out

    def apply_vector(self, vectors: ArrayLike) -> FloatArray:
        """Rotate direction vectors (no translation)."""
        out: FloatArray = np.asarray(vectors, dtype=np.float64) @ self._matrix.T
        return out

    def with_translation(self, translation_m: ArrayLike) -> Pose:
        """This pose's rotation with another translation (metres)."""
        return Pose._of(self._matrix, _as_vector3(translation_m, "Pose.translation"))

    def rotvec_to(self, other: Pose) -> FloatArray:
        """Rotation vector (rad) of the turn from this orientation to ``other``'s, in this pose's frame."""
        return _matrix_rotvec(self._matrix.T @ other._matrix)

    def interpolate(self, other: Pose, fraction: float) -> Pose:
        """The pose ``fraction`` (0..1) of the way to ``other``: straight-line translation and a
        constant-rate turn about one axis (spherical linear interpolation)."""
        s = float(fraction)
        turn = _rotvec_matrix(s * self.rotvec_to(other))  # the fraction s of the relative turn
        return Pose._of(self._matrix @ turn, self.translation + s * (other.translation - self.translation))

    # ------------------------------------------------------------------ views
    def as_matrix(self) -> FloatArray:
        """The 4x4 homogeneous matrix (translation in metres)."""
        m = np.eye(4)
        m[:3, :3] = self._matrix
        m[:3, 3] = self.translation
        return m

    def as_xyz_rotvec(self) -> FloatArray:
        """``[x, y, z, rx, ry, rz]``: metres and rotation vector (rad)."""
        return np.concatenate([self.translation, Pose.identity().rotvec_to(self)])

    def as_xyz_rpy(self) -> FloatArray:
        """``[x, y, z, roll, pitch, yaw]``: metres and fixed-axis x-y-z angles (rad).

        At pitch +-90 deg (gimbal lock) roll and yaw are not unique: scipy's split (yaw 0), without its warning.
        """
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            rpy = self.rotation.as_euler("xyz")
        return np.concatenate([self.translation, rpy])

    def as_quat_xyzw(self) -> FloatArray:
        """The rotation's unit quaternion ``[x, y, z, w]`` with ``w >= 0``.

        Written out from its definition, ``(n sin(a/2), cos(a/2))`` for the rotation
        vector ``a n``, so that a result document needs no scipy (ADR 0021).
        """
        rotvec = self.as_xyz_rotvec()[3:]
        half = 0.5 * float(np.linalg.norm(rotvec))                    # half the rotation angle, rad
        xyz = rotvec * (0.5 * np.sinc(half / np.pi))                  # n sin(a/2) = a n * sin(a/2) / a, exact at 0
        return np.append(xyz, np.cos(half))

    def angle_to(self, other: Pose) -> float:
        """Rotation angle (rad) between this pose's orientation and another's."""
        return float(np.linalg.norm(self.rotvec_to(other)))

    def distance_to(self, other: Pose) -> float:
        """Euclidean distance (m) between the two translations."""
        return float(np.linalg.norm(self.translation - other.translation))

    def is_close(self, other: Pose, *, atol_m: float = 1e-9, atol_rad: float = 1e-9) -> bool:
        """Whether both translation and rotation agree within tolerances."""
        return self.distance_to(other) <= atol_m and self.angle_to(other) <= atol_rad

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly form: translation (m), quaternion ``[x, y, z, w]`` and rotation vector (rad)."""
        return {
            "translation_m": [float(v) for v in self.translation],
            "quaternion_xyzw": [float(v) for v in self.as_quat_xyzw()],
            "rotvec_rad": [float(v) for v in self.as_xyz_rotvec()[3:]],
        }

    @classmethod
    def from_dict(cls, data: dict[str, Sequence[float]]) -> Pose:
        """Inverse of :meth:`to_dict`: its rotation vector (OpenCV), or without one its quaternion (scipy)."""
        translation = np.asarray(data["translation_m"], dtype=float)
        if "rotvec_rad" in data:
            return cls.from_xyz_rotvec(translation, np.asarray(data["rotvec_rad"], dtype=float))
        return cls(_scipy_rotation().from_quat(np.asarray(data["quaternion_xyzw"], dtype=float)), translation)

    def __repr__(self) -> str:
        t = ", ".join(f"{v:.6g}" for v in self.translation)
        r = ", ".join(f"{v:.6g}" for v in self.as_xyz_rotvec()[3:])
        return f"Pose(xyz_m=[{t}], rotvec_rad=[{r}])"
