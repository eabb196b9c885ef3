"""What the OPC UA face publishes, and on which terms: its namespace, node ids, values and security policy.

Pure (no asyncua): the values a camera's node shows are computed here from its
:class:`~cellcal.core.service.planepoint.PlaneCalibration`, with their 95 % half-widths
propagated to first order from its 9x9 covariance (the mount's turn about the flange axes and
its shift; the plane's tilts about ``tangent_basis(normal)`` through its anchor and its height
along the normal):

* the plane as the PLC reads it: ``tilt_x = atan2(-n_y, n_z)`` (its normal turned about the base
  x axis, rad), ``tilt_y = atan2(n_x, n_z)`` (about the base y axis, rad) and ``height = -c / n_z``
  (the base-frame z where the plane ``n . p + c = 0`` meets the base z axis, m);
* the mount ``T_flange_camera`` as x, y, z (m) and fixed-axis roll, pitch, yaw (rad,
  ``Rz(yaw) Ry(pitch) Rx(roll)``, :meth:`Pose.as_xyz_rpy`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cellcal.core.geometry.planes import tangent_basis
from cellcal.core.service.calibration import Z95
from cellcal.core.service.planepoint import PlaneCalibration
from cellcal.devices.errors import ConfigError

FloatArray = NDArray[np.float64]

__all__ = ["CAMERA_VARIABLES", "CELL_VARIABLES", "NAMESPACE", "ROOT_ID", "USERNAME", "WATCH_VARIABLES", "OpcUaSecurity",
           "camera_values", "cell_id", "mount_values", "opcua_security", "plane_values", "variable_id"]

#: The namespace URI of every node the service adds.
NAMESPACE = "urn:cellcal:service"
#: The string NodeId of the root object ``Cellcal`` (a cell name cannot start with '.').
ROOT_ID = ".Cellcal"
#: The user name a session logs in with when the face is secured (its password: the service's token).
USERNAME = "cellcal"
#: A camera's variables: name -> (OPC UA type, what it is).
CAMERA_VARIABLES: dict[str, tuple[str, str]] = {
    "Calibrated": ("Boolean", "whether the camera has a calibration"),
    "CalibrationKind": ("String", "'calibrate' or 'handeye': the run that wrote it ('' without one)"),
    "CalibrationCreatedUtc": ("String", "when that run started, ISO 8601"),
    "CalibrationError": ("String", "why the camera's result files cannot be read ('' when they can)"),
    "PlaneTiltX": ("Double", "the plane's normal turned about the base x axis, rad"),
    "PlaneTiltY": ("Double", "the plane's normal turned about the base y axis, rad"),
    "PlaneHeight": ("Double", "base-frame z where the plane meets the base z axis, m"),
    "PlaneTiltXHalfWidth": ("Double", "95 % half-width of PlaneTiltX, rad"),
    "PlaneTiltYHalfWidth": ("Double", "95 % half-width of PlaneTiltY, rad"),
    "PlaneHeightHalfWidth": ("Double", "95 % half-width of PlaneHeight, m"),
    **{f"Mount{a}": ("Double", f"T_flange_camera's {a.lower()}, m") for a in "XYZ"},
    **{f"Mount{a}": ("Double", f"T_flange_camera's fixed-axis {a.lower()}, rad") for a in ("Roll", "Pitch", "Yaw")},
    **{f"Mount{a}HalfWidth": ("Double", f"95 % half-width of Mount{a}, m") for a in "XYZ"},
    **{f"Mount{a}HalfWidth": ("Double", f"95 % half-width of Mount{a}, rad (0: the configured mount)")
       for a in ("Roll", "Pitch", "Yaw")},
}
#: A camera's tracking and monitoring variables (:func:`~cellcal.core.service.watch.watch_values`): name -> (OPC UA
#: type, what it is); written as the sessions' events come.
WATCH_VARIABLES: dict[str, tuple[str, str]] = {
    "TrackState": ("String", "the cell's tracking: idle (none yet), starting, running, stopping, stopped or failed"),
    "MonitorState": ("String", "the cell's monitoring: idle, starting, running, stopping, stopped or failed"),
    "TrackFrames": ("UInt32", "frames of this camera the latest tracking session has taken"),
    "ChangeOpen": ("Boolean", "tracking: a change of the mount or the plane is detected and not re-estimated yet"),
    "DriftEvents": ("UInt32", "drift events of this camera in the latest tracking and monitoring sessions"),
    "LastDrift": ("String", "the latest drift event, one line ('' before one)"),
}
#: A cell's variables: name -> (OPC UA type, what it is).
CELL_VARIABLES: dict[str, tuple[str, str]] = {
    "RunId": ("String", "the latest run's id ('' before the first)"),
    "RunKind": ("String", "its kind: calibrate, handeye or depthcal"),
    "RunCamera": ("String", "its camera"),
    "RunState": ("String", "idle (no run yet), queued, running, ok, failed or cancelled"),
    "PosesDone": ("UInt32", "poses measured so far by the latest run"),
    "PosesTotal": ("UInt32", "poses in its plan (0 until known)"),
    "LastError": ("String", "the latest run's one-line error ('' unless it failed or was cancelled)"),
    "LastRefusal": ("String", "why the latest refused method call on this cell was refused"),
}


def cell_id(cell: str, camera: str | None = None) -> str:
    """The string NodeId of a cell's object (``<cell>``) or of one of its cameras' (``<cell>/<camera>``)."""
    return cell if camera is None else f"{cell}/{camera}"


def variable_id(owner: str, name: str) -> str:
    """The string NodeId of variable or method ``name`` of the object ``owner`` (``<owner>.<name>``)."""
    return f"{owner}.{name}"


def plane_values(model: PlaneCalibration) -> dict[str, float]:
    """``PlaneTiltX``, ``PlaneTiltY`` (rad), ``PlaneHeight`` (m) and their 95 % half-widths (first order)."""
    n = np.asarray(model.plane.normal, dtype=np.float64)
    c = float(model.plane.offset_m)
    if n[2] < 0.0:
        n, c = -n, -c  # the same plane with its normal up: tilts near 0 for a table
    axes = tangent_basis(np.asarray(model.plane.normal, dtype=np.float64))
    # d(n, c) per parameter (tilt a, tilt b, height): a tilt turns n about its axis through the anchor
    # (the anchor stays on the plane, so dc = -dn . q); a height step h along n moves c by -h (sign of n kept)
    sign = 1.0 if np.dot(n, model.plane.normal) > 0 else -1.0
    dn = np.column_stack([np.cross(axes[:, 0], n), np.cross(axes[:, 1], n), np.zeros(3)])
    dc = np.array([-dn[:, 0] @ model.anchor_m, -dn[:, 1] @ model.anchor_m, -sign])
    ny2z2, nx2z2 = n[1] ** 2 + n[2] ** 2, n[0] ** 2 + n[2] ** 2
    jac = np.vstack([(-dn[1] * n[2] + n[1] * dn[2]) / ny2z2,  # d atan2(-n_y, n_z)
                     (dn[0] * n[2] - n[0] * dn[2]) / nx2z2,  # d atan2(n_x, n_z)
                     -dc / n[2] + c * dn[2] / n[2] ** 2])  # d (-c / n_z)
    half = _half_widths(jac, model.covariance[6:9, 6:9])
    return {"PlaneTiltX": math.atan2(-n[1], n[2]), "PlaneTiltY": math.atan2(n[0], n[2]), "PlaneHeight": -c / n[2],
            "PlaneTiltXHalfWidth": half[0], "PlaneTiltYHalfWidth": half[1], "PlaneHeightHalfWidth": half[2]}


def mount_values(model: PlaneCalibration) -> dict[str, float]:
    """``MountX..Z`` (m), ``MountRoll/Pitch/Yaw`` (rad) and their 95 % half-widths (first order; NaN at gimbal lock)."""
    xyz_rpy = model.mount.as_xyz_rpy()
    pitch, yaw = xyz_rpy[4], xyz_rpy[5]
    cy, sy, cp, sp = math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch)
    # a small turn phi about the flange axes (applied on the left) = E d(roll, pitch, yaw), with E's columns
    # the roll axis Rz(yaw) Ry(pitch) x, the pitch axis Rz(yaw) y and the yaw axis z
    e = np.array([[cy * cp, -sy, 0.0], [sy * cp, cy, 0.0], [-sp, 0.0, 1.0]])
    turn = model.covariance[0:3, 0:3]
    locked = abs(cp) < 1e-9  # gimbal lock: roll and yaw are not apart there
    angles = [math.nan if np.any(turn) else 0.0] * 3 if locked else _half_widths(np.linalg.inv(e), turn)
    shift = _half_widths(np.eye(3), model.covariance[3:6, 3:6])
    names = ("X", "Y", "Z", "Roll", "Pitch", "Yaw")
    out = {f"Mount{k}": float(v) for k, v in zip(names, xyz_rpy, strict=True)}
    out.update({f"Mount{k}HalfWidth": float(v) for k, v in zip(names, [*shift, *angles], strict=True)})
    return out


def _half_widths(jac: FloatArray, cov: FloatArray) -> list[float]:
    """95 % half-widths of ``jac @ theta`` for ``theta`` of covariance ``cov`` (first order)."""
    var = np.einsum("ij,jk,ik->i", jac, cov, jac)  # diag(J C J^T)
    return [float(Z95 * math.sqrt(max(v, 0.0))) for v in var]


def camera_values(calibration: Any) -> dict[str, Any]:
    """Every camera variable's value for ``calibration`` (a ``CameraCalibration``, or None before the first)."""
    if calibration is None:
        blank: dict[str, Any] = {name: 0.0 for name, (kind, _) in CAMERA_VARIABLES.items() if kind == "Double"}
        return {**blank, "Calibrated": False, "CalibrationKind": "", "CalibrationCreatedUtc": "",
                "CalibrationError": ""}
    return {"Calibrated": True, "CalibrationKind": calibration.kind,
            "CalibrationCreatedUtc": calibration.created_utc, "CalibrationError": "",
            **plane_values(calibration.model), **mount_values(calibration.model)}


