"""The robust start of the full-frame fit: the best triplet plane, a scale from below, reweighting passes.

The answer must not depend on which triplets were drawn (ADR 0007, "Robustness"): the
triplets are scored on a fixed subsample, and the reweighting passes start with a scale
below the noise and grow it to the smallest self-consistent one (the contaminated,
wider fixed points of hard rejection lie above it).
"""

from __future__ import annotations

import functools
import math
from statistics import NormalDist  # not scipy.special: its 0.2 s import is off calibrate's start-up

import numpy as np
from numpy.typing import NDArray

from cellcal.core.geometry.planes import Plane
from cellcal.core.methods.fullframe.expected import ExpectedPlane
from cellcal.core.methods.fullframe.passes import Cutoff, Model, Pass, Scratch, basis, gn_pass, step_plane, truncation
from cellcal.core.methods.fullframe.settings import FullFrameSettings
from cellcal.devices.errors import CalibrationError, CalibrationQualityError
from cellcal.devices.readable import quantity_pair

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
F32 = NDArray[np.float32]

#: Seed of the fixed subsample's jitter (and of the triplets when ``seed`` is None).
FIXED_SEED = 0x5EED
#: Points whose second principal variance is below this fraction of the first lie along a line.
LINE_RATIO = 1e-4
#: With an expected plane, this many times ``hypotheses`` triplets are drawn (only those within
#: its tolerances are scored: a plane holding a third of the points gives 1 in 27 triplets).
EXPECTED_DRAWS = 8


@functools.lru_cache(maxsize=16)
def fixed_subsample(n_points: int, limit: int) -> NDArray[np.intp]:
    """Indices of at most ``limit`` points, one at a fixed random place in each of ``limit`` equal strata.

    Cached per size (read-only: callers must not modify the result).
    """
    if n_points <= limit:
        out = np.arange(n_points)
    else:
        start = (np.arange(limit) * n_points) // limit
        width = np.diff(np.append(start, n_points))
        jitter = np.random.default_rng(FIXED_SEED).random(limit)
        out = start + (jitter * width).astype(np.intp)
    out.flags.writeable = False
    return out


def _triplet_planes(sub: FloatArray, count: int, seed: int | None) -> tuple[FloatArray, FloatArray]:
    """Unit normals (K, 3) and offsets (K,) of planes through random triplets of ``sub`` (m, 3)."""
    rng = np.random.default_rng(FIXED_SEED if seed is None else seed)
    idx = rng.integers(0, sub.shape[0], size=(3, count))
    a = sub[idx[0]]
    u = sub[idx[1]] - a
    v = sub[idx[2]] - a
    nrm = np.cross(u, v)
    length = np.sqrt(np.einsum("ij,ij->i", nrm, nrm))
    ok = length > 1e-9 * np.einsum("ij,ij->i", u, u)    # drop (nearly) collinear triplets
    if not ok.any():
        raise CalibrationError("full-frame fit: the points are collinear or coincident; no plane is defined")
    nrm = nrm[ok] / length[ok, None]
    return nrm, -np.einsum("ij,ij->i", nrm, a[ok])


def _within(expected: ExpectedPlane, nrm: FloatArray, off: FloatArray) -> tuple[BoolArray, FloatArray]:
    """Which planes (unit normals (K, 3), offsets (K,)) lie within the expected plane's tolerances.

    Also returns each one's departure in units of the tolerances (the larger of angle and offset).
    """
    n0 = np.asarray(expected.plane.normal, dtype=np.float64)
    cos = np.minimum(np.abs(nrm @ n0), 1.0)                     # either orientation of a triplet's normal
    angle = np.arccos(cos)                                      # rad
    doff = np.abs(np.abs(off) - abs(expected.plane.offset_m))   # camera's distance to each plane vs expected, m
    ok = (angle <= expected.angle_tolerance_rad) & (doff <= expected.offset_tolerance_m)
    return ok, np.maximum(angle / expected.angle_tolerance_rad, doff / expected.offset_tolerance_m)


