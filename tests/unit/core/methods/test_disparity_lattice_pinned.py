"""The lattice of depth levels (``disparity_lattice``) pinned on constructed depths (issue #32).

Depths ``f·B/(k·q)`` on chosen levels ``k``: how many levels and how many depths on each it needs, how close to
the lattice they must sit (both sides of the tenth-of-a-step limit), an exact pitch, levels with one reciprocal,
float32 depths, missing depths. The camera is tests/support/disparity_camera.py.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from disparity_camera import FB, V_TRUE, H, W, normalised

from cellcal.core.methods.fullframe.disparity import disparity_lattice


# ---------------------------------------------------------------------- the lattice of depth levels
def lattice_depths(levels_k: np.ndarray, counts: np.ndarray, fb_over_q: float) -> np.ndarray:
    return np.repeat(fb_over_q / levels_k, counts)


def test_lattice_needs_four_populated_levels_of_sixteen_depths() -> None:
    fbq = 33.0 * 8                                               # f·B/q, px·m: 1/8 px steps
    k = np.array([300.0, 301.0, 303.0, 306.0])
    assert disparity_lattice(lattice_depths(k, np.full(4, 16), fbq)) == pytest.approx(fbq, rel=1e-4)
    assert disparity_lattice(lattice_depths(k, np.array([16, 16, 16, 15]), fbq)) is None    # one level too thin
    assert disparity_lattice(lattice_depths(k[:3], np.full(3, 40), fbq)) is None             # three levels
    assert disparity_lattice(lattice_depths(k[:3], np.full(3, 40), fbq), min_levels=3) == pytest.approx(fbq,
                                                                                                         rel=1e-4)


def test_lattice_populated_share_is_two_per_mille() -> None:
    """20 000 depths: a level needs 40 of them (0.2 %); 39 leaves three levels, too few."""
    fbq = 33.0
    k = np.array([40.0, 41.0, 42.0, 44.0])
    filler = np.full(20_000 - 40 * 3 - 40, 0.5) + np.random.default_rng(3).uniform(0, 1e-3, 20_000 - 160)
    counts_ok = np.array([40, 40, 40, 40])
    z = np.concatenate([lattice_depths(k, counts_ok, fbq), filler])
    assert disparity_lattice(z) == pytest.approx(fbq, rel=1e-4)
    z = np.concatenate([lattice_depths(k, np.array([40, 40, 40, 39]), fbq), filler, [0.5]])
    assert disparity_lattice(z) is None


#: 40 levels: two adjacent ones on the lattice (the smallest gap, one step), 38 every other step alternately
#: ``±j`` steps off it; RMS ``j·sqrt(38/40)``, so the tenth-of-a-step limit is at ``j = 0.1·sqrt(40/38)``.
J_LIMIT = 0.1 * math.sqrt(40.0 / 38.0)


@pytest.mark.parametrize(("jitter", "found"), [(0.97 * J_LIMIT, True), (1.03 * J_LIMIT, False)])
def test_lattice_levels_must_sit_within_a_tenth_of_a_step(jitter: float, found: bool) -> None:
    fbq = 25.0
    k_off = 63.0 + 2.0 * np.arange(38)
    k_off += jitter * np.where(np.arange(38) % 2 == 0, 1.0, -1.0)   # alternating: no change of scale absorbs it
    k = np.concatenate([[60.0, 61.0], k_off])
    out = disparity_lattice(lattice_depths(k, np.full(k.size, 20), fbq))
    assert (out is not None) == found
    if found:
        assert out == pytest.approx(fbq, rel=1e-3)


def test_lattice_pitch_is_exact_when_two_levels_are_adjacent() -> None:
    """Levels exactly on the lattice, two of them one step apart: the first guess is the answer, to rounding."""
    fbq = 33.0 * 32                                              # 1/32 px steps
    z = lattice_depths(np.array([1400.0, 1401.0, 1404.0, 1409.0, 1416.0]), np.full(5, 20), fbq)
    assert disparity_lattice(z) == pytest.approx(fbq, rel=1e-9)


def test_lattice_of_levels_with_one_reciprocal_is_none() -> None:
    """Two depths one float apart with the same ``1/Z``: a gap of zero tells no pitch."""
    z0 = 0.70814
    assert 1.0 / z0 == 1.0 / np.nextafter(z0, 2.0)
    z = np.repeat([z0, np.nextafter(z0, 2.0), 0.69, 0.67, 0.65], 20)
    assert disparity_lattice(z) is None


@pytest.mark.parametrize("bits", [0, 2, 3])
def test_lattice_of_float32_depths_is_that_of_their_values(bits: int) -> None:
    """A camera's float32 depths give the answer of the same values in float64 (the pitch needs the precision)."""
    rng = np.random.default_rng(60 + bits)
    pix = np.arange(H * W)
    x, y = normalised(pix)
    d = np.round((V_TRUE[0] * x + V_TRUE[1] * y + V_TRUE[2] + 0.3 * rng.standard_normal(pix.size)) * 2**bits)
    z32 = (FB / (d / 2**bits)).astype(np.float32)
    out = disparity_lattice(z32)
    assert out == disparity_lattice(z32.astype(np.float64))
    assert out == pytest.approx(FB * 2**bits, rel=1e-4)


def test_lattice_ignores_missing_depths() -> None:
    fbq = 33.0
    z = lattice_depths(np.array([40.0, 41.0, 42.0, 43.0, 45.0]), np.full(5, 30), fbq)
    holes = np.concatenate([z, np.zeros(500), np.full(300, np.nan), np.full(200, -1.0), np.full(100, np.inf)])
    assert disparity_lattice(holes) == pytest.approx(disparity_lattice(z), rel=1e-15)
    assert disparity_lattice(np.zeros(100)) is None
    assert disparity_lattice(np.full(10, np.nan)) is None
    out = disparity_lattice(z.astype(np.float32).reshape(5, 30))
    assert type(out) is float and out == pytest.approx(fbq, rel=1e-4)
