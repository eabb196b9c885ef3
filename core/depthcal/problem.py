"""The least-squares problem of the depth calibration (ADR 0056): the sampled points and the model's predictions.

:class:`_Points` holds the sampled valid pixels of a set of views, stacked (:func:`_sample`), with the
field's monomials at the highest order (:func:`_monomials`). :class:`_Problem` predicts what the camera
should have measured at each point for a plane ``n · x = h`` in the base frame, the camera's poses
``C_i = F_i · M`` and a :class:`~cellcal.devices.systematic.SystematicError`, and gives the analytic
columns of its Jacobian, one row per parameter (the plane's from the ray's meeting with it, the mount's
by central differences). :func:`_initial_plane` and :func:`_tangents` give the plane the tilts are
measured from. The small helpers (:func:`_dot`, :func:`_sq`, :func:`_gram`) keep long products off
OpenBLAS's threads.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cellcal.core.depthcal.view import DepthcalView
from cellcal.devices.errors import ConfigError
from cellcal.devices.measurement import MeasurementModel
from cellcal.devices.pose import Pose
from cellcal.devices.systematic import SystematicError, field_terms

FloatArray = NDArray[np.float64]
#: Steps of the central differences for the mount's columns (rad, m).
_STEP_ANGLE = 1e-6
_STEP_LENGTH = 1e-6


def _dot(a: FloatArray, b: FloatArray) -> FloatArray:
    """``a @ b`` for a matrix and a vector (either way round) without BLAS: OpenBLAS threads a long
    matrix-vector or dot product and, on a busy machine, its spinning threads cost more than they save
    (measured: the whole fit twice the wall and CPU time with two threads than with one)."""
    out: FloatArray = np.einsum("ij,j->i", a, b) if a.ndim == 2 else np.einsum("i,ij->j", a, b)
    return out


def _sq(r: FloatArray) -> float:
    """``r @ r`` without BLAS (OpenBLAS threads a long dot product; see :func:`_dot`)."""
    return float(np.einsum("i,i->", r, r))


def _gram(a: FloatArray, b: FloatArray) -> FloatArray:
    """``a @ b.T`` of two row matrices ``(p, N)``, in slices of the columns small enough that OpenBLAS runs
    each on one thread (see :func:`_dot`; with the whole product the fit took 1.25x the CPU time with
    two threads than with one, with the slices the same)."""
    step = max(256, (1 << 17) // max(a.shape[0] * b.shape[0], 1))
    out = np.zeros((a.shape[0], b.shape[0]))
    for start in range(0, a.shape[1], step):
        out += a[:, start:start + step] @ b[:, start:start + step].T
    return out


@dataclass
class _Points:
    """The sampled points of a set of views, stacked."""

    ray: FloatArray            # (3, N) unit rays, camera frame, one row per axis
    u: FloatArray
    v: FloatArray
    measured: FloatArray       # native value, px or m
    basis: FloatArray          # (n_field, N) field monomials at the highest order, one row per monomial
    slices: list[slice]        # per view
    masks: list[NDArray[np.bool_]]   # per view, flat pixel mask of the sample
    shape: tuple[int, int]

    def index(self, views: Sequence[int]) -> NDArray[np.intp]:
        """Indices of the named views' points, in the order of ``views``."""
        if not views:
            return np.zeros(0, dtype=np.intp)
        return np.concatenate([np.arange(self.slices[i].start, self.slices[i].stop) for i in views])

    def subset(self, views: Sequence[int]) -> _Points:
        idx = self.index(views)
        slices, start = [], 0
        for i in views:
            n = self.slices[i].stop - self.slices[i].start
            slices.append(slice(start, start + n))
            start += n
        return _Points(self.ray[:, idx], self.u[idx], self.v[idx], self.measured[idx], self.basis[:, idx], slices,
                       [self.masks[i] for i in views], self.shape)

    def take(self, keep: NDArray[np.bool_]) -> _Points:
        """Only the points where ``keep`` (the views' masks follow)."""
        slices, masks, start = [], [], 0
        for s, m in zip(self.slices, self.masks, strict=True):
            k = keep[s]
            n = int(np.count_nonzero(k))
            slices.append(slice(start, start + n))
            start += n
            mm = m.copy()
            mm[np.flatnonzero(m)[~k]] = False
            masks.append(mm)
        return _Points(self.ray[:, keep], self.u[keep], self.v[keep], self.measured[keep], self.basis[:, keep], slices,
                       masks, self.shape)