def _nearest_refusal(expected: ExpectedPlane, nrm: FloatArray, off: FloatArray, score: FloatArray
                     ) -> CalibrationQualityError:
    """``expected_plane`` failed before the fit: no hypothesis within the tolerances; say what was nearest."""
    k = int(np.argmin(score))
    near = Plane(nrm[k], float(off[k])).oriented_toward_origin()
    angle, doff = expected.departure(near)
    a, tol_a = quantity_pair(angle, expected.angle_tolerance_rad, "rad")
    o, tol_o = quantity_pair(doff, expected.offset_tolerance_m, "m", digits=4)
    return CalibrationQualityError(
        "expected_plane", angle, expected.angle_tolerance_rad,
        f"no plane within {tol_a} and {tol_o} of the expected one among {nrm.shape[0]} candidate planes; "
        f"the nearest is {a} and {o} from it (tilt x "
        f"{math.degrees(near.tilt_about_x_rad()):.3g} deg, tilt y {math.degrees(near.tilt_about_y_rad()):.3g} deg, "
        f"{near.offset_m * 1000:.4g} mm from the camera)", unit="rad")


def robust_start(p: F32, dm: F32, model: Model, settings: FullFrameSettings,
                 expected: ExpectedPlane | None = None) -> tuple[FloatArray, float]:
    """The start plane: the triplet plane with the smallest ``hypothesis_quantile`` of residuals.

    Residuals are orthogonal distances over ``range^e`` (weighted), over the given sigmas,
    or plain (unweighted). With ``expected``, only triplet planes within its tolerances
    compete. Returns the unit normal (toward the camera) and the offset.

    Raises:
        CalibrationQualityError: ``expected_plane``, when no triplet plane lies within the
            expected plane's tolerances (the message names the nearest one).
    """
    idx = fixed_subsample(p.shape[1], settings.sample_points)
    sub = p[:, idx].T.astype(np.float64)
    if model.sigma is not None:
        inv_norm = 1.0 / model.sigma[idx].astype(np.float64)
    elif model.weighted:
        inv_norm = dm[idx].astype(np.float64) ** -model.exponent
    else:
        inv_norm = np.ones(idx.size)
    spread = np.linalg.eigvalsh(np.cov(sub.T)) if sub.shape[0] > 3 else np.zeros(3)
    if not spread[1] > LINE_RATIO * spread[2]:
        raise CalibrationError(f"full-frame fit: the {p.shape[1]} valid points lie along a line (one image row "
                               "or column?); no plane is defined")
    if expected is None:
        nrm, off = _triplet_planes(sub, settings.hypotheses, settings.seed)
    else:                                                 # only planes near the expected one compete
        nrm, off = _triplet_planes(sub, EXPECTED_DRAWS * settings.hypotheses, settings.seed)
        ok, score = _within(expected, nrm, off)
        if not ok.any():
            raise _nearest_refusal(expected, nrm, off, score)
        nrm, off = nrm[ok], off[ok]
    m = idx.size
    h = min(max(int(settings.hypothesis_quantile * m), 3), m)
    res = np.abs(nrm.astype(np.float32) @ sub.T.astype(np.float32) + off.astype(np.float32)[:, None])
    res *= inv_norm.astype(np.float32)[None, :]           # (hypotheses, points), rows contiguous
    k = _best_quantile(res, h)
    n, d = nrm[k], float(off[k])
    if d < 0 or (d == 0 and n[2] > 0):                   # normal toward the camera
        n, d = -n, -d
    return np.asarray(n, dtype=np.float64), d


