"""Full-frame fit kernels: the fast forms (issue 18) give what the direct computations give."""

from __future__ import annotations

import numpy as np
import pytest
from tof_frames import ToFSetup, make_frame, scattered_boxes, with_

from cellcal.core.methods.fullframe import fit_full_frame
from cellcal.core.methods.fullframe.flatness import _moments, grid_cells
from cellcal.core.methods.fullframe.passes import Model, Scratch, basis, final_pass
from cellcal.core.methods.fullframe.points import fixed_subsample
from cellcal.core.methods.fullframe.range_space import _best_quantile


def test_best_quantile_picks_the_row_a_full_partition_picks() -> None:
    """Random matrices, with ties and duplicated rows: the same row (first on ties) as partitioning every row."""
    rng = np.random.default_rng(3)
    for trial in range(400):
        rows, cols = int(rng.integers(1, 100)), int(rng.integers(3, 600))
        res = np.abs(rng.standard_normal((rows, cols))).astype(np.float32) * rng.random((rows, 1)).astype(np.float32)
        if trial % 3 == 0:
            res = np.round(res * 4) / 4                       # many equal values
        if trial % 5 == 0:
            res[-1] = res[0]                                  # a tie between rows: the first wins
        h = min(max(int(rng.random() * cols), 3), cols)
        full = np.partition(res, h - 1, axis=1)[:, h - 1]
        assert _best_quantile(res, h) == int(np.argmin(full)), trial


def test_moments_by_runs_equal_a_bincount_per_column() -> None:
    """Cell sums of the local-plane products over pixel-ordered points equal a bincount of each product."""
    rng = np.random.default_rng(4)
    shape, grid = (172, 224), (4, 4)
    pixels = np.sort(rng.choice(shape[0] * shape[1], 20_000, replace=False))
    cell = grid_cells(pixels, shape, grid)
    assert np.array_equal(cell, (pixels // 224) * 4 // 172 * 4 + (pixels % 224) * 4 // 224)
    u, v, w = rng.standard_normal((3, pixels.size))
    wt = rng.random(pixels.size) + 0.1
    got = _moments(np.stack([u, v, w]), wt, cell, 16)
    cols = [np.ones_like(wt), wt, wt * u, wt * v, wt * u * u, wt * u * v, wt * v * v, wt * w, wt * u * w, wt * v * w]
    want = np.array([np.bincount(cell, weights=c, minlength=16) for c in cols])
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-9)


def test_a_reused_scratch_gives_the_pass_a_fresh_one_gives() -> None:
    """Two passes on one scratch (as in the fit) give bit-identical sums and inliers to fresh buffers."""
    st = ToFSetup(quantisation_m=0.001)
    frame = make_frame(st, seed=2)
    p = np.ascontiguousarray(frame.xyz[frame.valid].T)
    dm = np.ascontiguousarray(frame.distance[frame.valid])
    truth = st.truth()
    n, offset = truth.normal, truth.offset_m
    e1, e2 = basis(n)
    scratch = Scratch(dm.size)
    thr = 3.0 * 0.0032                                        # 3 sigma of the noise at 1 m (whitened units)
    for answer in (False, True):
        a = final_pass(p, dm, n, e1, e2, offset, thr, Model(True, 1.5), None, answer=answer, scratch=scratch)
        b = final_pass(p, dm, n, e1, e2, offset, thr, Model(True, 1.5), None, answer=answer)
        assert np.array_equal(a.inliers, b.inliers) and a.n_inliers > 0.9 * dm.size
        for x, y in ((a.step, b.step), (a.hessian, b.hessian), (a.meat, b.meat), (a.radial[0], b.radial[0])):
            assert np.array_equal(x, y)
        assert (a.z2_sum, a.ortho2_sum, a.model_ortho2_sum) == (b.z2_sum, b.ortho2_sum, b.model_ortho2_sum)


def test_the_cached_subsample_cannot_be_changed_by_a_caller() -> None:
    idx = fixed_subsample(50_000, 1024)
    assert idx is fixed_subsample(50_000, 1024) and idx.size == 1024
    with pytest.raises(ValueError):
        idx[0] = 1


def test_repeated_fits_of_a_cluttered_frame_are_identical() -> None:
    """Caches and reused buffers leave nothing behind: the same frame fitted twice gives the same answer."""
    st = with_(ToFSetup(flying=0.5), boxes=scattered_boxes(0.4, 7))
    frame = make_frame(st, seed=1)
    a, b = fit_full_frame(frame), fit_full_frame(frame)
    assert np.array_equal(a.inlier_mask, b.inlier_mask) and a.n_mixed == b.n_mixed
    assert (a.tilt_x_rad, a.height_m, a.flatness_m, a.height_sigma_m) == (b.tilt_x_rad, b.height_m, b.flatness_m,
                                                                          b.height_sigma_m)
