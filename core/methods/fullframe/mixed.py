"""Mixed pixels found where they are: rings around depth edges whose residuals are biased.

A pixel whose footprint (or the optics' spill) straddles a depth edge returns a mix of
both surfaces. On the plane's side of an edge that mix stays within the noise band but
is biased toward the other surface, and with many pixels the bias exceeds the interval.
Method and rationale: docs/adr/0007-full-frame-fit.md ("Mixed pixels").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

BoolArray = NDArray[np.bool_]
F32 = NDArray[np.float32]

_K3 = np.ones((3, 3), np.uint8)
#: Pixels beyond every examined ring needed for their mean to be the reference.
MIN_REFERENCE = 1000
#: A band of rings matters when its residuals could move the fit by this many of its standard errors.
RELEVANT_PULL = 0.1
#: Points binned into rings per block.
CHUNK = 1 << 16


@dataclass
class EdgeReport:
    """What the last clean-up dropped.

    Attributes:
        margin_px: Rings (chessboard pixels) dropped around outlier patches.
        floor_px: Rings dropped around any patch (outliers or invalid), whatever the data say.
        n_dropped: Inliers dropped.
    """

    margin_px: int = 0
    floor_px: int = 0
    n_dropped: int = 0


def _open(mask: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """3x3 opening: solid patches stay, isolated pixels and thin lines go."""
    return np.asarray(cv2.morphologyEx(mask, cv2.MORPH_OPEN, _K3), dtype=np.uint8)


def _near(patches: NDArray[np.uint8], reach: int) -> NDArray[np.uint8]:
    """1 where a patch pixel lies within ``reach`` pixels (chessboard distance), else 0.

    The same as ``_distance(patches) <= reach``, by a dilation with a square (separable,
    several times faster than the distance transform).
    """
    kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * reach + 1, 2 * reach + 1))
    return np.asarray(cv2.dilate(patches, kernel), dtype=np.uint8)


def _distance(patches: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """Chessboard distance (pixels, saturating at 255) of every pixel to the nearest patch pixel."""
    if not patches.any():
        return np.full(patches.shape, 255, np.uint8)
    out = cv2.distanceTransform(np.uint8(1) - patches, cv2.DIST_C, 3, dstType=cv2.CV_8U)
    return np.asarray(out, dtype=np.uint8)


def _ring_sums(ring: NDArray[np.uint8], inliers: BoolArray, z: F32, n_bins: int
               ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Sum of ``z`` and count of the inliers in each ring (bin 0: every other point).

    In blocks of ``CHUNK`` points: the bin index array ``bincount`` wants (intp: other
    index types are cast on every call, 3x slower with weights) and its float64 copy of
    the weights then stay block-sized (16 B per point less at the peak of the fit) and in cache.
    """
    sums = np.zeros(n_bins)
    counts = np.zeros(n_bins)
    for s in range(0, ring.size, CHUNK):
        bins = np.multiply(ring[s:s + CHUNK], inliers[s:s + CHUNK], dtype=np.uint8).astype(np.intp)
        sums += np.bincount(bins, weights=z[s:s + CHUNK], minlength=n_bins)
        counts += np.bincount(bins, minlength=n_bins)
    return sums, counts


