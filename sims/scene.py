"""The simulated scene: the measuring plane, box-shaped work objects lying on it, and posed solids.

Everything here is in the *world* frame (the robot base frame), metres. Ray casting
is vectorised over rays: one call handles a whole 224x172 depth image. Every surface
(the plane, each face of each box or solid) has an id and a near-infrared reflectivity, which
the ToF artefacts (mixed pixels, multipath, amplitude) need: ADR 0014. A :class:`Solid` is a
box at any pose (the plate the arm holds, ``[sim.plate]``), added for one frame's cast.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cellcal.devices.errors import CalibrationError
from cellcal.devices.pose import Pose

FloatArray = NDArray[np.float64]

#: Rays with |cos(angle to the plane normal)| below this count as parallel to the plane.
_PARALLEL_EPS = 1e-12
#: Hits closer than this to the ray origin are ignored (the origin lying on a surface).
_T_MIN_M = 1e-9
#: Surface id of a ray that hits nothing, and of the measuring plane; box ``k``'s faces are
#: ``1 + 6 k + f``, ``f = 2 * axis + (1 if the face is the +axis one else 0)`` in the box frame;
#: the solids follow the boxes (solid ``j`` is box ``len(boxes) + j`` in that numbering).
SURFACE_NONE = -1
SURFACE_PLANE = 0
#: Default near-infrared reflectivity of the plane and the boxes (a grey table, cardboard).
DEFAULT_REFLECTIVITY = 0.5
#: Largest reflectivity accepted (above 1: retro-reflective material, a "strong reflector").
MAX_REFLECTIVITY = 100.0


def _vec3(value: ArrayLike, what: str) -> FloatArray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise CalibrationError(f"{what} must be 3 finite numbers, got {value!r}")
    return arr


@dataclass(frozen=True)
class Box:
    """A box-shaped work object standing on the measuring plane.

    Attributes:
        center_xy_m: Centre of the box's footprint in the plane frame (x, y), metres.
        size_m: Edge lengths (along the box's x, y and the plane normal), metres, > 0.
        yaw_rad: Rotation of the box about the plane normal, radians.
        reflectivity: Near-infrared (Lambertian) reflectivity of its faces, > 0 (1 = white;
            above 1 models a retro-reflective "strong reflector").
    """

    center_xy_m: tuple[float, float]
    size_m: tuple[float, float, float]
    yaw_rad: float = 0.0
    reflectivity: float = DEFAULT_REFLECTIVITY

    def __post_init__(self) -> None:
        c = np.asarray(self.center_xy_m, dtype=np.float64)
        s = np.asarray(self.size_m, dtype=np.float64)
        if c.shape != (2,) or not np.all(np.isfinite(c)):
            raise CalibrationError(f"Box.center_xy_m must be 2 finite numbers, got {self.center_xy_m!r}")
        if s.shape != (3,) or not np.all(np.isfinite(s)) or np.any(s <= 0):
            raise CalibrationError(f"Box.size_m must be 3 positive numbers, got {self.size_m!r}")
        if not np.isfinite(self.yaw_rad):
            raise CalibrationError(f"Box.yaw_rad must be finite, got {self.yaw_rad!r}")
        _check_reflectivity(self.reflectivity, "Box.reflectivity")
        object.__setattr__(self, "center_xy_m", (float(c[0]), float(c[1])))
        object.__setattr__(self, "size_m", (float(s[0]), float(s[1]), float(s[2])))
        object.__setattr__(self, "yaw_rad", float(self.yaw_rad))
        object.__setattr__(self, "reflectivity", float(self.reflectivity))


def _check_reflectivity(value: float, what: str) -> None:
    if not (isinstance(value, (int, float)) and 0.0 < float(value) <= MAX_REFLECTIVITY):
        raise CalibrationError(f"{what} must be in (0, {MAX_REFLECTIVITY:g}], got {value!r}")


@dataclass(frozen=True, eq=False)
class Solid:
    """A box at any pose in the world (not standing on the plane): the plate the arm holds.

    Attributes:
        rotation: Rotation world <- solid frame, (3, 3) (columns: the solid's x, y, z axes).
        centre_m: The solid's centre, world frame, metres, (3,).
        size_m: Edge lengths along the solid's x, y, z axes, metres, > 0.
        reflectivity: Near-infrared reflectivity of its faces, > 0.
    """

    rotation: FloatArray
    centre_m: FloatArray
    size_m: tuple[float, float, float]
    reflectivity: float = DEFAULT_REFLECTIVITY

    def __post_init__(self) -> None:
        rot = np.asarray(self.rotation, dtype=np.float64)
        if rot.shape != (3, 3) or not np.allclose(rot.T @ rot, np.eye(3), atol=1e-9):
            raise CalibrationError("Solid.rotation must be a 3x3 rotation matrix")
        s = np.asarray(self.size_m, dtype=np.float64)
        if s.shape != (3,) or not np.all(np.isfinite(s)) or np.any(s <= 0):
            raise CalibrationError(f"Solid.size_m must be 3 positive numbers, got {self.size_m!r}")
        _check_reflectivity(self.reflectivity, "Solid.reflectivity")
        object.__setattr__(self, "rotation", rot)
        object.__setattr__(self, "centre_m", _vec3(self.centre_m, "Solid.centre_m"))
        object.__setattr__(self, "size_m", (float(s[0]), float(s[1]), float(s[2])))
        object.__setattr__(self, "reflectivity", float(self.reflectivity))


@dataclass(frozen=True, eq=False)
class Scene:
    """The measuring plane (world frame, metres) and boxes lying on it.

    Plane frame: origin at :attr:`plane_point_m`, z along the plane's unit normal, x
    along the world x axis projected into the plane (world y if x is nearly parallel
    to the normal), y = z × x. Boxes are placed in this frame.

    Attributes:
        plane_point_m: A point on the plane, world frame, metres, shape (3,).
        plane_normal: Unit normal of the plane, world frame (normalised on construction).
        boxes: Work objects standing on the plane (on the side the normal points to).
        plane_reflectivity: Near-infrared reflectivity of the plane, > 0.
        solids: Boxes at any pose (ray cast after the boxes; their surface ids follow the boxes').
    """

    plane_point_m: FloatArray = field(default_factory=lambda: np.zeros(3))
    plane_normal: FloatArray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    boxes: tuple[Box, ...] = ()
    plane_reflectivity: float = DEFAULT_REFLECTIVITY
    solids: tuple[Solid, ...] = ()

    def __post_init__(self) -> None:
        p = _vec3(self.plane_point_m, "Scene.plane_point_m")
        n = _vec3(self.plane_normal, "Scene.plane_normal")
        norm = float(np.linalg.norm(n))
        if norm < 1e-9:
            raise CalibrationError("Scene.plane_normal must be non-zero")
        n = n / norm
        for a in (p, n):
            a.setflags(write=False)
        object.__setattr__(self, "plane_point_m", p)
        object.__setattr__(self, "plane_normal", n)
        object.__setattr__(self, "boxes", tuple(self.boxes))
        _check_reflectivity(self.plane_reflectivity, "Scene.plane_reflectivity")
        object.__setattr__(self, "plane_reflectivity", float(self.plane_reflectivity))
        # Plane frame basis (columns x, y, z in world coordinates).
        ref = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        x = ref - n * float(ref @ n)
        x /= np.linalg.norm(x)
        y = np.cross(n, x)
        r_world_plane = np.column_stack([x, y, n])
        object.__setattr__(self, "_r_world_plane", r_world_plane)
        # Per box: rotation world<-box (3x3), centre (3,), half extents (3,).
        rots, centres, halves = [], [], []
        for b in self.boxes:
            if not isinstance(b, Box):
                raise CalibrationError(f"Scene.boxes must hold Box objects, got {type(b).__name__}")
            r_plane_box = Pose.from_xyz_rpy(np.zeros(3), (0.0, 0.0, b.yaw_rad)).rotation_matrix
            rots.append(r_world_plane @ r_plane_box)
            local = np.array([b.center_xy_m[0], b.center_xy_m[1], b.size_m[2] / 2.0])
            centres.append(p + r_world_plane @ local)
            halves.append(np.asarray(b.size_m) / 2.0)
        object.__setattr__(self, "solids", tuple(self.solids))
        for solid in self.solids:
            if not isinstance(solid, Solid):
                raise CalibrationError(f"Scene.solids must hold Solid objects, got {type(solid).__name__}")
            rots.append(solid.rotation)
            centres.append(solid.centre_m)
            halves.append(np.asarray(solid.size_m) / 2.0)
        object.__setattr__(self, "_box_rot", np.array(rots).reshape(-1, 3, 3))
        object.__setattr__(self, "_box_centre", np.array(centres).reshape(-1, 3))
        object.__setattr__(self, "_box_half", np.array(halves).reshape(-1, 3))
        # Reflectivity per surface id + 1 (index 0: no surface, 1: the plane, then 6 faces per box, then per solid).
        faces = [b.reflectivity for b in self.boxes] + [s.reflectivity for s in self.solids]
        refl = [0.0, self.plane_reflectivity] + [r for r in faces for _ in range(6)]
        object.__setattr__(self, "_reflectivity", np.asarray(refl, dtype=np.float64))

    @property
    def has_edges(self) -> bool:
        """Whether anything but the plane is in the scene (a box or a solid: depth edges, multipath)."""
        return bool(self.boxes or self.solids)

    def solid_surface_ids(self, index: int) -> range:
        """Surface ids of the six faces of solid ``index`` (face ``f`` is ``ids[f]``, numbered as a box's)."""
        if not 0 <= index < len(self.solids):
            raise IndexError(f"no solid {index} (the scene has {len(self.solids)})")
        first = 1 + 6 * (len(self.boxes) + index)
        return range(first, first + 6)

    def with_solids(self, solids: Sequence[Solid]) -> Scene:
        """This scene with ``solids`` in place of its own (the plane and the boxes shared)."""
        return Scene(self.plane_point_m, self.plane_normal, self.boxes, self.plane_reflectivity, tuple(solids))

    @property
    def plane_rotation(self) -> FloatArray:
        """3x3 rotation world <- plane frame (columns: plane x, y, normal)."""
        out: FloatArray = self._r_world_plane.copy()  # type: ignore[attr-defined]
        return out

    def plane_to_world(self, xyz_plane_m: ArrayLike) -> FloatArray:
        """Map points from the plane frame to the world frame (metres, (3,) or (N, 3))."""
        p = np.asarray(xyz_plane_m, dtype=np.float64)
        out: FloatArray = p @ self._r_world_plane.T + self.plane_point_m  # type: ignore[attr-defined]
        return out

    def signed_distance_to_plane(self, points_m: ArrayLike) -> FloatArray:
        """Signed distance (m) of world points from the plane, positive on the normal's side."""
        p = np.asarray(points_m, dtype=np.float64)
        out: FloatArray = (p - self.plane_point_m) @ self.plane_normal
        return out

    def reflectivity(self, surface: NDArray[np.integer]) -> FloatArray:
        """Reflectivity per surface id (:meth:`raycast_surfaces`; 0 where the id is ``SURFACE_NONE``)."""
        out: FloatArray = self._reflectivity[np.asarray(surface) + 1]  # type: ignore[attr-defined]
        return out

    # ------------------------------------------------------------------ ray casting
    def raycast(self, origin: ArrayLike, dirs: ArrayLike) -> tuple[FloatArray, FloatArray, NDArray[np.bool_]]:
        """Cast rays from one origin against the plane, the boxes and the solids.

        Args:
            origin: Ray origin, world frame, metres, shape (3,).
            dirs: Ray directions, world frame, shape (N, 3); need not be unit length
                (``t`` is then in units of the direction's length).

        Returns:
            ``(t, normal, hit)``: ``t`` (N,) the ray parameter of the nearest hit
            (metres along unit directions), ``inf`` where nothing is hit; ``normal``
            (N, 3) the unit surface normal at the hit, oriented against the ray
            (``dot(dir, normal) <= 0``), NaN where nothing is hit; ``hit`` (N,) bool.

        Raises:
            CalibrationError: On malformed shapes or non-finite values.
        """
        t, normals, hit, _ = self.raycast_surfaces(origin, dirs)
        return t, normals, hit

    def raycast_surfaces(self, origin: ArrayLike, dirs: ArrayLike
                         ) -> tuple[FloatArray, FloatArray, NDArray[np.bool_], NDArray[np.int32]]:
        """:meth:`raycast` plus the id of the surface each ray hits (``SURFACE_NONE`` = -1 for none).

        Ids: ``SURFACE_PLANE`` (0) for the plane, ``1 + 6 k + f`` for face ``f`` of box ``k`` (the solids
        numbered on after the boxes: :meth:`solid_surface_ids`).

        Raises:
            CalibrationError: On malformed shapes or non-finite values.
        """
        o, d = _checked_rays(origin, dirs)
        # The plane first: the nearest hit so far, its normal and surface id.
        t_best, normals = self._hit_plane(o, d)
        surface = np.where(np.isfinite(t_best), SURFACE_PLANE, SURFACE_NONE).astype(np.int32)
        # Then each box (and solid); a hit replaces the current one only where it is nearer.
        boxes = zip(self._box_rot, self._box_centre, self._box_half, strict=True)  # type: ignore[attr-defined]
        for k, (rot, centre, half) in enumerate(boxes):
            t_best = _hit_box(o, d, rot, centre, half, t_best, normals, surface, 1 + 6 * k)
        hit_any = np.isfinite(t_best)
        # Orient normals against the ray (dot(dir, normal) <= 0); NaN where nothing was hit.
        flip = np.einsum("ij,ij->i", normals, d) > 0
        normals[flip] *= -1.0
        normals[~hit_any] = np.nan
        return t_best, normals, hit_any, surface

    def _hit_plane(self, o: FloatArray, d: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Ray parameters of the plane hits (``inf`` for none) and the plane normal per ray, (N,) and (N, 3)."""
        n = self.plane_normal
        # t = (p0 - o).n / (d.n), with p0 a point on the plane
        denom = d @ n
        num = float((self.plane_point_m - o) @ n)
        # Rays (nearly) parallel to the plane never hit it: t = inf.
        parallel = np.abs(denom) < _PARALLEL_EPS
        with np.errstate(divide="ignore", invalid="ignore"):
            t_plane = np.where(parallel, np.inf, num / np.where(parallel, 1.0, denom))
        # Hits behind (or at) the origin do not count.
        t_plane = np.where(t_plane > _T_MIN_M, t_plane, np.inf)
        normals = np.broadcast_to(n, (d.shape[0], 3)).copy()
        return t_plane, normals


def _checked_rays(origin: ArrayLike, dirs: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """``origin`` as a finite (3,) array and ``dirs`` as a finite (N, 3) array, float64.

    Raises:
        CalibrationError: On malformed shapes or non-finite values.
    """
    o = _vec3(origin, "ray origin")
    d = np.asarray(dirs, dtype=np.float64)
    if d.ndim != 2 or d.shape[1] != 3:
        raise CalibrationError(f"ray directions must have shape (N, 3), got {d.shape}")
    if not np.all(np.isfinite(d)):
        raise CalibrationError("ray directions must be finite")
    return o, d


def _hit_box(o: FloatArray, d: FloatArray, rot: FloatArray, centre: FloatArray, half: FloatArray,
             t_best: FloatArray, normals: FloatArray, surface: NDArray[np.int32], first_id: int) -> FloatArray:
    """Intersect the rays with one box (slab method in the box's own frame).

    Args:
        o: Ray origin, world frame, metres, (3,).
        d: Ray directions, world frame, (N, 3).
        rot: Rotation world <- box, (3, 3).
        centre: Box centre, world frame, metres, (3,).
        half: Half edge lengths, metres, (3,).
        t_best: Ray parameters of the nearest hits so far, (N,) (``inf`` for none).
        normals: Surface normals of those hits, world frame, (N, 3); rows of rays the
            box hits nearer are overwritten in place with the box face's normal.
        surface: Surface ids of those hits, (N,); overwritten in place like ``normals``.
        first_id: Surface id of this box's face 0.

    Returns:
        The updated nearest ray parameters, (N,).
    """
    idx = _near_sphere(o, d, centre, float(np.linalg.norm(half)), t_best)
    if idx.size == 0:
        return t_best
    # Ray origin and directions in the box frame (box centre at the origin, axes along its edges).
    o_l = rot.T @ (o - centre)
    d_l = d[idx] @ rot  # == (rot.T @ d.T).T
    # Entry and exit parameters of the three slabs |x_i| <= half_i.
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d_l
        t1 = (-half - o_l) * inv
        t2 = (half - o_l) * inv
    t_lo = np.fmin(t1, t2)  # NaN (0 * inf on a slab boundary) is ignored by fmin/fmax
    t_hi = np.fmax(t1, t2)
    # The ray is inside the box between the last slab entry and the first slab exit.
    t_near = np.max(np.where(np.isnan(t_lo), -np.inf, t_lo), axis=1)
    t_far = np.min(np.where(np.isnan(t_hi), np.inf, t_hi), axis=1)
    # A hit: a non-empty interval entered in front of the origin, nearer than the best so far.
    hit = (t_near <= t_far) & (t_near > _T_MIN_M) & np.isfinite(t_near)
    closer = hit & (t_near < t_best[idx])
    if not np.any(closer):
        return t_best
    sel = np.nonzero(closer)[0]
    rays = idx[sel]
    normals[rays], faces = _entry_faces(t_lo, d_l, rot, sel)
    surface[rays] = first_id + faces
    out = t_best.copy()
    out[rays] = t_near[sel]
    return out


def _near_sphere(o: FloatArray, d: FloatArray, centre: FloatArray, radius: float, t_best: FloatArray
                 ) -> NDArray[np.intp]:
    """Indices of the rays that meet the sphere ``|x - centre| <= radius`` in front of the origin and
    enter it before ``t_best`` (the only rays that can hit a box inside it nearer)."""
    w = centre - o
    dw = d @ w
    a = np.einsum("ij,ij->i", d, d)
    # |o + t d - c|^2 = r^2  <=>  a t^2 - 2 (d.w) t + |w|^2 - r^2 = 0
    disc = dw * dw - a * (float(w @ w) - radius * radius)
    root = np.sqrt(np.maximum(disc, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        cand = (disc >= 0) & (dw + root > 0) & ((dw - root) / a < t_best)
    out: NDArray[np.intp] = np.nonzero(cand)[0]
    return out


def _entry_faces(t_lo: FloatArray, d_l: FloatArray, rot: FloatArray, idx: NDArray[np.intp]
                 ) -> tuple[FloatArray, NDArray[np.int32]]:
    """World-frame normals (len(idx), 3) and face numbers (0..5) of the box faces the rays ``idx`` enter through.

    Args:
        t_lo: Slab entry parameters per ray and box axis, (N, 3) (NaN on a slab boundary).
        d_l: Ray directions in the box frame, (N, 3).
        rot: Rotation world <- box, (3, 3).
        idx: Indices of the rays that hit the box.
    """
    # The entry face is the slab entered last; its outward normal points against the ray.
    axis = np.argmax(np.where(np.isnan(t_lo), -np.inf, t_lo), axis=1)
    sign = -np.sign(d_l[idx, axis[idx]])
    n_local = np.zeros((idx.size, 3))
    n_local[np.arange(idx.size), axis[idx]] = sign
    # Box frame -> world frame; face number 2 * axis (+1 for the face on the +axis side).
    out: FloatArray = n_local @ rot.T
    return out, (2 * axis[idx] + (sign > 0)).astype(np.int32)


def scene_from_boxes(plane_point_m: Sequence[float], plane_normal: Sequence[float],
                     boxes: Sequence[Box] = (), plane_reflectivity: float = DEFAULT_REFLECTIVITY) -> Scene:
    """Convenience constructor: ``Scene`` from plain sequences."""
    return Scene(np.asarray(plane_point_m, dtype=np.float64), np.asarray(plane_normal, dtype=np.float64),
                 tuple(boxes), plane_reflectivity)
