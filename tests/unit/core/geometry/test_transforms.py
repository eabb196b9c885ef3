"""Vendor pose converters and the closed frame chain."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from cellcal.core.geometry.frames import FrameChain
from cellcal.devices.errors import CalibrationError
from cellcal.devices.geometry.vendor_poses import pose_from_ur, pose_from_xarm, pose_to_ur, pose_to_xarm
from cellcal.devices.pose import Pose


def random_pose(rng: np.random.Generator) -> Pose:
    return Pose(Rotation.random(random_state=int(rng.integers(1 << 31))), rng.normal(size=3))


def test_ur_round_trip_and_meaning() -> None:
    p = pose_from_ur([0.1, -0.2, 0.3, 0.0, 0.0, math.pi / 2])
    np.testing.assert_allclose(p.apply([1.0, 0, 0]), [0.1, 0.8, 0.3], atol=1e-12)
    rng = np.random.default_rng(1)
    for _ in range(20):
        q = random_pose(rng)
        assert pose_from_ur(pose_to_ur(q)).is_close(q, atol_m=1e-12, atol_rad=1e-12)


def test_xarm_units_and_euler_convention() -> None:
    # 90 deg yaw then 90 deg roll, extrinsic: R = Rz(yaw) Ry(pitch) Rx(roll)
    roll, pitch, yaw = 0.3, -0.4, 1.2
    p = pose_from_xarm([100.0, -50.0, 250.0, roll, pitch, yaw])
    np.testing.assert_allclose(p.translation, [0.1, -0.05, 0.25], atol=1e-15)
    rx = Rotation.from_rotvec([roll, 0, 0]).as_matrix()
    ry = Rotation.from_rotvec([0, pitch, 0]).as_matrix()
    rz = Rotation.from_rotvec([0, 0, yaw]).as_matrix()
    np.testing.assert_allclose(p.rotation.as_matrix(), rz @ ry @ rx, atol=1e-12)
    np.testing.assert_allclose(pose_to_xarm(p), [100.0, -50.0, 250.0, roll, pitch, yaw], atol=1e-9)


@pytest.mark.parametrize("bad", [[1, 2, 3], [1, 2, 3, 4, 5, float("nan")], "abcdef", None])
def test_vendor_converters_reject_bad_input(bad: object) -> None:
    with pytest.raises(CalibrationError):
        pose_from_ur(bad)  # type: ignore[arg-type]
    with pytest.raises(CalibrationError):
        pose_from_xarm(bad)  # type: ignore[arg-type]


def lecture_scene(seed: int) -> dict[str, Pose]:
    """A consistent cell: pick Z, T6, E, G at random and close the loop with B."""
    rng = np.random.default_rng(seed)
    z, t6, e, g = (random_pose(rng) for _ in range(4))
    b = z @ t6 @ e @ g.inv()
    return {"Z": z, "T6": t6, "E": e, "B": b, "G": g}


@given(st.integers(0, 10_000), st.sampled_from(["Z", "T6", "E", "B", "G"]))
@settings(max_examples=40, deadline=None)
def test_chain_solves_any_unknown(seed: int, unknown: str) -> None:
    scene = lecture_scene(seed)
    chain = FrameChain.parse("Z T6 E = B G")
    known = {k: v for k, v in scene.items() if k != unknown}
    name, pose = chain.solve(known)
    assert name == unknown
    assert pose.is_close(scene[unknown], atol_m=1e-9, atol_rad=1e-9)
    assert chain.solve_for(unknown, known).is_close(pose, atol_m=1e-12, atol_rad=1e-12)
    res = chain.residual({**known, unknown: pose})
    assert res.is_close(Pose.identity(), atol_m=1e-9, atol_rad=1e-9)


def test_chain_matches_lecture_formulas() -> None:
    s = lecture_scene(3)
    chain = FrameChain(["Z", "T6", "E"], ["B", "G"])
    t6 = chain.solve_for("T6", Z=s["Z"], E=s["E"], B=s["B"], G=s["G"])
    np.testing.assert_allclose(
        t6.as_matrix(),
        np.linalg.inv(s["Z"].as_matrix()) @ s["B"].as_matrix() @ s["G"].as_matrix()
        @ np.linalg.inv(s["E"].as_matrix()),
        atol=1e-12,
    )
    b = chain.solve_for("B", Z=s["Z"], T6=s["T6"], E=s["E"], G=s["G"])
    np.testing.assert_allclose(
        b.as_matrix(),
        s["Z"].as_matrix() @ s["T6"].as_matrix() @ s["E"].as_matrix()
        @ np.linalg.inv(s["G"].as_matrix()),
        atol=1e-12,
    )


def test_chain_with_inverse_terms() -> None:
    rng = np.random.default_rng(5)
    i, c = random_pose(rng), random_pose(rng)
    p = i @ c
    chain = FrameChain.parse("C = I^-1 * P")
    assert chain.solve_for("C", I=i, P=p).is_close(c, atol_m=1e-12, atol_rad=1e-12)
    assert chain.solve_for("I", C=c, P=p).is_close(i, atol_m=1e-12, atol_rad=1e-12)
    assert str(chain) == "C = I^-1 P"


def test_chain_errors() -> None:
    s = lecture_scene(0)
    chain = FrameChain.parse("Z T6 E = B G")
    with pytest.raises(CalibrationError, match="2 unknowns"):
        chain.solve({k: s[k] for k in ("Z", "T6", "E")})
    with pytest.raises(CalibrationError, match="no unknown"):
        chain.solve(s)
    with pytest.raises(CalibrationError, match="Q not in frame chain"):
        chain.solve({**s, "Q": s["Z"]})
    with pytest.raises(CalibrationError, match="not in frame chain"):
        chain.solve_for("Q", s)
    with pytest.raises(CalibrationError, match="missing"):
        chain.solve_for("T6", Z=s["Z"])
    with pytest.raises(CalibrationError, match="more than once"):
        FrameChain(["A", "B"], ["A"])
    with pytest.raises(CalibrationError, match="exactly one"):
        FrameChain.parse("A B")
    with pytest.raises(CalibrationError, match="must be a Pose"):
        chain.solve({"Z": np.eye(4)})  # type: ignore[dict-item]
