"""Comparisons of floating-point results that hold on any CPU and BLAS."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike


def assert_covariance_close(actual: ArrayLike, desired: ArrayLike, rtol: float) -> None:
    """Assert two covariance matrices agree to ``rtol`` of each entry's own scale ``sqrt(C_ii C_jj)``.

    An off-diagonal entry that is nearly zero next to its variances (a correlation of 1e-7, say) is
    the difference of large products: its last bits, and so its relative error, change with the BLAS
    kernel. Measured against ``sqrt(C_ii C_jj)`` the tolerance is one on the correlation and the
    relative variance alike. A zero variance (a parameter held exact) must be zero in both.
    """
    a = np.asarray(actual, dtype=np.float64)
    d = np.asarray(desired, dtype=np.float64)
    assert a.shape == d.shape, f"shapes differ: {a.shape} vs {d.shape}"
    scale = np.sqrt(np.abs(np.outer(np.diag(d), np.diag(d))))
    err = np.abs(a - d)
    bad = err > rtol * scale
    if np.any(bad):
        i, j = np.argwhere(bad)[0]
        raise AssertionError(f"{int(bad.sum())} of {a.size} entries differ by more than {rtol:g} of "
                             f"sqrt(C_ii C_jj): e.g. [{i}, {j}] {a[i, j]!r} vs {d[i, j]!r} (scale {scale[i, j]:.3g})")