@dataclass(frozen=True)
class OpcUaSecurity:
    """The secured face: Basic256Sha256 Sign&Encrypt only, sessions log in as :data:`USERNAME` with the token.

    Attributes:
        certificate: The server's certificate (PEM or DER file).
        private_key: Its private key (PEM file, unencrypted).
        token: The password every session gives (the service's token).
    """

    certificate: Path
    private_key: Path
    token: str


def opcua_security(loopback: bool, certificate: str | None, private_key: str | None,
                   token: str | None) -> OpcUaSecurity | None:
    """The OPC UA face's security policy: None (no security, anonymous) on loopback without a certificate;
    else Basic256Sha256 Sign&Encrypt with a log-in by the token.

    Args:
        loopback: Whether the service binds a loopback address.
        certificate, private_key: ``--opcua-cert`` and ``--opcua-key`` (files), or None.
        token: The service's token (a non-loopback bind always has one).

    Raises:
        ConfigError: One line: a non-loopback bind without a certificate and key, only one of the two, an
            unreadable file, or a secured face without a token.
    """
    if (certificate is None) != (private_key is None):
        raise ConfigError("--opcua-cert and --opcua-key go together: give both or neither")
    if certificate is None or private_key is None:
        if loopback:
            return None
        raise ConfigError("an OPC UA face bound to a non-loopback address needs --opcua-cert and --opcua-key "
                          "(it offers only Basic256Sha256 SignAndEncrypt there)")
    for path in (certificate, private_key):
        if not Path(path).is_file():
            raise ConfigError("cannot read the OPC UA certificate or key: no such file", source=path)
    if token is None:
        raise ConfigError("a secured OPC UA face needs the service's token (--token-file or CELLCAL_SERVE_TOKEN): "
                          f"sessions log in as {USERNAME!r} with it")
    return OpcUaSecurity(Path(certificate), Path(private_key), token)
