"""What a set of plane observations can and cannot determine about the mount, in words.

The whitened Jacobian's singular values give the rank and condition; each direction
whose 1-sigma would exceed :data:`UNOBSERVABLE_SIGMA` (0.1 rad or 0.1 m: the data do
not determine it) is split into the mount's rotation and translation parts, expressed
in the flange frame and named: about or along which axis, whether it is the plane
normal seen from the flange, parallel to the plane at every pose, or confounded with
the plane's height; with the poses that would make it visible (ADR 0018).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cellcal.core.handeye.model import MOUNT_ROTATION, MOUNT_TRANSLATION, PARAMETERS, PLANE_OFFSET, PLANE_TILT

FloatArray = NDArray[np.float64]

#: A direction whose 1-sigma exceeds this (rad for rotations, m for translations) is unobservable.
UNOBSERVABLE_SIGMA = 0.1
#: A null vector's share in a block above which that block takes part in the unseen direction.
BLOCK_SHARE = 0.2
#: |cos| above which an axis counts as the plane normal / below which as parallel to the plane.
PARALLEL_COS = 0.98
ACROSS_COS = 0.02

FIX_ROTATION = "poses at a second inclination or rolled about the tool axis"
FIX_ALONG_PLANE = "poses tilted toward that axis (a second inclination, several rolls about the tool axis)"
FIX_HEIGHT = "poses at a second inclination (one cone of normals is not enough), or given = [\"plane_offset\"]"
#: The fix of any unobservable plan, in one line.
FIX_PLAN = "add a second inclination and rolls about the tool axis"


@dataclass(frozen=True)
class UnseenDirection:
    """One direction of the mount the data cannot determine.

    Attributes:
        part: ``"rotation"``, ``"translation"`` or ``"plane"``.
        axis: Unit axis in the flange frame (base frame for ``"plane"``), or None for a subspace.
        what: The direction in words.
        fix: The poses (or given value) that would make it observable.
    """

    part: str
    axis: tuple[float, float, float] | None
    what: str
    fix: str

    def to_dict(self) -> dict[str, Any]:
        """JSON form."""
        return {"part": self.part, "axis_flange": None if self.axis is None else list(self.axis),
                "what": self.what, "fix": self.fix}


@dataclass(frozen=True)
class Observability:
    """Rank, condition and the unseen directions of a plane hand-eye problem.

    Attributes:
        rank: Directions the data determine.
        n_parameters: Parameters estimated (nine minus the given ones).
        condition: Largest over smallest singular value of the whitened Jacobian (inf if singular).
        singular_values: Of the whitened Jacobian, descending (per rad / per m).
        unseen: The directions the data cannot determine, named.
    """

    rank: int
    n_parameters: int
    condition: float
    singular_values: tuple[float, ...]
    unseen: tuple[UnseenDirection, ...]

    @property
    def observable(self) -> bool:
        """Whether every estimated parameter is determined."""
        return self.rank == self.n_parameters

    def message(self) -> str:
        """One line: what cannot be seen and what would fix it."""
        if self.observable:
            return f"all {self.n_parameters} parameters observable (condition {self.condition:.3g})"
        height = any("height" in d.what for d in self.unseen)
        fix = FIX_PLAN + (", or give [handeye] given = [\"plane_offset\"]" if height and len(self.unseen) == 1 else "")
        return (f"cannot see {self.n_parameters - self.rank} of {self.n_parameters} parameters: "
                + "; ".join(d.what for d in self.unseen) + f"; fix: {fix}")

    def to_dict(self) -> dict[str, Any]:
        """JSON form."""
        return {"rank": self.rank, "n_parameters": self.n_parameters, "observable": self.observable,
                "condition": self.condition if np.isfinite(self.condition) else None,
                "singular_values": list(self.singular_values), "unobservable": [d.to_dict() for d in self.unseen]}


def axis_text(axis: FloatArray, frame: str = "flange") -> str:
    """``"flange z"`` for a coordinate axis, else the vector in that frame (``"flange (0.26, 0.00, 0.97)"``)."""
    for k, name in enumerate("xyz"):
        if abs(axis[k]) > 0.999:
            return f"{frame} {'-' if axis[k] < 0 else ''}{name}"
    a = np.round(axis, 2) + 0.0  # + 0.0: no "-0.00"
    return f"{frame} ({a[0]:.2f},{a[1]:.2f},{a[2]:.2f})"


def _canonical(axis: FloatArray) -> FloatArray:
    """The unseen line's direction with its largest component positive.

    An SVD returns a null vector with either sign (which one changes with the BLAS kernel); a line
    has no sign, so it is named the same way on every machine.
    """
    k = int(np.argmax(np.abs(axis)))
    out: FloatArray = -axis if axis[k] < 0 else axis
    return out


def _rotation_text(dirs: FloatArray, normals_flange: FloatArray, with_plane: bool) -> UnseenDirection:
    """Name an unseen subspace (columns ``dirs``) of the mount's rotation."""
    mean = normals_flange.mean(axis=0)
    mean /= np.linalg.norm(mean)
    traded = " (traded with the plane's tilt)" if with_plane else ""
    if dirs.shape[1] == 1:
        a = _canonical(dirs[:, 0])
        normal = " (= the plane normal)" if abs(a @ mean) > PARALLEL_COS else ""
        return UnseenDirection("rotation", tuple(float(v) for v in a),  # type: ignore[arg-type]
                               f"mount rotation about {axis_text(a)}{normal}{traded}", FIX_ROTATION)
    if dirs.shape[1] == 2:
        b = _canonical(np.cross(dirs[:, 0], dirs[:, 1]))
        return UnseenDirection("rotation", None, f"mount rotation about axes across {axis_text(b)}{traded}",
                               FIX_ROTATION)
    return UnseenDirection("rotation", None, f"mount rotation about any axis{traded}", FIX_ROTATION)