class EdgeClean:
    """``(inliers, z) -> keep``: drops inliers near solid patches of outliers or invalid pixels.

    Per frame (pooled order of points), outliers and invalid pixels are opened with a
    3x3 square (isolated ones go: noise tails and random flying pixels do not mark an
    edge). Every inlier within ``floor_px`` of a patch is dropped. Around the outlier
    patches, bands of ``floor_px`` rings beyond the floor (pooled over the frames) are
    dropped while the sum of their normalised residuals exceeds ``ring_sigma`` standard
    errors: the data say how far the mixing reaches, which scales with the resolution
    (the optics' spill is an angle) and with the height of the jump over the noise.

    Args:
        masks: Per frame, the flat (H*W,) mask of the pixels that became points.
        shape: ``(H, W)``.
        floor_px: Rings always dropped.
        max_px: Farthest ring examined.
        ring_sigma: Significance of a biased ring, standard errors.
        scale: Robust scale of the normalised residuals (z / scale is standard normal).
        region: Flat (H*W,) region of interest; pixels outside it are neither invalid nor
            outliers (its border is not a depth edge). None: the whole image.
    """

    def __init__(self, masks: list[BoolArray], shape: tuple[int, int], floor_px: int, max_px: int,
                 ring_sigma: float, scale: float = 1.0, region: BoolArray | None = None) -> None:
        self.masks = masks
        self.shape = shape
        self.floor_px = floor_px
        self.max_px = min(max(max_px, floor_px), 250)
        self.ring_sigma = ring_sigma
        self.scale = scale
        self.report = EdgeReport(floor_px=floor_px)
        self.invalid = [(~m if region is None else region & ~m).astype(np.uint8) for m in masks]

    def margin_keep(self) -> int:
        """How many points lie farther than ``floor_px`` from the solid patches of invalid pixels."""
        h, w = self.shape
        return sum(int(np.count_nonzero(_near(_open(inv.reshape(h, w)), self.floor_px).reshape(-1)[m] == 0))
                   for m, inv in zip(self.masks, self.invalid, strict=True))

    def __call__(self, inliers: BoolArray, z: F32) -> BoolArray:
        h, w = self.shape
        cap = self.max_px + 1                      # rings beyond max_px: the reference bin
        ring = np.empty(inliers.size, dtype=np.uint8)
        start = 0
        for m, invalid in zip(self.masks, self.invalid, strict=True):   # per frame, in image space
            k = int(np.count_nonzero(m))
            flat = np.zeros(h * w, dtype=np.uint8)
            flat[m] = ~inliers[start:start + k]    # boolean scatter: 4x faster than by index at 98 % valid
            outlier = flat.reshape(h, w)
            # ring = distance to the outlier patches (capped), 0 within the floor of any patch:
            # outliers and invalid pixels together there (a wall seen at grazing incidence is both)
            code = np.minimum(_distance(_open(outlier)), np.uint8(cap))
            far = np.subtract(np.uint8(1), _near(_open(outlier | invalid.reshape(h, w)), self.floor_px))
            code *= far                             # 0 within the floor (multiply: no boolean-mask pass)
            ring[start:start + k] = code.reshape(-1)[m]
            start += k
        sums, counts = _ring_sums(ring, inliers, z, cap + 1)
        sums[0] = counts[0] = 0.0
        margin = self._margin(sums, counts, float(np.count_nonzero(inliers)))
        keep: BoolArray = ring > margin
        self.report = EdgeReport(margin, self.floor_px, int(np.count_nonzero(inliers & ~keep)))
        return keep

    def _margin(self, sums: NDArray[np.float64], counts: NDArray[np.float64], n_total: float) -> int:
        """The outer edge of an unbroken run of biased bands of rings beyond the floor.

        Bands are ``floor_px`` rings wide (the mixing reaches farther in pixels at a higher
        resolution; a band holds enough pixels to show it). A band is biased when the sum
        of its residuals is significant (``ring_sigma`` standard errors) and large enough
        to move the fit by ``RELEVANT_PULL`` of its own standard error, both measured
        against the mean residual of the pixels beyond every band (contamination pulls the
        fit itself, which shifts every residual).
        """
        width = max(self.floor_px, 1)
        margin = self.floor_px
        n_ref, s_ref = float(counts[-1]), float(sums[-1])
        if n_ref < MIN_REFERENCE:                  # few pixels far from every patch: all of them
            n_ref, s_ref = float(counts.sum()), float(sums.sum())
        mean_ref = s_ref / max(n_ref, 1.0)         # residual level of the clean plane (the fit may be pulled)
        while margin + width <= self.max_px:
            band = slice(margin + 1, margin + width + 1)
            n = float(counts[band].sum())
            excess = abs(float(sums[band].sum()) - n * mean_ref)
            noise = math.sqrt(n * (1.0 + n / max(n_ref, 1.0)))
            if n < 1 or excess <= self.scale * max(self.ring_sigma * noise, RELEVANT_PULL * math.sqrt(n_total)):
                break
            margin += width
        return margin
