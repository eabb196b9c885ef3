"""The camera's systematic allowance in the hand-eye estimate: common to the poses, not per-pose noise (issue #39).

ADR 0059 "Amended": the poses are weighed by their fits' noise alone; each systematic term is one
coefficient common to the poses, its first-order response added to the mount's covariance.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from cellcal.core.handeye import estimate_mount, observation_from_pose
from cellcal.core.handeye.model import PlaneObservation
from cellcal.core.handeye.synthetic import observations, sim_scenario

SCENARIO = sim_scenario()


def _estimate(obs: list[PlaneObservation], **kw: object):  # type: ignore[no-untyped-def]
    return estimate_mount(obs, SCENARIO.nominal_mount, SCENARIO.nominal_plane, max_interval_scale=np.inf, **kw)


def _without_common_term(obs: list[PlaneObservation]) -> list[PlaneObservation]:
    """The same planes weighed by their noise, the allowance left out."""
    return [dataclasses.replace(o, covariance=o.noise, noise_covariance=None, systematic_shifts={}) for o in obs]


def _as_before(obs: list[PlaneObservation]) -> list[PlaneObservation]:
    """The allowance taken as per-pose noise (the total covariance weighs the poses)."""
    return [dataclasses.replace(o, noise_covariance=None, systematic_shifts={}) for o in obs]


def _tz_error(est) -> float:  # type: ignore[no-untyped-def]
    return float(est.mount.translation[2] - SCENARIO.true_mount.translation[2])


def test_a_common_1_percent_scale_error_is_covered_with_the_systematic_term_and_not_without() -> None:
    scenario = dataclasses.replace(SCENARIO, depth_scale_error=0.01, scale_allowance=0.01)
    obs = observations(scenario, np.random.default_rng(4))
    est = _estimate(obs)
    bare = _estimate(_without_common_term(obs))
    err = _tz_error(est)
    assert abs(err) > 2e-3                                            # the scale moved the mount by mm
    assert abs(err) <= est.z * est.translation_sigma_m[2]             # covered with the common term ...
    assert abs(_tz_error(bare)) > bare.z * bare.translation_sigma_m[2]  # ... not without it
    assert est.systematic_covariance is not None and bare.systematic_covariance is None
    note = [n for n in est.notes if "systematic allowance" in n]
    assert len(note) == 1 and "tz x" in note[0] and "never scaled" in note[0]
    # the budget's 1 % scale is the first-order response: the error the 1 % scale caused, same sign
    budget = est.error_budget
    assert budget is not None
    assert budget["terms"]["depth_scale_1pct"]["tz_m"] == pytest.approx(err, rel=0.05)
    covariance = np.asarray(est.covariance)
    assert np.all(np.linalg.eigvalsh(covariance) > -1e-15)


def _with_field(obs: list[PlaneObservation], tilt_rad: float) -> list[PlaneObservation]:
    """Two field terms as a full-frame fit states them: the plane tilted about the camera's y and x axes."""
    out = []
    for o in obs:
        n = np.asarray(o.normal)
        shifts, cov = dict(o.systematic_shifts), o.covariance.copy()
        for key, axis in (("field:u", [0.0, 1.0, 0.0]), ("field:v", [1.0, 0.0, 0.0])):
            dn = tilt_rad * np.cross(axis, n)
            v = np.concatenate([dn, [0.0]])
            shifts[key], cov = (dn, 0.0), cov + np.outer(v, v)
        out.append(dataclasses.replace(o, covariance=cov, systematic_shifts=shifts))
    return out


def test_chi2_per_dof_is_not_deflated_by_the_allowance() -> None:
    scenario = dataclasses.replace(SCENARIO, scale_allowance=0.01)   # allowance stated, no scale error
    now, before = [], []
    rng = np.random.default_rng(8)
    for _ in range(12):
        obs = _with_field(observations(scenario, rng), 2e-3)         # and a field's common tilt of 2 mrad
        est, old = _estimate(obs), _estimate(_as_before(obs))
        now.append(est.chi2 / est.dof)
        before.append(old.chi2 / old.dof)
    assert 0.6 < float(np.mean(now)) < 1.5                          # the noise's chi2: about 1
    assert float(np.mean(before)) < 0.05                            # the allowance as per-pose noise deflated it


def test_zero_allowance_changes_nothing() -> None:
    obs = observations(SCENARIO, np.random.default_rng(3))
    est = _estimate(obs)
    again = _estimate([dataclasses.replace(o, noise_covariance=o.covariance) for o in obs])
    assert est.systematic_covariance is None and not any("systematic allowance" in n for n in est.notes)
    assert np.array_equal(est.covariance, again.covariance)


def test_the_error_budget_keeps_its_keys() -> None:
    scenario = dataclasses.replace(SCENARIO, scale_allowance=0.002)
    est = _estimate(observations(scenario, np.random.default_rng(5)))
    b = est.error_budget
    assert b is not None
    values = {"tx_m", "ty_m", "tz_m", "roll_rad", "pitch_rad", "yaw_rad", "plane_offset_m"}
    assert set(b["terms"]) == {"depth_scale_1pct", "depth_offset_1mm", "arm_accuracy"}
    assert all(set(t) == values for t in b["terms"].values())
    assert b["judged"] == "allowance" and b["dominant"] in b["at_allowance"] and b["next"]
    # a 1 mm offset on every plane: the plane's offset takes most of it
    assert abs(b["terms"]["depth_offset_1mm"]["plane_offset_m"]) > 5e-4
    plain = _estimate(observations(SCENARIO, np.random.default_rng(5))).error_budget
    assert plain is not None and plain["judged"] == "per unit" and plain["dominant"] in plain["terms"]


def _record(ff: dict[str, object]) -> dict[str, object]:
    flange = {"translation_m": [0.3, 0.0, 0.5], "quaternion_xyzw": [1.0, 0.0, 0.0, 0.0]}
    return {"index": 0, "reported_flange_pose": flange, "full_frame": ff}


def test_documents_with_and_without_the_split() -> None:
    total = (np.eye(3) * 4e-8).tolist()
    old = {"plane_cam": {"normal": [0.0, 0.0, -1.0], "offset_m": 0.5, "offset_sigma_m": 2e-3},
           "normal_covariance": total}
    o = observation_from_pose(_record(old))
    assert o.noise_covariance is None and o.systematic_shifts == {} and o.noise is o.covariance
    new = {**old, "noise_normal_covariance": (np.eye(3) * 1e-8).tolist(), "noise_offset_sigma_m": 1e-5,
           "noise_normal_offset_covariance": [0.0, 0.0, 0.0],
           "systematic_shifts": {"scale": {"normal": [0.0, 0.0, 0.0], "offset_m": 1e-3}},
           "error_budget": {"depth_scale_1pct": {"normal_cam": [0.0, 0.0, 0.0], "offset_m": 5e-3},
                            "depth_offset_1mm": {"normal_cam": [0.0, 0.0, 0.0], "offset_m": 1e-3}}}
    o = observation_from_pose(_record(new))
    assert o.noise[3, 3] == pytest.approx(1e-10) and o.covariance[3, 3] == pytest.approx(4e-6)
    assert o.systematic_shifts["scale"][1] == pytest.approx(1e-3)
    assert o.budget_shifts["depth_scale_1pct"][1] == pytest.approx(5e-3)