def _translation_text(dirs: FloatArray, height_axis: FloatArray | None,
                      normals_flange: FloatArray) -> list[UnseenDirection]:
    """Name an unseen subspace (columns ``dirs``) of the mount's translation.

    ``height_axis`` is the translation that trades against the plane's height (None when none does).
    """
    out: list[UnseenDirection] = []
    if height_axis is not None:
        h = height_axis
        out.append(UnseenDirection("translation", tuple(float(v) for v in h),  # type: ignore[arg-type]
                                   f"mount translation along {axis_text(h)} vs the plane's height", FIX_HEIGHT))
        dirs = dirs - np.outer(h, h @ dirs)  # what is left across the height axis
        u, s, _ = np.linalg.svd(dirs, full_matrices=False)
        dirs = u[:, s > BLOCK_SHARE]
    if dirs.shape[1] == 0:
        return out
    flat = bool(np.max(np.abs(normals_flange @ dirs)) < ACROSS_COS)  # every pose sees them edge-on
    along = " (parallel to the plane)" if flat else ""
    if dirs.shape[1] == 1:
        a = _canonical(dirs[:, 0])
        what = f"mount translation along {axis_text(a)}{along}"
    elif dirs.shape[1] == 2:
        what = f"mount translation across {axis_text(_canonical(np.cross(dirs[:, 0], dirs[:, 1])))}{along}"
    else:
        what = "mount translation in every direction"
    axis = tuple(float(v) for v in _canonical(dirs[:, 0])) if dirs.shape[1] == 1 else None
    out.append(UnseenDirection("translation", axis, what, FIX_ALONG_PLANE))  # type: ignore[arg-type]
    return out


def _block_dirs(null: FloatArray, block: slice) -> FloatArray:
    """Orthonormal directions (columns) of a parameter block that take part in the null space."""
    if null.shape[1] == 0:
        return np.zeros((block.stop - block.start, 0))
    u, s, _ = np.linalg.svd(null[block], full_matrices=False)
    return u[:, s > BLOCK_SHARE]


def analyse(jacobian: FloatArray, free: Sequence[int], normals_flange: FloatArray) -> Observability:
    """Rank, condition and named unseen directions of a whitened Jacobian.

    Args:
        jacobian: Whitened residuals by free parameters (per rad / per m), shape (3N, len(free)).
        free: Indices into :data:`~cellcal.core.handeye.model.PARAMETERS` of its columns.
        normals_flange: The plane normal in the flange frame at every pose (N, 3) (``u_i``).
    """
    _, s, vt = np.linalg.svd(jacobian, full_matrices=True)
    s_full = np.zeros(len(free))
    s_full[:len(s)] = s  # fewer residuals than parameters: the missing singular values are 0
    threshold = max(1.0 / UNOBSERVABLE_SIGMA, (s_full[0] if len(s_full) else 0.0) * 1e-10)
    seen = s_full >= threshold
    null = np.zeros((len(PARAMETERS), int((~seen).sum())))
    null[list(free)] = vt[~seen].T  # the unseen directions in the full 9-parameter space
    unseen: list[UnseenDirection] = []
    rot = _block_dirs(null, MOUNT_ROTATION)
    if rot.shape[1]:
        unseen.append(_rotation_text(rot, normals_flange, bool(np.abs(null[PLANE_TILT]).max() > BLOCK_SHARE)))
    trans = _block_dirs(null, MOUNT_TRANSLATION)
    if trans.shape[1]:
        height = null[MOUNT_TRANSLATION] @ null[PLANE_OFFSET]  # the translation that moves with the plane's height
        norm = float(np.linalg.norm(height))
        unseen += _translation_text(trans, height / norm if norm > BLOCK_SHARE else None, normals_flange)
    if not unseen and null.shape[1]:  # only the plane itself is undetermined
        unseen.append(UnseenDirection("plane", None, "the plane's tilt or height in the base frame",
                                      "add poses at other inclinations, or give plane_tilt_a/b and plane_offset"))
    condition = float(s_full[0] / s_full[-1]) if len(s_full) and s_full[-1] > 0 else float("inf")
    return Observability(int(seen.sum()), len(free), condition, tuple(float(v) for v in s_full), tuple(unseen))


__all__ = ["UNOBSERVABLE_SIGMA", "Observability", "UnseenDirection", "analyse", "axis_text"]
