"""Pose: its matrix algebra and OpenCV rotation vectors agree with scipy's Rotation, which it builds on demand."""

from __future__ import annotations

import math
import pickle
import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from cellcal.devices.errors import CalibrationError
from cellcal.devices.pose import Pose

#: Rotation angles (rad) from tiny, where cv2.Rodrigues alone returns zero, to half a turn.
ANGLES = (0.0, 1e-12, 1e-9, 3e-6, 2e-5, 1e-4, 1e-2, 0.5, 0.6, 2.0, 3.0, math.pi - 1e-6)


def _rotations(seed: int, n: int = 30) -> list[Rotation]:
    rng = np.random.default_rng(seed)
    out = []
    for angle in ANGLES:
        for _ in range(n // len(ANGLES) + 1):
            axis = rng.normal(size=3)
            out.append(Rotation.from_rotvec(angle * axis / np.linalg.norm(axis)))
    return out


def test_algebra_matches_scipy() -> None:
    rng = np.random.default_rng(1)
    for r in _rotations(1):
        a = Rotation.random(random_state=rng)
        b = a * r
        ta, tb = rng.normal(size=3), rng.normal(size=3)
        pa, pb = Pose(a, ta), Pose(b, tb)
        pts = rng.normal(size=(5, 3))
        np.testing.assert_allclose((pa @ pb).rotation_matrix, (a * b).as_matrix(), atol=1e-14)
        np.testing.assert_allclose((pa @ pb).translation, a.apply(tb) + ta, atol=1e-14)
        np.testing.assert_allclose(pa.inv().apply(pa.apply(pts)), pts, atol=1e-13)
        np.testing.assert_allclose(pa.apply(pts), a.apply(pts) + ta, atol=1e-14)
        np.testing.assert_allclose(pa.apply_vector(pts), a.apply(pts), atol=1e-14)
        assert abs(pa.angle_to(pb) - (a.inv() * b).magnitude()) < 1e-13
        np.testing.assert_allclose(pa.rotvec_to(pb), (a.inv() * b).as_rotvec(), atol=1e-13)


def test_rotation_vectors_and_quaternions_match_scipy_at_every_angle() -> None:
    for r in _rotations(2):
        pose = Pose(r, [0.1, 0.2, 0.3])
        if r.magnitude() < math.pi - 1e-3:  # away from the half turn, where the vector's sign is a choice
            np.testing.assert_allclose(pose.as_xyz_rotvec()[3:], r.as_rotvec(), atol=1e-13)
        q = r.as_quat()
        np.testing.assert_allclose(pose.as_quat_xyzw(), q if q[3] >= 0 else -q, atol=1e-12)
        back = Pose.from_xyz_rotvec(pose.translation, pose.as_xyz_rotvec()[3:])
        assert back.is_close(pose, atol_rad=1e-12)


def test_constructors_match_scipy() -> None:
    rng = np.random.default_rng(3)
    for _ in range(50):
        rpy = rng.uniform(-3.0, 3.0, 3)
        rotvec = rng.normal(size=3)
        np.testing.assert_allclose(Pose.from_xyz_rpy(np.zeros(3), rpy).rotation_matrix,
                                   Rotation.from_euler("xyz", rpy).as_matrix(), atol=1e-14)
        np.testing.assert_allclose(Pose.from_xyz_rotvec(np.zeros(3), rotvec).rotation_matrix,
                                   Rotation.from_rotvec(rotvec).as_matrix(), atol=1e-14)
        pose = Pose.from_xyz_rpy(rng.normal(size=3), rpy)
        np.testing.assert_allclose(pose.as_xyz_rpy()[3:], Rotation.from_matrix(pose.rotation_matrix).as_euler("xyz"),
                                   atol=1e-12)
        for data in (pose.to_dict(), {k: v for k, v in pose.to_dict().items() if k != "rotvec_rad"}):
            assert Pose.from_dict(data).is_close(pose, atol_m=0.0, atol_rad=1e-12)


def test_interpolation_is_scipys_slerp() -> None:
    rng = np.random.default_rng(4)
    for r in _rotations(4, 12):
        a = Rotation.random(random_state=rng)
        start, end = Pose(a, rng.normal(size=3)), Pose(a * r, rng.normal(size=3))
        s = np.linspace(0.0, 1.0, 7)
        want = Slerp([0.0, 1.0], Rotation.concatenate([a, a * r]))(s).as_matrix()
        for k, f in enumerate(s):
            mid = start.interpolate(end, float(f))
            np.testing.assert_allclose(mid.rotation_matrix, want[k], atol=1e-12)
            np.testing.assert_allclose(mid.translation, start.translation + f * (end.translation - start.translation))


def test_matrices_are_kept_exactly_and_checked() -> None:
    r = Rotation.from_rotvec([0.3, -0.2, 0.9]).as_matrix()
    assert np.array_equal(Pose.from_rotation_matrix(r, [1.0, 2.0, 3.0]).rotation_matrix, r)  # bit for bit
    nearly = r + 1e-8
    fixed = Pose.from_rotation_matrix(nearly).rotation_matrix
    np.testing.assert_allclose(fixed @ fixed.T, np.eye(3), atol=1e-15)  # projected to a rotation
    with pytest.raises(CalibrationError, match="not a proper rotation"):
        Pose.from_rotation_matrix(np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(CalibrationError, match="3x3"):
        Pose.from_rotation_matrix([[1.0, 0.0], [0.0, 1.0]])
    with pytest.raises(CalibrationError, match="single scipy Rotation"):
        Pose(np.eye(3))  # type: ignore[arg-type]


def test_immutable_picklable_and_scipy_on_demand() -> None:
    pose = Pose.from_xyz_rpy([0.1, 0.0, 0.5], [0.1, 0.2, 0.3])
    with pytest.raises(AttributeError, match="immutable"):
        pose.translation = np.zeros(3)  # type: ignore[misc]
    with pytest.raises(ValueError):
        pose.translation[0] = 1.0
    copy = pickle.loads(pickle.dumps(pose))
    assert np.array_equal(copy.as_matrix(), pose.as_matrix())
    assert pose.with_translation([1.0, 2.0, 3.0]).angle_to(pose) == 0.0
    np.testing.assert_allclose(pose.rotation.as_matrix(), pose.rotation_matrix, atol=1e-15)
    code = ("import sys\nfrom cellcal.devices.pose import Pose\n"
            "p = Pose.from_xyz_rpy([0, 0, 1], [0.1, 0.2, 0.3]) @ Pose.from_xyz_rotvec([1, 0, 0], [0, 0, 1])\n"
            "p.inv().apply([[1.0, 2.0, 3.0]]); p.to_dict(); p.angle_to(p)\n"
            "print('scipy' in sys.modules)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    assert done.stdout.strip() == "False"
