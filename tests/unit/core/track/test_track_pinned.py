"""Pinned numbers of the tracker's change detector (issue #32): the CUSUM at its exact boundaries, the
two change hypotheses against an independent least-squares fit, classify at its levels on both sides.

The independent fit (:func:`independent_fit`) computes the residuals from the hand-eye model
(``PlaneModel.predict`` and ``whitening``, not :mod:`cellcal.core.track.linear`) and minimises them
with ``scipy.optimize.least_squares``; the marginal information is taken from the inverse of the
regularised information (a covariance block) instead of a Schur complement.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.stats import chi2 as chi2_dist

from cellcal.core.handeye.model import PlaneModel, PlaneObservation, whitening
from cellcal.core.handeye.synthetic import Scenario, observations, sim_scenario
from cellcal.core.track.detector import (
    KIND_EITHER,
    KIND_MOUNT,
    KIND_PLANE,
    MOUNT,
    PLANE,
    Cusum,
    Hypothesis,
    classify,
    hypothesis,
)
from cellcal.core.track.linear import Frames, LinearModel
from cellcal.core.track.synthetic import knocked_mount, shifted_plane

SC = sim_scenario()
ARM_SIGMA_M = 2.5e-5
LEVER_M = float(np.linalg.norm(SC.nominal_mount.translation))
WEAK = 0.05 ** -2  # the tracker's default isotropic prior (sigma 0.05 rad / m)


# ---------------------------------------------------------------------------------------------- the CUSUM
def test_cusum_defaults_are_the_adr_values_8_40_120() -> None:
    cusum = Cusum()
    assert (cusum.reference, cusum.clip, cusum.threshold) == (8.0, 40.0, 120.0)
    assert (cusum.statistic, cusum.run_length) == (0.0, 0)


def test_cusum_alarms_strictly_above_the_threshold() -> None:
    cusum = Cusum()  # each frame at the clip adds 40 - 8 = 32
    assert [cusum.update(40.0) for _ in range(3)] == [False, False, False] and cusum.statistic == 96.0
    assert not cusum.update(32.0) and cusum.statistic == 120.0  # exactly at the threshold: no alarm
    assert cusum.run_length == 4
    assert cusum.update(8.0 + 2.0 ** -40)  # the smallest step above it alarms
    assert cusum.statistic == 120.0 + 2.0 ** -40 and cusum.run_length == 5


def test_cusum_clip_is_the_most_one_frame_adds() -> None:
    at, above = Cusum(), Cusum()
    at.update(40.0)
    above.update(40.0 + 1e9)
    assert at.statistic == above.statistic == 32.0
    below = Cusum()
    below.update(39.5)
    assert below.statistic == 31.5  # under the clip a frame adds all it has


def test_cusum_run_length_counts_frames_since_the_statistic_was_zero() -> None:
    cusum = Cusum(reference=8.0, clip=40.0, threshold=120.0)
    cusum.update(8.0)  # exactly the reference: the statistic stays 0, no run
    assert cusum.statistic == 0.0 and cusum.run_length == 0
    cusum.update(8.0 + 2.0 ** -40)  # the smallest excess starts a run
    assert cusum.statistic == 2.0 ** -40 and cusum.run_length == 1
    cusum.reset()
    cusum.update(18.0)
    cusum.update(3.0)  # falling but still above 0: the run goes on
    assert cusum.statistic == 5.0 and cusum.run_length == 2
    cusum.update(3.0)  # 5 + 3 - 8 = 0: back to no evidence
    assert cusum.statistic == 0.0 and cusum.run_length == 0
    cusum.update(0.0)  # far below: floored at 0
    assert cusum.statistic == 0.0 and cusum.run_length == 0


def test_cusum_reset_forgets_statistic_and_run() -> None:
    cusum = Cusum()
    for _ in range(3):
        cusum.update(40.0)
    cusum.reset()
    assert (cusum.statistic, cusum.run_length) == (0.0, 0)
    assert not cusum.update(40.0) and cusum.statistic == 32.0 and cusum.run_length == 1  # starts again from 0


@pytest.mark.parametrize(("reference", "clip", "threshold"), [(0.0, 40.0, 120.0), (40.0, 40.0, 120.0),
                                                               (41.0, 40.0, 120.0), (-1.0, 40.0, 120.0),
                                                               (8.0, 40.0, 0.0), (8.0, 40.0, -5.0)])
def test_cusum_rejects_settings_at_and_beyond_the_bounds(reference: float, clip: float, threshold: float) -> None:
    with pytest.raises(ValueError) as err:
        Cusum(reference, clip, threshold)
    assert str(err.value) == (f"CUSUM needs 0 < reference < clip, threshold > 0; got {reference}, {clip}, "
                              f"{threshold}")


def test_cusum_accepts_settings_just_inside_the_bounds() -> None:
    tiny = 5e-324
    cusum = Cusum(tiny, 40.0, tiny)
    assert (cusum.reference, cusum.threshold) == (tiny, tiny)
    assert Cusum(math.nextafter(40.0, 0.0), 40.0, 120.0).reference < 40.0
    assert cusum.update(1.0)  # 1 - tiny > tiny: an alarm at once


# ---------------------------------------------------------------------------------- the change hypotheses
def frames_of(scenario: Scenario, seed: int, views: list[int], repeat: int) -> tuple[list[PlaneObservation], Frames]:
    """``repeat`` noisy observations of each view in ``views``, as a list and as stacked tracker frames."""
    rng = np.random.default_rng(seed)
    obs = []
    for _ in range(repeat):
        for v in views:
            obs.extend(observations(dataclasses.replace(scenario, flanges=(scenario.flanges[v],)), rng))
    frames = Frames.stack([Frames.of(0.1 * k, o, ARM_SIGMA_M, 0.0, LEVER_M) for k, o in enumerate(obs)])
    return obs, frames


def residuals(x: np.ndarray, obs: list[PlaneObservation]) -> np.ndarray:
    """Whitened residuals (3 per observation) from the hand-eye model: normal error across itself, offset."""
    model = PlaneModel(SC.nominal_mount, SC.nominal_plane)
    normals, offsets = model.predict(x, [o.flange for o in obs])
    out = []
    for o, n, c in zip(obs, normals, offsets, strict=True):
        basis, white = whitening(o, ARM_SIGMA_M, 0.0, LEVER_M)
        out.append(white @ np.r_[basis.T @ (n - o.normal), c - o.offset_m])
    return np.concatenate(out)


def independent_fit(obs: list[PlaneObservation], prior_info: np.ndarray, prior_mean: np.ndarray
                    ) -> tuple[np.ndarray, float, np.ndarray]:
    """Minimiser, minimum of ``|r(x)|² + |x - mean|²_P`` and the data's ``JᵀJ`` at it (least_squares)."""
    root = np.linalg.cholesky(prior_info).T  # |L (x - m)|² = (x - m)' P (x - m)

    def fun(x: np.ndarray) -> np.ndarray:
        return np.concatenate([residuals(x, obs), root @ (x - prior_mean)])

    sol = least_squares(fun, np.zeros(9), xtol=1e-15, ftol=1e-15, gtol=1e-15, x_scale=1e-3)
    jac = sol.jac[:-9]
    return sol.x, float(sol.fun @ sol.fun), jac.T @ jac


