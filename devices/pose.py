"""Rigid transforms (poses) in SI units, built on ``scipy.spatial.transform``.

A :class:`Pose` ``T_a_b`` maps coordinates expressed in frame *b* into frame *a*:
``p_a = T_a_b.apply(p_b)``. Composition follows matrix order, so
``T_a_c = T_a_b @ T_b_c``. Translations are metres; rotations are
:class:`scipy.spatial.transform.Rotation` objects (no hand-rolled quaternion or
Euler code anywhere in cellcal).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from .errors import CalibrationError

FloatArray = NDArray[np.float64]


def _rotate(rotation: Rotation, vectors: ArrayLike) -> FloatArray:
    """``rotation.apply`` that also accepts read-only arrays (scipy >= 1.15 rejects them)."""
    arr = np.array(vectors, dtype=np.float64)  # always a fresh, writeable copy
    out: FloatArray = rotation.apply(arr)
    return out


def _as_vector3(value: ArrayLike, what: str) -> FloatArray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise CalibrationError(f"{what} must be 3 numbers, got {value!r}") from exc
    if arr.shape != (3,):
        raise CalibrationError(f"{what} must have shape (3,), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise CalibrationError(f"{what} must be finite, got {arr.tolist()}")
    return arr


@dataclass(frozen=True, eq=False)
class Pose:
    """A rigid transform: rotation then translation (metres).

    Attributes:
        rotation: Rotation part.
        translation: Translation part, shape (3,), metres.
    """

    rotation: Rotation = field(default_factory=Rotation.identity)
    translation: FloatArray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        if not isinstance(self.rotation, Rotation) or not self.rotation.single:
            raise CalibrationError("Pose.rotation must be a single scipy Rotation")
        t = _as_vector3(self.translation, "Pose.translation")
        t.setflags(write=False)
        object.__setattr__(self, "translation", t)

    # ------------------------------------------------------------------ constructors
    @classmethod
    def identity(cls) -> Pose:
        """The identity transform."""
        return cls()

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
        if not np.allclose(r @ r.T, np.eye(3), atol=1e-6) or np.linalg.det(r) <= 0:
            raise CalibrationError("3x3 block of the transform is not a proper rotation")
        return cls(Rotation.from_matrix(r), m[:3, 3].copy())

    @classmethod
    def from_xyz_rotvec(cls, xyz_m: ArrayLike, rotvec_rad: ArrayLike) -> Pose:
        """Build from a translation (m) and a rotation vector (axis * angle, rad)."""
        return cls(Rotation.from_rotvec(_as_vector3(rotvec_rad, "rotation vector")), np.asarray(xyz_m))

    @classmethod
    def from_xyz_rpy(cls, xyz_m: ArrayLike, rpy_rad: ArrayLike) -> Pose:
        """Build from a translation (m) and fixed-axis roll, pitch, yaw (rad).

        The rotation is ``Rz(yaw) @ Ry(pitch) @ Rx(roll)`` (extrinsic x-y-z), the
        convention of REP 103 and of most robot controllers.
        """
        return cls(Rotation.from_euler("xyz", _as_vector3(rpy_rad, "roll/pitch/yaw")), np.asarray(xyz_m))

    # ------------------------------------------------------------------ algebra
    def __matmul__(self, other: Pose) -> Pose:
        if not isinstance(other, Pose):
            return NotImplemented
        t = _rotate(self.rotation, other.translation) + self.translation
        return Pose(self.rotation * other.rotation, t)

    def inv(self) -> Pose:
        """The inverse transform."""
        r_inv = self.rotation.inv()
        return Pose(r_inv, -_rotate(r_inv, self.translation))

    def apply(self, points: ArrayLike) -> FloatArray:
        """Transform points (shape (3,) or (N, 3), metres) from the source to the target frame."""
        p = np.asarray(points, dtype=np.float64)
        if p.shape[-1:] != (3,) or p.ndim > 2:
            raise CalibrationError(f"points must have shape (3,) or (N, 3), got {p.shape}")
        out: FloatArray = _rotate(self.rotation, p) + self.translation
        return out

    def apply_vector(self, vectors: ArrayLike) -> FloatArray:
        """Rotate direction vectors (no translation)."""
        out: FloatArray = _rotate(self.rotation, vectors)
        return out

    # ------------------------------------------------------------------ views
    def as_matrix(self) -> FloatArray:
        """The 4x4 homogeneous matrix (translation in metres)."""
        m = np.eye(4)
        m[:3, :3] = self.rotation.as_matrix()
        m[:3, 3] = self.translation
        return m

    def as_xyz_rotvec(self) -> FloatArray:
        """``[x, y, z, rx, ry, rz]``: metres and rotation vector (rad)."""
        return np.concatenate([self.translation, self.rotation.as_rotvec()])

    def as_xyz_rpy(self) -> FloatArray:
        """``[x, y, z, roll, pitch, yaw]``: metres and fixed-axis x-y-z angles (rad)."""
        return np.concatenate([self.translation, self.rotation.as_euler("xyz")])

    def angle_to(self, other: Pose) -> float:
        """Rotation angle (rad) between this pose's orientation and another's."""
        return float((self.rotation.inv() * other.rotation).magnitude())

    def distance_to(self, other: Pose) -> float:
        """Euclidean distance (m) between the two translations."""
        return float(np.linalg.norm(self.translation - other.translation))

    def is_close(self, other: Pose, *, atol_m: float = 1e-9, atol_rad: float = 1e-9) -> bool:
        """Whether both translation and rotation agree within tolerances."""
        return self.distance_to(other) <= atol_m and self.angle_to(other) <= atol_rad

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly form: translation (m) and quaternion ``[x, y, z, w]``."""
        return {
            "translation_m": [float(v) for v in self.translation],
            "quaternion_xyzw": [float(v) for v in self.rotation.as_quat()],
            "rotvec_rad": [float(v) for v in self.rotation.as_rotvec()],
        }

    @classmethod
    def from_dict(cls, data: dict[str, Sequence[float]]) -> Pose:
        """Inverse of :meth:`to_dict` (uses the quaternion)."""
        return cls(Rotation.from_quat(np.asarray(data["quaternion_xyzw"], dtype=float)),
                   np.asarray(data["translation_m"], dtype=float))

    def __repr__(self) -> str:
        t = ", ".join(f"{v:.6g}" for v in self.translation)
        r = ", ".join(f"{v:.6g}" for v in self.rotation.as_rotvec())
        return f"Pose(xyz_m=[{t}], rotvec_rad=[{r}])"