@dataclass
class _Problem:
    """What one least-squares fit needs: the kind, the poses, which correction terms are free."""

    stereo: bool
    fb: float
    flanges: list[Pose]
    mount: Pose
    estimate_mount: bool
    n0: FloatArray             # the plane normal the tilt angles are measured from
    e1: FloatArray
    e2: FloatArray
    template: SystematicError  # kind, field order and wiggle period of the correction
    free: NDArray[np.intp]     # indices of the correction's vector that are fitted
    prior: FloatArray          # per free term, a weak prior's 1-sigma about 0 (keeps what a plan cannot see bounded)

    @property
    def n_geometry(self) -> int:
        return 3 + (6 if self.estimate_mount else 0)

    @property
    def n_field(self) -> int:
        return len(self.template.field_coeffs) if self.template.field_order else 0

    def normal(self, g: FloatArray) -> FloatArray:
        n = self.n0 + g[0] * self.e1 + g[1] * self.e2
        out: FloatArray = n / np.linalg.norm(n)
        return out

    def camera_poses(self, g: FloatArray) -> list[tuple[FloatArray, FloatArray]]:
        """Per view ``(R_base_camera, origin)`` for geometry ``g``."""
        mount = self.mount
        if self.estimate_mount:
            mount = mount @ Pose.from_xyz_rotvec(g[6:9], g[3:6])
        out = []
        for f in self.flanges:
            c = f @ mount
            out.append((c.rotation_matrix, np.asarray(c.translation, dtype=np.float64)))
        return out

    def true_values(self, g: FloatArray, pts: _Points, derivatives: bool = False
                    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray | None]:
        """True native value, range along the ray (m), cos of incidence and (``derivatives``) d(true)/d(g), per point.

        The derivatives are one row per geometry parameter, ``(n_geometry, N)``.

        The plane's columns are analytic (per view: the ray meets ``n · x = h`` at ``t = (h - n·o) / (n·R ray)``);
        the mount's, when estimated, central differences.
        """
        n = self.normal(g)
        h = float(g[2])
        size = pts.ray.shape[1]
        t = np.empty(size)
        nd_all = np.empty(size)
        poses = self.camera_poses(g)
        if derivatives:
            # d n / d g_k for the two tilts: the tangent's part normal to n over |n0 + g0 e1 + g1 e2|
            m = float(np.linalg.norm(self.n0 + g[0] * self.e1 + g[1] * self.e2))
            dn = [(e - n * float(n @ e)) / m for e in (self.e1, self.e2)]
            dt = np.empty((3, size))
        for s, (rot, origin) in zip(pts.slices, poses, strict=True):
            ray = pts.ray[:, s]
            nd = _dot(rot.T @ n, ray)               # n · (R ray)
            nd = np.minimum(nd, -1e-6)              # the ray must go towards the plane
            ts = (h - float(n @ origin)) / nd
            t[s] = ts
            nd_all[s] = nd
            if derivatives:
                for k in range(2):                  # dt/dg_k = -(o·dn_k + t ray·(Rᵀ dn_k)) / nd
                    dt[k, s] = -(float(origin @ dn[k]) + ts * _dot(rot.T @ dn[k], ray)) / nd
                dt[2, s] = 1.0 / nd
        clipped = t < 1e-4
        t = np.maximum(t, 1e-4)
        cos = -nd_all
        true = self.fb / (t * pts.ray[2]) if self.stereo else t
        if not derivatives:
            return true, t, cos, None
        jac = np.empty((self.n_geometry, size))    # one row per geometry parameter
        dtrue_dt = np.where(clipped, 0.0, -true / t if self.stereo else 1.0)
        np.multiply(dt, dtrue_dt, out=jac[:3])
        for k in range(3, self.n_geometry):
            step = _STEP_ANGLE if k < 6 else _STEP_LENGTH
            gp, gm = g.copy(), g.copy()
            gp[k] += step
            gm[k] -= step
            jac[k] = (self.true_values(gp, pts)[0] - self.true_values(gm, pts)[0]) / (2.0 * step)
        return true, t, cos, jac

    def vector(self, x: FloatArray) -> FloatArray:
        """The correction's full vector from the fitted parameters (fixed terms 0)."""
        c = np.zeros(len(self.template.names))
        c[self.free] = x[self.n_geometry:]
        return c

    def _wiggle(self, true: FloatArray) -> tuple[FloatArray, FloatArray]:
        phase = (2.0 * math.pi / self.template.wiggle_period_m) * true
        return np.cos(phase), np.sin(phase)

    def predicted(self, x: FloatArray, pts: _Points, true: FloatArray | None = None) -> FloatArray:
        """What the camera should measure (``distort`` of the true value), per point."""
        if true is None:
            true = self.true_values(x[:self.n_geometry], pts)[0]
        c = self.vector(x)
        out: FloatArray = true * (1.0 + c[0]) + c[1]
        head = 2
        if not self.stereo:
            head = 4
            if self.template.wiggle_period_m > 0.0 and (c[2] or c[3]):
                cos, sin = self._wiggle(true)
                out += c[2] * cos + c[3] * sin
        if c.size > head:
            out += _dot(c[head:], pts.basis[:c.size - head])
        return out

    def columns(self, x: FloatArray, pts: _Points) -> tuple[FloatArray, FloatArray]:
        """d(predicted)/d(fitted parameters), one row per parameter ``(n_geometry + n_free, N)``, and the prediction."""
        ng = self.n_geometry
        true, _, _, dtrue = self.true_values(x[:ng], pts, derivatives=True)
        assert dtrue is not None
        c = self.vector(x)
        tp = self.template
        slope = np.full(true.size, 1.0 + c[0])   # d(predicted)/d(true)
        full = [true, np.ones_like(true)]
        if not self.stereo:
            if tp.wiggle_period_m > 0.0:
                cos, sin = self._wiggle(true)
                slope += (2.0 * math.pi / tp.wiggle_period_m) * (c[3] * cos - c[2] * sin)
            else:
                cos = sin = np.zeros_like(true)
            full += [cos, sin]
        head = len(full)
        out = np.empty((ng + self.free.size, true.size))
        np.multiply(dtrue, slope, out=out[:ng])
        for k, j in enumerate(self.free):
            out[ng + k] = full[j] if j < head else pts.basis[j - head]
        return out, self.predicted(x, pts, true)


