"""Mixed ("flying") pixels: a pixel whose footprint straddles a depth edge returns a blend.

A pixel's footprint is the pixel (1 px square) blurred by the lens (Gaussian,
``psf_sigma_px``, out to 2.5 sigma). Near an edge, rays are cast on a sub-pixel lattice
(``supersampling`` per pixel width, shared by neighbouring pixels); each pixel sums the
returns under its footprint, weighted by it, as phasors (amplitude, phase ``4 pi f d / c``),
which is what a continuous-wave ToF pixel measures. Its range lies between the depths,
weighted by their amplitudes; pixels a little farther from the edge get a little of the
other surface (the blur's tail). ADR 0014.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .scene import SURFACE_NONE, Scene
from .tof import ArtefactsConfig, relative_amplitude

FloatArray = NDArray[np.float64]

#: The footprint reaches this many blur sigmas beyond the pixel (the tail left out: < 0.2 %).
_PSF_REACH_SIGMAS = 2.5


@dataclass(frozen=True)
class PixelReturns:
    """Per-pixel returns of a frame, flattened (H*W,).

    Attributes:
        range_m: Effective radial distance of the return, metres (NaN: no return).
        amplitude: Relative amplitude of the return (0: none).
    """

    range_m: FloatArray
    amplitude: FloatArray


def footprint(psf_sigma_px: float, samples_per_px: int) -> FloatArray:
    """Weights of a pixel's footprint along one image axis at offsets ``k / samples_per_px`` px.

    The pixel's response is a 1 px box blurred by a Gaussian of ``psf_sigma_px``:
    ``w(x) = Phi((x + 0.5) / s) - Phi((x - 0.5) / s)``, for ``|x| <= 0.5 + 2.5 s``,
    ``k = -K .. K``; the weights sum to 1. The 2-D footprint is the outer product.
    """
    half = 0.5 + _PSF_REACH_SIGMAS * psf_sigma_px
    reach = max(0, math.floor(half * samples_per_px - 1e-9))
    off = np.arange(-reach, reach + 1) / samples_per_px
    if psf_sigma_px <= 0:
        w = np.ones(off.size)
    else:
        phi = np.vectorize(lambda v: 0.5 * (1.0 + math.erf(v / math.sqrt(2.0))))
        w = phi((off + 0.5) / psf_sigma_px) - phi((off - 0.5) / psf_sigma_px)
    out: FloatArray = w / w.sum()
    return out


def edge_pixels(surface: NDArray[np.int32], radius: int = 1) -> NDArray[np.bool_]:
    """Pixels that hit a surface and have another surface (or none) within ``radius`` px, (H, W)."""
    h, w = surface.shape
    padded = np.pad(surface, radius, mode="edge")  # the image border is no edge
    out = np.zeros((h, w), dtype=bool)
    for dr in range(-radius, radius + 1):
        for dc in range(-radius, radius + 1):
            if dr or dc:
                out |= padded[radius + dr:radius + dr + h, radius + dc:radius + dc + w] != surface
    out &= surface != SURFACE_NONE
    return out


def lattice_rays(rays: FloatArray, lat_v: NDArray[np.intp], lat_u: NDArray[np.intp], samples_per_px: int
                 ) -> FloatArray:
    """Unit rays through sub-pixel lattice points ``(lat_v, lat_u) / samples_per_px`` px, (N, 3).

    First-order from the nearest pixel-centre ray (central differences, one-sided at the
    image border): over half a pixel the lens distortion is linear to well below 1e-5 rad.

    Args:
        rays: Pixel-centre unit rays, (H, W, 3) (H, W >= 2), in any frame.
        lat_v, lat_u: Lattice coordinates, (N,) (pixel centre ``(v, u)`` is ``(v s, u s)``).
        samples_per_px: Lattice points per pixel width ``s``.
    """
    h, w = rays.shape[:2]
    rows = np.clip(np.rint(lat_v / samples_per_px).astype(np.intp), 0, h - 1)
    cols = np.clip(np.rint(lat_u / samples_per_px).astype(np.intp), 0, w - 1)
    dv = (lat_v / samples_per_px - rows)[:, None]
    du = (lat_u / samples_per_px - cols)[:, None]
    r0, r1 = np.maximum(rows - 1, 0), np.minimum(rows + 1, h - 1)
    c0, c1 = np.maximum(cols - 1, 0), np.minimum(cols + 1, w - 1)
    # ray + dv * (d ray / d row) + du * (d ray / d column)
    out = (rays[rows, cols] + dv * (rays[r1, cols] - rays[r0, cols]) / (r1 - r0)[:, None]
           + du * (rays[rows, c1] - rays[rows, c0]) / (c1 - c0)[:, None])
    out /= np.sqrt(np.einsum("ij,ij->i", out, out))[:, None]
    result: FloatArray = out
    return result


def _footprint_lattice(rows: NDArray[np.intp], cols: NDArray[np.intp], s: int, reach: int
                       ) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.intp]]:
    """The lattice points under the pixels' footprints, each once, and which of them each pixel sees.

    Returns:
        Lattice coordinates ``(lat_v, lat_u)`` of the distinct points, (N,) each, and their
        indices per pixel and footprint sample, (M, (2 reach + 1)**2).
    """
    steps = np.arange(-reach, reach + 1)
    v0, u0 = int(rows.min()) * s - reach, int(cols.min()) * s - reach
    width = (int(cols.max()) - int(cols.min())) * s + 2 * reach + 1
    height = (int(rows.max()) - int(rows.min())) * s + 2 * reach + 1
    # Flat index of every footprint sample in the lattice's bounding box; mark, number, look up.
    lv = (rows[:, None] * s + steps[None, :] - v0)[:, :, None]
    lu = (cols[:, None] * s + steps[None, :] - u0)[:, None, :]
    flat = (lv * width + lu).reshape(rows.size, -1)
    mark = np.zeros(height * width, dtype=bool)
    mark[flat.ravel()] = True
    number = np.cumsum(mark, dtype=np.int64) - 1
    points = np.flatnonzero(mark)
    return points // width + v0, points % width + u0, number[flat]


def blend_edges(returns: PixelReturns, scene: Scene, origin: FloatArray, rays: FloatArray,
                surface: NDArray[np.int32], config: ArtefactsConfig) -> PixelReturns:
    """The returns with every pixel near an edge replaced by the phasor blend over its footprint.

    Args:
        returns: Centre-ray returns, (H*W,).
        scene: The scene (ray casting, reflectivities).
        origin: Camera centre, world frame, metres.
        rays: Pixel-centre unit rays, world frame, (H, W, 3), finite.
        surface: Surface id per pixel, (H, W).
        config: Artefact settings (lens blur, supersampling, modulation frequency).
    """
    h, w = surface.shape
    s = config.supersampling
    weights = footprint(config.psf_sigma_px, s)
    reach = (weights.size - 1) // 2  # lattice steps from the centre to the footprint's edge
    rows, cols = np.nonzero(edge_pixels(surface, max(1, math.ceil(reach / s))))
    if rows.size == 0 or h < 2 or w < 2:
        return returns
    lat_v, lat_u, inv = _footprint_lattice(rows, cols, s, reach)
    dirs = lattice_rays(rays, lat_v, lat_u, s)
    t, normal, hit, surf = scene.raycast_surfaces(origin, dirs)
    cos = np.where(hit, -np.einsum("ij,ij->i", normal, dirs), 0.0)
    amp = np.where(hit, relative_amplitude(np.where(hit, t, 1.0), cos, scene.reflectivity(surf)), 0.0)
    # Phasors relative to each pixel's centre range (no phase wrapping), summed over its footprint.
    k = config.wavenumber_rad_m
    idx = rows * w + cols
    t_c = returns.range_m[idx]
    dphi = np.where(amp[inv] > 0, k * (np.where(hit, t, 0.0)[inv] - t_c[:, None]), 0.0)
    wa = amp[inv] * np.outer(weights, weights).ravel()[None, :]
    z = (wa * np.cos(dphi)).sum(axis=1) + 1j * (wa * np.sin(dphi)).sum(axis=1)
    rng = returns.range_m.copy()
    out_amp = returns.amplitude.copy()
    rng[idx] = t_c + np.angle(z) / k
    out_amp[idx] = np.abs(z)
    return PixelReturns(rng, out_amp)
