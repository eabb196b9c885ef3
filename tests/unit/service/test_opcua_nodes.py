"""The OPC UA face's values (plane tilts and height, mount x..yaw, their 95 % half-widths) and its security policy.

The half-widths are first-order propagations of the calibration's 9x9 covariance: each is
checked against the Jacobian of the same values taken by central differences of the
parameterisation itself (the mount turned about the flange axes on the left and shifted; the
plane turned about ``tangent_basis(normal)`` through its anchor and moved along its normal).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cellcal.core.geometry.planes import Plane, tangent_basis
from cellcal.core.geometry.relative import perturb
from cellcal.core.service.calibration import Z95
from cellcal.core.service.opcua_nodes import (
    OpcUaSecurity,
    camera_values,
    mount_values,
    opcua_security,
    plane_values,
)
from cellcal.core.service.planepoint import PlaneCalibration
from cellcal.devices.errors import ConfigError
from cellcal.devices.pose import Pose
from cellcal.devices.types import Intrinsics

LENS = Intrinsics(width=224, height=172, fx=194.0, fy=207.6, cx=111.5, cy=85.5)
MOUNT = Pose.from_xyz_rpy([0.01, 0.04, 0.06], [0.05, -0.3, 1.2])
PLANE = Plane.from_point_normal([0.1, -0.2, 0.002], [0.03, -0.02, 1.0])
#: Central-difference step of the parameters (rad and m): truncation ~1e-12, rounding ~1e-10 relative.
STEP = 1e-6


def calibration(plane: Plane = PLANE, mount: Pose = MOUNT) -> PlaneCalibration:
    """A calibration with a dense covariance (~1e-3 per parameter), anchored away from the plane's foot."""
    a = np.random.default_rng(5).normal(size=(9, 9)) * 1e-3
    anchor = plane.project_points(np.array([0.2, 0.1, 0.0]))
    return PlaneCalibration(LENS, mount, plane, anchor, a @ a.T)


def _numeric_half_widths(values: dict[str, float], keys: list[str], moved: object, block: slice,
                         cal: PlaneCalibration) -> np.ndarray:
    """95 % half-widths of ``keys`` by a central-difference Jacobian over the parameters of ``block``."""
    jac = np.zeros((len(keys), 3))
    for j in range(3):
        step = np.zeros(9)
        step[block.start + j] = STEP
        up, down = moved(cal, step), moved(cal, -step)  # type: ignore[operator]
        jac[:, j] = [(up[k] - down[k]) / (2 * STEP) for k in keys]
    cov = cal.covariance[block, block]
    return Z95 * np.sqrt(np.einsum("ij,jk,ik->i", jac, cov, jac))


def _moved_plane(cal: PlaneCalibration, theta: np.ndarray) -> dict[str, float]:
    normal = np.array(cal.plane.normal)
    turned = Rotation.from_rotvec(tangent_basis(normal) @ theta[6:8]).apply(normal)
    plane = Plane.from_point_normal(cal.anchor_m + theta[8] * normal, turned)
    return plane_values(PlaneCalibration(cal.intrinsics, cal.mount, plane, cal.anchor_m, np.zeros((9, 9))))


def _moved_mount(cal: PlaneCalibration, theta: np.ndarray) -> dict[str, float]:
    mount = perturb(cal.mount, theta[:6])
    return mount_values(PlaneCalibration(cal.intrinsics, mount, cal.plane, cal.anchor_m, np.zeros((9, 9))))


def test_plane_values_describe_the_plane() -> None:
    got = plane_values(calibration())
    tx, ty, h = got["PlaneTiltX"], got["PlaneTiltY"], got["PlaneHeight"]
    normal = np.array([math.tan(ty), -math.tan(tx), 1.0])  # the normal the two tilts give back
    assert np.allclose(normal / np.linalg.norm(normal), PLANE.normal, atol=1e-12)
    assert abs(PLANE.signed_distance(np.array([0.0, 0.0, h]))) < 1e-12  # (0, 0, height) lies on the plane
    flipped = plane_values(calibration(Plane(-np.array(PLANE.normal), -PLANE.offset_m)))
    for key in ("PlaneTiltX", "PlaneTiltY", "PlaneHeight"):  # the same plane with its normal down: the same values
        assert flipped[key] == pytest.approx(got[key], abs=1e-12)


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_plane_half_widths_are_the_first_order_propagation(sign: float) -> None:
    cal = calibration(Plane(sign * np.array(PLANE.normal), sign * PLANE.offset_m))
    keys = ["PlaneTiltX", "PlaneTiltY", "PlaneHeight"]
    want = _numeric_half_widths(plane_values(cal), keys, _moved_plane, slice(6, 9), cal)
    got = plane_values(cal)
    assert np.all(want > 1e-4)  # a covariance of ~1e-3 per parameter: not a degenerate check
    assert np.allclose([got[f"{k}HalfWidth"] for k in keys], want, rtol=1e-6)


def test_mount_values_and_half_widths() -> None:
    cal = calibration()
    got = mount_values(cal)
    assert np.allclose([got[f"Mount{k}"] for k in ("X", "Y", "Z", "Roll", "Pitch", "Yaw")],
                       [0.01, 0.04, 0.06, 0.05, -0.3, 1.2], atol=1e-12)
    keys = ["MountRoll", "MountPitch", "MountYaw"]
    want = _numeric_half_widths(got, keys, _moved_mount, slice(0, 3), cal)
    assert np.allclose([got[f"{k}HalfWidth"] for k in keys], want, rtol=1e-6)
    shift = Z95 * np.sqrt(np.diag(cal.covariance)[3:6])
    assert np.allclose([got[f"Mount{k}HalfWidth"] for k in "XYZ"], shift, rtol=1e-12)


def test_gimbal_lock_gives_nan_half_widths_not_a_crash() -> None:
    locked = calibration(mount=Pose.from_xyz_rpy([0.0, 0.0, 0.1], [0.0, math.pi / 2, 0.0]))
    got = mount_values(locked)
    assert all(math.isnan(got[f"Mount{k}HalfWidth"]) for k in ("Roll", "Pitch", "Yaw"))
    assert got["MountPitch"] == pytest.approx(math.pi / 2, abs=1e-9)


def test_camera_values_without_a_calibration_are_blank() -> None:
    blank = camera_values(None)
    assert blank["Calibrated"] is False and blank["CalibrationKind"] == "" and blank["PlaneHeight"] == 0.0


def test_security_policy(tmp_path: Path) -> None:
    assert opcua_security(True, None, None, None) is None  # loopback: no security, anonymous
    with pytest.raises(ConfigError, match="non-loopback address needs --opcua-cert and --opcua-key"):
        opcua_security(False, None, None, "t" * 16)
    with pytest.raises(ConfigError, match="go together"):
        opcua_security(True, "cert.pem", None, None)
    cert, key = tmp_path / "cert.pem", tmp_path / "key.pem"
    with pytest.raises(ConfigError, match="no such file"):
        opcua_security(False, str(cert), str(key), "t" * 16)
    cert.write_text("x")
    key.write_text("x")
    with pytest.raises(ConfigError, match="needs the service's token"):
        opcua_security(True, str(cert), str(key), None)
    assert opcua_security(False, str(cert), str(key), "t" * 16) == OpcUaSecurity(cert, key, "t" * 16)
