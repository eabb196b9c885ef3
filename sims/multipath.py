"""Multipath: light that reaches a pixel's surface point via a second surface (two bounces).

The camera's illuminator lights every surface the camera sees; each lit patch re-emits
(Lambertian) toward the other surfaces, which send part of it back to the camera over a
longer path. In a concave corner (a box standing on the table) the table near the box
and the box's sides light each other, and the range reads long there. The scene is
discretised as the camera sees it (Fuchs 2010): patches on a coarse pixel grid send, every
pixel receives; coplanar pairs exchange nothing, so a lone plane has no multipath.
Visibility between two patches (a third surface in between) is not checked. ADR 0014.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .scene import SURFACE_NONE
from .tof import ArtefactsConfig

FloatArray = NDArray[np.float64]
ComplexArray = NDArray[np.complex128]

#: Receivers x senders evaluated per block (bounds the temporary arrays).
_PAIRS_PER_BLOCK = 1_000_000
#: Incidence cosines are clipped here (grazing pixels are invalid anyway).
_MIN_COS = 0.05
#: A pixel is interpolated if its own surface's grid nodes carry this much bilinear weight,
#: else (next to another surface, where multipath changes fastest) evaluated exactly.
_MIN_NODE_WEIGHT = 0.5


@dataclass(frozen=True)
class SurfacePoints:
    """What the camera sees per pixel, flattened (H*W,).

    Attributes:
        points_m: Surface point, world frame, (N, 3), metres (any finite value where none).
        normals: Unit normal facing the camera, (N, 3).
        range_m: Radial distance from the camera, (N,), metres.
        cos_incidence: Cosine between the pixel's ray and the normal, (N,).
        reflectivity: Reflectivity of the surface, (N,).
        solid_angle_sr: Solid angle of the pixel, (N,), steradians.
        surface: Surface id, (N,) (``SURFACE_NONE`` where nothing is seen).
    """

    points_m: FloatArray
    normals: FloatArray
    range_m: FloatArray
    cos_incidence: FloatArray
    reflectivity: FloatArray
    solid_angle_sr: FloatArray
    surface: NDArray[np.int32]


@dataclass(frozen=True)
class Patches:
    """The lit surfaces as senders: the pixels of each surface within each ``g x g`` block, merged.

    Attributes:
        points_m: Centroid, world frame, (S, 3), metres.
        normals: Unit normal facing the camera, (S, 3).
        range_m: Mean radial distance from the camera, (S,), metres.
        power: ``rho / pi`` times the patch's solid angle: the light it re-emits per unit of
            the illuminator's intensity, (S,).
        area_m2: Area on its surface, (S,), square metres.
        surface: Surface id, (S,).
    """

    points_m: FloatArray
    normals: FloatArray
    range_m: FloatArray
    power: FloatArray
    area_m2: FloatArray
    surface: NDArray[np.int32]


def lit_patches(seen: SurfacePoints, shape: tuple[int, int], g: int) -> Patches:
    """Merge the seen pixels into patches, one per surface per ``g x g`` block (solid-angle weighted)."""
    w = shape[1]
    idx = np.nonzero(seen.surface != SURFACE_NONE)[0]
    v, u = np.divmod(idx, w)
    block = (v // g) * (-(-w // g)) + (u // g)
    n_ids = int(seen.surface.max()) + 2
    keys, first, inv = np.unique(block.astype(np.int64) * n_ids + seen.surface[idx] + 1, return_index=True,
                                 return_inverse=True)
    om = seen.solid_angle_sr[idx]
    tot = np.bincount(inv, om)

    def mean(values: FloatArray) -> FloatArray:  # solid-angle-weighted mean per patch
        out: FloatArray = np.bincount(inv, om * values) / tot
        return out

    pts = np.column_stack([mean(seen.points_m[idx, k]) for k in range(3)])
    t = seen.range_m[idx]
    # Area of a pixel on its surface: omega t^2 / cos.
    area = np.bincount(inv, om * t**2 / np.maximum(seen.cos_incidence[idx], _MIN_COS)).astype(np.float64)
    power = np.bincount(inv, om * seen.reflectivity[idx]) / math.pi
    return Patches(pts, seen.normals[idx[first]], mean(t), power, area,
                   (keys % n_ids - 1).astype(np.int32))


def second_bounce(seen: SurfacePoints, shape: tuple[int, int], config: ArtefactsConfig) -> ComplexArray:
    """Indirect return of every pixel relative to its direct return, as a phasor, (H*W,).

    With ``z`` the result, the pixel measures ``range + angle(1 + z) / k`` (``k`` =
    :attr:`ArtefactsConfig.wavenumber_rad_m`) with ``|1 + z|`` times its amplitude;
    ``z = 0`` where nothing is seen or the scene has one surface in view. Receivers are
    evaluated on the patch grid's centres and interpolated over each surface; pixels with
    no grid node of their own surface around them are evaluated one by one.
    """
    h, w = shape
    out = np.zeros(h * w, dtype=np.complex128)
    seen_ids = np.unique(seen.surface[seen.surface != SURFACE_NONE])
    if seen_ids.size < 2 or h < 2 or w < 2:
        return out
    g = max(1, round(w / config.multipath_patches))
    node_r = np.arange(g // 2, h, g)
    node_c = np.arange(g // 2, w, g)
    if node_r.size < 2 or node_c.size < 2:
        g, node_r, node_c = 1, np.arange(h), np.arange(w)
    patches = lit_patches(seen, shape, g)
    nodes = (node_r[:, None] * w + node_c[None, :]).ravel()
    z_nodes = _receive(seen, nodes, patches, config)
    z_pix, exact = _interpolate(seen.surface.reshape(h, w), z_nodes.reshape(node_r.size, node_c.size),
                                node_r, node_c)
    out[:] = z_pix
    todo = np.nonzero(exact)[0]
    if todo.size:
        out[todo] = _receive(seen, todo, patches, config)
    return out


def _receive(seen: SurfacePoints, receivers: NDArray[np.intp], patches: Patches, config: ArtefactsConfig
             ) -> ComplexArray:
    """Indirect phasor (relative to the direct return) at each receiver pixel from the patches."""
    out = np.zeros(receivers.size, dtype=np.complex128)
    r_ids = seen.surface[receivers]
    for sid in np.unique(r_ids[r_ids != SURFACE_NONE]):
        rec = np.nonzero(r_ids == sid)[0]
        snd = _facing(seen, receivers[rec], patches)
        if snd.size == 0:
            continue
        block = max(1, _PAIRS_PER_BLOCK // snd.size)
        for start in range(0, rec.size, block):
            part = rec[start:start + block]
            out[part] = _pairs(seen, receivers[part], patches, snd, config)
    return out


def _facing(seen: SurfacePoints, rec: NDArray[np.intp], patches: Patches) -> NDArray[np.intp]:
    """Indices of the patches on surfaces that face the receivers (all on one planar surface) and that they face.

    Surfaces are planar: a surface exchanges light with the receivers' surface only if
    part of it lies in front of the receivers' plane and some receiver in front of its
    plane; the receivers' own surface exchanges nothing.
    """
    n_r, p_r = seen.normals[rec[0]], seen.points_m[rec[0]]
    keep = []
    for qid in np.unique(patches.surface):
        if qid == seen.surface[rec[0]]:
            continue
        snd = np.nonzero(patches.surface == qid)[0]
        n_q, p_q = patches.normals[snd[0]], patches.points_m[snd[0]]
        if np.max((patches.points_m[snd] - p_r) @ n_r) > 0 and np.max((seen.points_m[rec] - p_q) @ n_q) > 0:
            keep.append(snd)
    return np.concatenate(keep) if keep else np.empty(0, dtype=np.intp)


def _pairs(seen: SurfacePoints, rec: NDArray[np.intp], patches: Patches, snd: NDArray[np.intp],
           config: ArtefactsConfig) -> ComplexArray:
    """Sum over patches of (indirect / direct irradiance) x phase of the extra path, per receiver.

    Lambertian radiometry: a patch re-emits ``power`` x the illuminator's intensity; the
    receiver's direct irradiance is ``cos / t**2`` of it.
    """
    p, n_p = seen.points_m[rec], seen.normals[rec]
    q, n_q = patches.points_m[snd], patches.normals[snd]
    # Receiver -> patch vectors through dot products only: (m, S) matrices, no (m, S, 3) array.
    r2 = np.maximum(np.einsum("ij,ij->i", p, p)[:, None] + np.einsum("ij,ij->i", q, q)[None, :] - 2.0 * (p @ q.T),
                    1e-12)
    r = np.sqrt(r2)
    # cos at the receiver (toward the patch) and at the patch (toward the receiver), 0 when facing away.
    cos_p = np.clip((n_p @ q.T - np.einsum("ij,ij->i", n_p, p)[:, None]) / r, 0.0, 1.0)
    cos_q = np.clip((p @ n_q.T - np.einsum("ij,ij->i", n_q, q)[None, :]) / r, 0.0, 1.0)
    t_p = seen.range_m[rec]
    # Indirect / direct irradiance; the disc term area / pi keeps a patch next to the
    # receiver finite (the on-axis disc form factor).
    ratio = patches.power[snd][None, :] * cos_p * cos_q / (r2 + patches.area_m2[snd][None, :] / math.pi)
    ratio *= (t_p**2 / np.maximum(seen.cos_incidence[rec], _MIN_COS))[:, None]
    # Phase of the extra path (camera -> patch -> receiver -> camera vs camera -> receiver -> camera).
    phase = (0.5 * config.wavenumber_rad_m) * (patches.range_m[snd][None, :] + r - t_p[:, None])
    z: ComplexArray = (ratio * np.cos(phase)).sum(axis=1) + 1j * (ratio * np.sin(phase)).sum(axis=1)
    return z


def _interpolate(surface: NDArray[np.int32], z_nodes: ComplexArray, node_r: NDArray[np.intp],
                 node_c: NDArray[np.intp]) -> tuple[ComplexArray, NDArray[np.bool_]]:
    """Bilinear interpolation of the node phasors over the pixels, using only nodes on the pixel's surface.

    Returns:
        The interpolated phasors (H*W,) and the pixels (H*W,) with too little weight of
        nodes on their own surface around them (to be evaluated exactly).
    """
    h, w = surface.shape
    # Cell of each row / column: nodes (i, i + 1) x (j, j + 1); outside the lattice the nearest cell, clamped.
    rows, cols = np.arange(h), np.arange(w)
    i = np.clip((rows - node_r[0]) // (node_r[1] - node_r[0]), 0, node_r.size - 2)
    j = np.clip((cols - node_c[0]) // (node_c[1] - node_c[0]), 0, node_c.size - 2)
    fv = np.clip((rows - node_r[i]) / (node_r[i + 1] - node_r[i]), 0.0, 1.0)[:, None]
    fu = np.clip((cols - node_c[j]) / (node_c[j + 1] - node_c[j]), 0.0, 1.0)[None, :]
    s_nodes = surface[node_r[:, None], node_c[None, :]]
    re = np.zeros((h, w))
    im = np.zeros((h, w))
    den = np.zeros((h, w))
    for di, dj in ((0, 0), (0, 1), (1, 0), (1, 1)):
        wt = (fv if di else 1.0 - fv) * (fu if dj else 1.0 - fu)
        ii, jj = (i + di)[:, None], (j + dj)[None, :]
        wt = np.where(s_nodes[ii, jj] == surface, wt, 0.0)  # only nodes on the pixel's own surface
        zc = z_nodes[ii, jj]
        re += wt * zc.real
        im += wt * zc.imag
        den += wt
    seen = surface != SURFACE_NONE
    ok = den >= _MIN_NODE_WEIGHT
    safe = np.where(ok, den, 1.0)
    z = np.where(ok & seen, (re + 1j * im) / safe, 0.0)
    return z.ravel(), (seen & ~ok).ravel()