def _best_quantile(res: F32, h: int) -> int:
    """Index of the row of ``res`` with the smallest ``h``-th smallest value (first on ties).

    The same answer as partitioning every row, with far fewer rows ordered: a row whose
    ``h``-th value could be at most that of a good row has at least ``h`` values ``<=`` it;
    only those rows are ordered (exactly). The good row is the best by the same quantile
    on every 8th column (a cheap guess; any row keeps the answer exact). Rows are sorted,
    not partitioned: a noise-free plane gives rows of many equal residuals (zeros), where
    numpy's introselect degrades (2.9 ms instead of 0.5 ms for 96 x 1024).
    """
    guess_cols = res[:, ::8]
    g = min(max(h // 8, 1), guess_cols.shape[1]) - 1
    guess = int(np.argmin(np.sort(guess_cols, axis=1)[:, g]))
    q0 = np.sort(res[guess])[h - 1]                       # the guess's exact quantile
    cand = np.flatnonzero(np.count_nonzero(res <= q0, axis=1) >= h)   # rows whose quantile is <= q0
    score = np.full(res.shape[0], np.inf, dtype=np.float32)
    score[cand] = np.sort(res[cand], axis=1)[:, h - 1]
    return int(np.argmin(score))                          # rows left out have a larger quantile


def initial_scale(p: F32, dm: F32, model: Model, n: FloatArray, offset: float,
                  settings: FullFrameSettings) -> tuple[float, Cutoff]:
    """A scale at or below the noise's, from the start plane's residuals, and the cut-off.

    The ``q`` quantile of |z| is divided by the Gaussian quantile of ``q / 0.5``: exact when
    half of the points are inliers (the least the inlier gate accepts), an underestimate
    when more are. The passes then grow it to the smallest self-consistent scale.
    """
    k0 = max(1, p.shape[1] // 1024)
    p0, d0 = p[:, ::k0], dm[::k0]
    inv_c = d0 / (n.astype(np.float32) @ p0)   # 1 / cos(ray, normal)
    t = inv_c * np.float32(-offset)            # predicted range along the ray
    z = d0 - t                                 # range residual ...
    sig_med = 1.0
    if model.sigma is not None or model.weighted:
        if model.sigma is not None:
            sig = model.sigma[::k0]
        else:                                  # ... or by the noise model t^e / sqrt|cos|
            sig = (np.abs(t) ** np.float32(model.exponent) / np.sqrt(np.abs(inv_c))).astype(np.float32)
        z /= sig                               # ... normalised
        mid = sig.size // 2
        sig_med = max(float(np.partition(sig, mid)[mid]), 1e-12)   # median pixel's sigma
    q = settings.hypothesis_quantile
    az = np.abs(z)
    kq = min(int(q * az.size), az.size - 1)
    level = min(q / 0.5, 0.98)
    s = float(np.partition(az, kq)[kq]) / NormalDist().inv_cdf(0.5 + level / 2.0)   # |z| quantile -> Gaussian sigma
    k_sig = settings.inlier_threshold_sigma
    kept_var, cov_factor = truncation(k_sig)
    cutoff = Cutoff(k_sig, settings.min_inlier_threshold_m / sig_med, settings.max_inlier_threshold_m / sig_med,
                    kept_var, cov_factor)
    return s, cutoff


def _converged(it: Pass, s: float, s_new: float, floor_scale: float) -> bool:
    """The step is a small fraction of the parameters' (subsample) sigma and the scale has settled.

    Noise-free data: the cut-off sits at its floor (``floor_scale``) and the scale never settles
    in relative terms. The full-data pass after the loop finishes the job.
    """
    try:
        sd = np.sqrt(np.abs(np.diag(np.linalg.inv(it.hessian)))) * max(s_new, floor_scale)   # parameter sigmas
    except np.linalg.LinAlgError:
        sd = np.full(3, np.inf)
    settled = abs(s_new - s) <= 0.01 * s or max(s, s_new) <= floor_scale
    return bool(np.all(np.abs(it.step) <= 0.1 * sd)) and settled


def refine(p: F32, dm: F32, model: Model, n: FloatArray, offset: float, s: float, cutoff: Cutoff,
           settings: FullFrameSettings) -> tuple[FloatArray, float, float]:
    """Reweighted Gauss-Newton passes (on the subsample) until converged: normal, offset, scale."""
    e1, e2 = basis(n)
    scratch = Scratch(dm.size)                                  # rows reused by every pass
    for _ in range(settings.max_iterations):
        it = gn_pass(p, dm, n, e1, e2, offset, cutoff.at(s), model, scratch)
        n, offset = step_plane(n, e1, e2, offset, it.step)
        e1, e2 = basis(n)
        s_new = math.sqrt(it.z2_sum / it.n_inliers / cutoff.kept_var)   # inlier RMS, truncation-corrected
        converged = _converged(it, s, s_new, cutoff.lo / cutoff.k_sig)
        s = s_new
        if converged:
            break
    return n, offset, s