def marginal(info: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """The information on ``keep`` with the rest marginalised out, via the covariance block (9x9, 0 elsewhere)."""
    drop = np.setdiff1d(np.arange(9), keep)
    reg = info.copy()
    reg[drop, drop] += WEAK  # the weak prior on the block marginalised out
    out = np.zeros((9, 9))
    out[np.ix_(keep, keep)] = np.linalg.inv(np.linalg.inv(reg)[np.ix_(keep, keep)])
    return out


@pytest.fixture(scope="module")
def anchor() -> tuple[np.ndarray, np.ndarray]:
    """The state before the change: every view twice, fitted with the weak prior (x, JᵀJ)."""
    obs, _ = frames_of(SC, 3, list(range(8)), 2)
    x, _, info = independent_fit(obs, WEAK * np.eye(9), np.zeros(9))
    return x, info


def expected(kind: str, obs: list[PlaneObservation], anchor_x: np.ndarray, anchor_info: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Independently: the hypothesis' fit, its 1-sigma, chi2 and p-value (dof: residuals - the new block's size)."""
    changed = {KIND_MOUNT: np.arange(6), KIND_PLANE: np.arange(6, 9)}.get(kind, np.arange(9))
    kept = np.setdiff1d(np.arange(9), changed)
    held = marginal(anchor_info, kept) if len(kept) else np.zeros((9, 9))
    mean = np.zeros(9)  # the new block toward the configured values, the kept one shrunk to its old value
    if len(kept):
        block = held[np.ix_(kept, kept)]
        mean[kept] = np.linalg.solve(block + WEAK * np.eye(len(kept)), block @ anchor_x[kept])
    x, chi2, info = independent_fit(obs, held + WEAK * np.eye(9), mean)
    sigma = np.sqrt(np.diag(np.linalg.inv(info + held + WEAK * np.eye(9))))  # the fit's 1-sigma
    return x, sigma, chi2, float(chi2_dist.sf(chi2, 3 * len(obs) - len(changed)))


def test_blocks_are_the_mount_six_and_the_plane_three() -> None:
    assert MOUNT.tolist() == [0, 1, 2, 3, 4, 5] and PLANE.tolist() == [6, 7, 8]
    assert (KIND_MOUNT, KIND_PLANE, KIND_EITHER) == ("mount", "plane", "mount or plane")


KNOCKED = dataclasses.replace(SC, true_mount=knocked_mount(SC.true_mount, 0.5, (0.0, 1.0, 0.0)))
MOVED = dataclasses.replace(SC, true_plane=shifted_plane(SC.true_plane, 0.005))


@pytest.mark.parametrize("kind", [KIND_MOUNT, KIND_PLANE, KIND_EITHER])
def test_hypothesis_matches_an_independent_least_squares_fit(kind: str, anchor: tuple[np.ndarray, np.ndarray]
                                                            ) -> None:
    obs, frames = frames_of(KNOCKED, 5, [0, 3, 5], 2)
    x_ref, sigma, chi2_ref, p_ref = expected(kind, obs, *anchor)
    got = hypothesis(kind, LinearModel(SC.nominal_mount, SC.nominal_plane), frames, anchor[0], anchor[1], WEAK)
    assert isinstance(got, Hypothesis) and got.kind == kind
    assert got.fit.n_residuals == 18
    assert np.all(np.abs(got.fit.x - x_ref) < 1e-4 * sigma)  # the same minimum, to 1e-4 sigma
    assert got.fit.chi2 == pytest.approx(chi2_ref, rel=1e-6)
    assert got.p_value == pytest.approx(p_ref, rel=1e-5, abs=1e-300)


def test_hypotheses_on_a_knock_keep_the_plane_and_reject_the_plane_change(anchor: tuple[np.ndarray, np.ndarray]
                                                                          ) -> None:
    obs, frames = frames_of(KNOCKED, 6, [0, 2, 4, 6], 3)
    model = LinearModel(SC.nominal_mount, SC.nominal_plane)
    mount = hypothesis(KIND_MOUNT, model, frames, anchor[0], anchor[1], WEAK)
    plane = hypothesis(KIND_PLANE, model, frames, anchor[0], anchor[1], WEAK)
    p_ref = expected(KIND_MOUNT, obs, *anchor)[3]
    assert mount.p_value == pytest.approx(p_ref, rel=1e-5) and p_ref > 1e-3
    assert plane.p_value < 1e-6 < mount.p_value
    # the kept plane stays within its pre-change sigma of the anchor; the new mount moved by the knock
    sigma_plane = np.sqrt(np.diag(np.linalg.inv(anchor[1] + WEAK * np.eye(9))))[6:]
    assert np.all(np.abs(mount.fit.x[6:] - anchor[0][6:]) < 3 * sigma_plane)
    assert abs(mount.fit.x[1] - anchor[0][1]) == pytest.approx(math.radians(0.5), abs=2e-4)


def test_hypothesis_without_dof_has_p_value_1(anchor: tuple[np.ndarray, np.ndarray]) -> None:
    obs, frames = frames_of(KNOCKED, 7, [0, 1], 1)  # 6 residuals, 6 mount parameters: no dof
    got = hypothesis(KIND_MOUNT, LinearModel(SC.nominal_mount, SC.nominal_plane), frames, *anchor, WEAK)
    assert got.fit.n_residuals == 6 and got.p_value == 1.0
    obs, frames = frames_of(KNOCKED, 7, [0, 1, 2], 1)  # 9 residuals: 3 dof
    got = hypothesis(KIND_MOUNT, LinearModel(SC.nominal_mount, SC.nominal_plane), frames, *anchor, WEAK)
    assert got.p_value == pytest.approx(expected(KIND_MOUNT, obs, *anchor)[3], rel=1e-5)
    assert got.p_value < 1.0


# ------------------------------------------------------------------------------------- classify at its levels
def both(frames: Frames, anchor: tuple[np.ndarray, np.ndarray]) -> tuple[float, float]:
    model = LinearModel(SC.nominal_mount, SC.nominal_plane)
    return (hypothesis(KIND_MOUNT, model, frames, *anchor, WEAK).p_value,
            hypothesis(KIND_PLANE, model, frames, *anchor, WEAK).p_value)


def kind_at(frames: Frames, anchor: tuple[np.ndarray, np.ndarray], accept: float, reject: float) -> str | None:
    kind, mount, plane = classify(LinearModel(SC.nominal_mount, SC.nominal_plane), frames, *anchor, WEAK, accept,
                                  reject)
    assert (mount.kind, plane.kind) == (KIND_MOUNT, KIND_PLANE)
    return kind


def up(v: float) -> float:
    return math.nextafter(v, math.inf)


def test_classify_a_knock_at_the_accept_and_reject_levels(anchor: tuple[np.ndarray, np.ndarray]) -> None:
    _, frames = frames_of(KNOCKED, 6, [0, 2, 4, 6], 3)
    p_mount, p_plane = both(frames, anchor)
    assert p_mount > 1e-3 and p_plane < 1e-6
    assert kind_at(frames, anchor, 1e-3, 1e-6) == KIND_MOUNT  # the tracker's levels
    assert kind_at(frames, anchor, p_mount, 1e-6) == KIND_MOUNT  # p == accept level: fits
    assert kind_at(frames, anchor, up(p_mount), 1e-6) is None  # just above: not accepted, not rejected
    assert kind_at(frames, anchor, 1e-3, p_plane) is None  # p == reject level: not ruled out
    assert kind_at(frames, anchor, 1e-3, up(p_plane)) == KIND_MOUNT


def test_classify_a_table_shift_at_the_accept_and_reject_levels(anchor: tuple[np.ndarray, np.ndarray]) -> None:
    _, frames = frames_of(MOVED, 8, [0, 2, 4, 6], 3)
    p_mount, p_plane = both(frames, anchor)
    assert p_plane > 1e-3 and p_mount < 1e-6
    assert kind_at(frames, anchor, 1e-3, 1e-6) == KIND_PLANE
    assert kind_at(frames, anchor, p_plane, 1e-6) == KIND_PLANE
    assert kind_at(frames, anchor, up(p_plane), 1e-6) is None
    assert kind_at(frames, anchor, 1e-3, p_mount) is None
    assert kind_at(frames, anchor, 1e-3, up(p_mount)) == KIND_PLANE


def test_classify_both_changed_is_mount_or_plane_below_the_reject_level(anchor: tuple[np.ndarray, np.ndarray]
                                                                      ) -> None:
    both_changed = dataclasses.replace(KNOCKED, true_plane=MOVED.true_plane)
    _, frames = frames_of(both_changed, 9, [0, 2, 4, 6], 3)
    p_mount, p_plane = both(frames, anchor)
    assert max(p_mount, p_plane) < 1e-6
    assert kind_at(frames, anchor, 1e-3, 1e-6) == KIND_EITHER
    high = max(p_mount, p_plane)
    assert kind_at(frames, anchor, 1e-3, high) is None  # the larger p at the level: not both ruled out
    assert kind_at(frames, anchor, 1e-3, up(high)) == KIND_EITHER


def test_classify_at_one_pose_both_fit_and_nothing_is_concluded(anchor: tuple[np.ndarray, np.ndarray]) -> None:
    _, frames = frames_of(MOVED, 10, [0], 6)  # one pose: a plane shift looks like a mount shift
    p_mount, p_plane = both(frames, anchor)
    assert min(p_mount, p_plane) > 1e-3
    assert kind_at(frames, anchor, 1e-3, 1e-6) is None
    assert kind_at(frames, anchor, 1e-3, min(p_mount, p_plane)) is None
    assert p_mount < p_plane  # one pose: both fit, the plane with three more degrees of freedom
    high = up(p_plane)
    assert kind_at(frames, anchor, high, p_plane) is None  # the plane's p at the reject level: not ruled out
    assert kind_at(frames, anchor, high, high) == KIND_EITHER  # both below both levels: neither fits alone