def _sample(views: Sequence[DepthcalView], model: MeasurementModel, order: int, max_points: int,
            seed: int) -> tuple[_Points, FloatArray]:
    """Up to ``max_points`` valid pixels per view (seeded), and their measured points (camera frame)."""
    rng = np.random.default_rng(seed)
    rays, us, vs, meas, masks, slices, points = [], [], [], [], [], [], []
    start = 0
    shape = (views[0].frame.intrinsics.height, views[0].frame.intrinsics.width)
    for k, view in enumerate(views):
        fr = view.frame
        intr = fr.intrinsics
        xyz32 = fr.xyz.reshape(-1, 3)
        dist32 = fr.distance.reshape(-1)
        z = xyz32[:, 2]
        ok = fr.valid.reshape(-1) & (z > 0) & np.isfinite(xyz32[:, 0]) & np.isfinite(xyz32[:, 1]) \
            & np.isfinite(z) & np.isfinite(dist32)
        idx = np.flatnonzero(ok)
        if idx.size < 50:
            raise ConfigError(f"view {view.name or k}: {idx.size} valid pixels, too few to see the plane",
                              key="depthcal.views")
        if idx.size > max_points:
            idx = np.sort(rng.choice(idx, size=max_points, replace=False))
        p = xyz32[idx].astype(np.float64)
        points.append(p)
        rays.append((p / np.linalg.norm(p, axis=1)[:, None]).T)
        rows, cols = np.divmod(idx, intr.width)
        us.append((cols - intr.cx) / (intr.width / 2.0))
        vs.append((rows - intr.cy) / (intr.height / 2.0))
        meas.append(model.fb_px_m / p[:, 2] if model.triangulating else dist32[idx].astype(np.float64))
        mask = np.zeros(ok.size, dtype=bool)
        mask[idx] = True
        masks.append(mask)
        slices.append(slice(start, start + idx.size))
        start += idx.size
    u_all, v_all = np.concatenate(us), np.concatenate(vs)
    return (_Points(np.concatenate(rays, axis=1), u_all, v_all, np.concatenate(meas), _monomials(u_all, v_all, order),
                    slices, masks, shape), np.concatenate(points))


def _monomials(u: FloatArray, v: FloatArray, order: int) -> FloatArray:
    """The field's monomials (:func:`~cellcal.devices.systematic.field_basis`'s, in its order) as rows ``(n, N)``,
    by products of powers (``**`` of arrays is several times slower)."""
    terms = field_terms(order)
    out = np.empty((len(terms), u.size))
    pu, pv = [np.ones_like(u)], [np.ones_like(v)]
    for _ in range(order):
        pu.append(pu[-1] * u)
        pv.append(pv[-1] * v)
    for k, (i, j) in enumerate(terms):
        np.multiply(pu[i], pv[j], out=out[k])
    return out


def _initial_plane(pts: _Points, points: FloatArray, flanges: Sequence[Pose], mount: Pose
                   ) -> tuple[FloatArray, float]:
    """A plane through the measured points in the base frame (trimmed least squares), normal towards the cameras."""
    base = []
    for s, flange in zip(pts.slices, flanges, strict=True):
        sample = points[s][:: max(1, (s.stop - s.start) // 2000)]
        base.append((flange @ mount).apply(sample))
    p = np.concatenate(base)
    keep = np.ones(len(p), dtype=bool)
    for _ in range(4):
        c = p[keep].mean(axis=0)
        q = p[keep] - c
        n = np.linalg.eigh(np.einsum("ij,ik->jk", q, q))[1][:, 0]   # the scatter's least direction
        r = _dot(p - c, n)
        mad = float(np.median(np.abs(r[keep] - np.median(r[keep])))) + 1e-9
        keep = np.abs(r - np.median(r[keep])) < 4.0 * 1.4826 * mad
    origin = np.asarray((flanges[0] @ mount).translation)
    if float((origin - c) @ n) < 0:
        n = -n
    return n, float(n @ c)


def _tangents(n: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Two unit vectors normal to ``n`` and to each other: the axes of the plane's tilt angles."""
    ref = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = ref - n * float(ref @ n)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(n, e1)


def _rms(a: FloatArray) -> float:
    """Root mean square (NaN when empty)."""
    return float(np.sqrt(np.mean(a * a))) if a.size else math.nan

