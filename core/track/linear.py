"""The hand-eye plane model (:mod:`cellcal.core.handeye.model`) vectorised over parameter sets and frames.

The tracker evaluates the whitened residual of a frame at 19 parameter vectors per update
(central differences of all nine parameters at once) and refits a few hundred buffered
frames after a change, so the model is written here in stacked numpy (one rotation object per
call for all parameter sets); a unit test checks it against ``PlaneModel.predict``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cellcal.core.geometry.planes import Plane
from cellcal.core.handeye.model import PlaneObservation, tangent_basis, whitening
from cellcal.devices.pose import Pose

FloatArray = NDArray[np.float64]
#: Central-difference step of the Jacobian (rad or m), as in the hand-eye estimator.
STEP = 1e-6
#: Terms of the camera's systematic allowance a frame can carry (scale, offset and six field shapes: ADR 0059).
SYSTEMATIC_SLOTS = 8


def rotvec_matrices(v: FloatArray) -> FloatArray:
    """Rotation matrices (K, 3, 3) of rotation vectors (K, 3) (rad), all in one call."""
    from scipy.spatial.transform import Rotation

    out: FloatArray = Rotation.from_rotvec(v).as_matrix()
    return out


@dataclass(frozen=True)
class Frames:
    """Whitened plane observations stacked (N of them).

    Attributes:
        t_s: Frame times, s (N,).
        rot_a, t_a: ``T_base_flange`` rotation matrices (N, 3, 3) and translations (N, 3), m.
        normals, offsets: Measured camera-frame normals (N, 3) and offsets (N,), m.
        bases: Tangent bases of the measured normals (N, 3, 2).
        whiten: Inverse Cholesky factors of the residuals' covariance (N, 3, 3).
        systematic: Per frame and term of the camera's systematic allowance (a coefficient common to
            every frame), the whitened residual's 1-sigma change (N, SYSTEMATIC_SLOTS, 3); zeros: none.
    """

    t_s: FloatArray
    rot_a: FloatArray
    t_a: FloatArray
    normals: FloatArray
    offsets: FloatArray
    bases: FloatArray
    whiten: FloatArray
    systematic: FloatArray

    def __len__(self) -> int:
        return len(self.t_s)

    @staticmethod
    def of(t_s: float, obs: PlaneObservation, arm_translation_sigma_m: float, arm_rotation_sigma_rad: float,
           lever_m: float, shifts: FloatArray | None = None) -> Frames:
        """One observation as a stack of one (whitened as the hand-eye fit whitens it).

        ``shifts``: (SYSTEMATIC_SLOTS, 4) the camera-frame plane's 1-sigma shift per allowance term
        (normal delta, offset delta), or None.
        """
        basis, white = whitening(obs, arm_translation_sigma_m, arm_rotation_sigma_rad, lever_m)
        flange = obs.flange
        sys = np.zeros((1, SYSTEMATIC_SLOTS, 3))
        if shifts is not None:
            raw = np.concatenate([shifts[:, :3] @ basis, shifts[:, 3:4]], axis=1)  # (S, 3): across the normal, offset
            sys[0] = -raw @ white.T  # the measured plane moves: the residual (predicted - measured) the other way
        return Frames(np.array([t_s]), flange.rotation_matrix[None].copy(), np.asarray(flange.translation)[None],
                      np.asarray(obs.normal, dtype=np.float64)[None], np.array([obs.offset_m]), basis[None],
                      white[None], sys)

    @staticmethod
    def stack(frames: Sequence[Frames]) -> Frames:
        """Several stacks as one."""
        return Frames(*(np.concatenate([getattr(f, name) for f in frames]) for name in FrameRing._FIELDS))


class FrameRing:
    """A bounded window of frames in preallocated arrays; the oldest is handed back when a new one pushes it out.

    Args:
        capacity: Frames kept.
    """

    _FIELDS = ("t_s", "rot_a", "t_a", "normals", "offsets", "bases", "whiten", "systematic")
    _SHAPES = ((), (3, 3), (3,), (3,), (), (3, 2), (3, 3), (SYSTEMATIC_SLOTS, 3))

    def __init__(self, capacity: int) -> None:
        if capacity < 1:
            raise ValueError(f"a frame window needs a capacity of at least 1, got {capacity}")
        self.capacity = capacity
        self._arrays = [np.zeros((capacity, *shape)) for shape in self._SHAPES]
        self._n = 0  # frames held
        self._next = 0  # slot of the next frame (the oldest once full)

    def __len__(self) -> int:
        return self._n

    def push(self, frame: Frames) -> Frames | None:
        """Add one frame (a stack of one); the frame it pushed out (None while not full)."""
        evicted = None
        if self._n == self.capacity:
            evicted = Frames(*(a[self._next:self._next + 1].copy() for a in self._arrays))
        for a, name in zip(self._arrays, self._FIELDS, strict=True):
            a[self._next] = getattr(frame, name)[0]
        self._next = (self._next + 1) % self.capacity
        self._n = min(self._n + 1, self.capacity)
        return evicted

    def frames(self) -> Frames:
        """The frames held (in slot order, not time order), as views."""
        return Frames(*(a[:self._n] for a in self._arrays))

    def drop_from(self, t_s: float) -> int:
        """Remove the frames at or after ``t_s``; how many."""
        times = self._arrays[0][:self._n]
        order = np.argsort(times, kind="stable")
        order = order[times[order] < t_s]  # the kept frames, oldest first
        removed = self._n - len(order)
        if removed == 0:
            return 0
        for a in self._arrays:
            a[:len(order)] = a[order]  # compact in time order: the next push goes after the newest
        self._n = len(order)
        self._next = self._n % self.capacity
        return removed

    def clear(self) -> None:
        """Remove every frame."""
        self._n = self._next = 0


class LinearModel:
    """Whitened residuals and their Jacobian of the nine parameters (as ``PARAMETERS``) for stacked frames.

    Args:
        nominal_mount: The configured ``T_flange_camera`` (the zero of the parameters).
        nominal_plane: The configured base-frame plane, normal toward the camera side.
    """

    def __init__(self, nominal_mount: Pose, nominal_plane: Plane) -> None:
        self.r_x0 = np.array(nominal_mount.rotation_matrix)
        self.t_x0 = np.array(nominal_mount.translation)
        self.n_b0 = np.array(nominal_plane.normal)
        self.c_b0 = float(nominal_plane.offset_m)
        self.tilt_axes = tangent_basis(self.n_b0)  # the plane's tilt axes (3x2), as PlaneModel's

    def residuals(self, params: FloatArray, frames: Frames) -> FloatArray:
        """Whitened residuals (K, N, 3) (predicted - measured) at parameter vectors (K, 9)."""
        r_x = rotvec_matrices(params[:, 0:3]) @ self.r_x0  # mount turned about the flange axes
        t_x = self.t_x0 + params[:, 3:6]  # mount translation, flange frame
        n_b = np.einsum("kij,j->ki", rotvec_matrices(params[:, 6:8] @ self.tilt_axes.T), self.n_b0)  # tilted normal
        c_b = self.c_b0 + params[:, 8]  # plane offset
        u = np.einsum("nji,kj->kni", frames.rot_a, n_b)  # the normal in the flange frame, R_A^T n_B
        n_c = np.einsum("kji,knj->kni", r_x, u)  # in the camera frame, R_X^T u
        t_c = np.einsum("nij,kj->kni", frames.rot_a, t_x) + frames.t_a  # camera origin, base frame
        c_c = c_b[:, None] + np.einsum("kni,ki->kn", t_c, n_b)  # the camera's distance to the plane
        tangent = np.einsum("nij,kni->knj", frames.bases, n_c - frames.normals)  # normal error across itself
        raw = np.concatenate([tangent, (c_c - frames.offsets)[:, :, None]], axis=2)
        white: FloatArray = np.einsum("nij,knj->kni", frames.whiten, raw)
        return white

    def linearise(self, x: FloatArray, frames: Frames) -> tuple[FloatArray, FloatArray]:
        """Whitened residuals (N, 3) at ``x`` (9,) and their Jacobian (N, 3, 9) by central differences."""
        steps = np.vstack([np.zeros(9), STEP * np.eye(9), -STEP * np.eye(9)])
        res = self.residuals(x + steps, frames)  # all 19 parameter vectors at once
        jac = np.moveaxis((res[1:10] - res[10:19]) / (2 * STEP), 0, 2)  # (N, 3, 9)
        return res[0], jac


__all__ = ["SYSTEMATIC_SLOTS", "FrameRing", "Frames", "LinearModel", "rotvec_matrices"]
