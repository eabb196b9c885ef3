"""Data types exchanged through the device interfaces.

Conventions (ADR 0002, 0003): SI units; the camera (optical) frame is OpenCV's —
x right, y down, z forward along the optical axis; pixel ``(u, v)`` has its
centre at integer coordinates, ``u`` along columns, ``v`` along rows.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .errors import CalibrationError, FrameError
from .jsonsafe import json_safe
from .measurement import UNKNOWN_MODEL, MeasurementModel

#: Lens models of :class:`Intrinsics`: OpenCV's pinhole + Brown–Conrady, and OpenCV's fisheye.
LENS_MODELS = ("brown", "fisheye")
#: Coefficients a fisheye model leaves at 0.
_NOT_FISHEYE = ("p1", "p2", "k5", "k6", "s1", "s2", "s3", "s4")
#: Order of the OpenCV distortion vector (14 terms; tauX/tauY unsupported and always 0).
OPENCV_DISTORTION_ORDER = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4")


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics with Brown–Conrady distortion, OpenCV conventions.

    Attributes:
        width: Image width in pixels.
        height: Image height in pixels.
        fx: Focal length along x, pixels.
        fy: Focal length along y, pixels.
        cx: Principal point x, pixels (pixel centres at integers).
        cy: Principal point y, pixels.
        k1, k2, k3: Radial distortion coefficients.
        k4, k5, k6: Rational radial denominators (OpenCV rational model), usually 0.
        p1, p2: Decentering (tangential) coefficients.
        s1, s2, s3, s4: Thin-prism coefficients.
        model: ``"brown"`` (the above, OpenCV's ``calib3d`` model) or ``"fisheye"``
            (OpenCV's ``cv2.fisheye`` / Kannala–Brandt model: ``theta_d = theta (1 + k1 theta^2
            + k2 theta^4 + k3 theta^6 + k4 theta^8)``, only k1..k4 used; wide-angle heads
            such as the O3R225). Project and back-project through
            :mod:`cellcal.devices.geometry.camera_model`, which handles both; :attr:`distortion`
            is the Brown vector only.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    k4: float = 0.0
    k5: float = 0.0
    k6: float = 0.0
    s1: float = 0.0
    s2: float = 0.0
    s3: float = 0.0
    s4: float = 0.0
    model: str = "brown"

    def __post_init__(self) -> None:
        if self.model not in LENS_MODELS:
            raise CalibrationError(f"Intrinsics.model must be one of {', '.join(LENS_MODELS)}, got {self.model!r}")
        if self.model == "fisheye" and any(getattr(self, n) != 0 for n in _NOT_FISHEYE):
            raise CalibrationError("fisheye intrinsics use only k1..k4; p1, p2, k5, k6, s1..s4 must be 0")
        for f in fields(self):
            if f.name == "model":
                continue
            value = getattr(self, f.name)
            if f.name in ("width", "height"):
                if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value <= 0:
                    raise CalibrationError(f"Intrinsics.{f.name} must be a positive integer, got {value!r}")
                object.__setattr__(self, f.name, int(value))
                continue
            try:
                fv = float(value)
            except (TypeError, ValueError):
                raise CalibrationError(f"Intrinsics.{f.name} must be a number, got {value!r}") from None
            if not math.isfinite(fv):
                raise CalibrationError(f"Intrinsics.{f.name} must be finite, got {value!r}")
            object.__setattr__(self, f.name, fv)
        if self.fx <= 0 or self.fy <= 0:
            raise CalibrationError(f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")

    @property
    def camera_matrix(self) -> NDArray[np.float64]:
        """The 3x3 camera matrix K."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def distortion(self) -> NDArray[np.float64]:
        """OpenCV distortion vector (12 terms, order :data:`OPENCV_DISTORTION_ORDER`)."""
        return np.array([getattr(self, n) for n in OPENCV_DISTORTION_ORDER], dtype=np.float64)

    @property
    def has_distortion(self) -> bool:
        """Whether any distortion coefficient is non-zero."""
        return bool(np.any(self.distortion != 0.0))

    @property
    def shape(self) -> tuple[int, int]:
        """Image shape as ``(rows, cols)`` = ``(height, width)``."""
        return (self.height, self.width)

    @classmethod
    def from_opencv(cls, width: int, height: int, camera_matrix: Any, distortion: Any = ()) -> Intrinsics:
        """Build from an OpenCV camera matrix and distortion vector (4, 5, 8, 12 or 14 terms).

        Raises:
            CalibrationError: On a malformed matrix, a distortion vector of another length,
                or non-zero tilt terms (tauX, tauY), which cellcal does not model.
        """
        k = np.asarray(camera_matrix, dtype=np.float64)
        if k.shape != (3, 3):
            raise CalibrationError(f"camera matrix must be 3x3, got shape {k.shape}")
        d = np.asarray(distortion, dtype=np.float64).ravel()
        if d.size not in (0, 4, 5, 8, 12, 14):
            raise CalibrationError(f"distortion vector must have 0/4/5/8/12/14 terms, got {d.size}")
        if d.size == 14 and np.any(d[12:] != 0):
            raise CalibrationError("tilted-sensor distortion terms (tauX, tauY) are not supported")
        coeffs = dict(zip(OPENCV_DISTORTION_ORDER, d[:12].tolist(), strict=False))
        return cls(width=width, height=height, fx=k[0, 0], fy=k[1, 1], cx=k[0, 2], cy=k[1, 2], **coeffs)

    def to_dict(self) -> dict[str, float | int | str]:
        """JSON-friendly dict of all fields (``model`` only when it is not the default ``"brown"``)."""
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name != "model" or self.model != "brown"}


@dataclass(frozen=True)
class DeviceInfo:
    """Identity of a connected device.

    Attributes:
        backend: Registered backend name, e.g. ``"o3r"``.
        vendor: Manufacturer.
        model: Model name.
        serial: Serial number or other unique id ("" if unknown).
        firmware: Firmware / software version ("" if unknown).
        extra: Backend-specific details: JSON data only (dicts with string keys,
            lists, numbers, strings, booleans, None; numpy values and tuples are
            fine), because reports and recordings store it.

    Raises:
        TypeError: If ``extra`` holds anything else, naming the backend and the key.
    """

    backend: str
    vendor: str
    model: str
    serial: str = ""
    firmware: str = ""
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        try:
            json_safe(self.extra)
        except TypeError as exc:
            raise TypeError(f"DeviceInfo.extra of backend {self.backend!r}: {exc}") from None


@dataclass(frozen=True, eq=False)
class Frame:
    """One 3D camera frame.

    Attributes:
        distance: Radial distance from the optical centre, metres, float32, shape (H, W);
            NaN where invalid.
        xyz: Points in the camera (optical) frame, metres, float32, shape (H, W, 3);
            NaN where invalid.
        amplitude: Return-signal amplitude, float32, shape (H, W), backend units.
        valid: True where the pixel holds a valid measurement, bool, shape (H, W).
        intrinsics: The intrinsics the frame was taken with.
        timestamp: Acquisition time, seconds since the Unix epoch.
        sequence: Frame counter from the device (monotonic per stream).
        confidence: Raw vendor confidence / status image, if the device sends one.
        metadata: Per-frame vendor facts, JSON data only (e.g. the device's own clock
            reading ``device_timestamp_s``, an O3R's measurement block in a cycling mode).
        measurement: How the camera measured (:class:`~cellcal.devices.measurement.MeasurementModel`);
            :meth:`Camera3D.capture <cellcal.devices.camera.Camera3D.capture>` stamps the
            camera's model on frames that carry none.
    """

    distance: NDArray[np.float32]
    xyz: NDArray[np.float32]
    amplitude: NDArray[np.float32]
    valid: NDArray[np.bool_]
    intrinsics: Intrinsics
    timestamp: float
    sequence: int
    confidence: NDArray[Any] | None = None
    metadata: dict[str, Any] = field(default_factory=dict)
    measurement: MeasurementModel = UNKNOWN_MODEL

    def __post_init__(self) -> None:
        if not isinstance(self.measurement, MeasurementModel):
            raise FrameError(f"Frame.measurement must be a MeasurementModel, got {type(self.measurement).__name__}")
        h, w = self.intrinsics.height, self.intrinsics.width
        checks = (
            ("distance", self.distance, (h, w), np.float32),
            ("xyz", self.xyz, (h, w, 3), np.float32),
            ("amplitude", self.amplitude, (h, w), np.float32),
            ("valid", self.valid, (h, w), np.bool_),
        )
        for name, arr, shape, dtype in checks:
            if not isinstance(arr, np.ndarray) or arr.shape != shape or arr.dtype != dtype:
                got = (getattr(arr, "shape", None), getattr(arr, "dtype", type(arr).__name__))
                raise FrameError(
                    f"Frame.{name} must be {np.dtype(dtype).name} of shape {shape}, got {got}"
                )
        if self.confidence is not None and self.confidence.shape != (h, w):
            raise FrameError(f"Frame.confidence must have shape {(h, w)}, got {self.confidence.shape}")

    @property
    def shape(self) -> tuple[int, int]:
        """``(height, width)`` in pixels."""
        return self.intrinsics.shape

    @property
    def valid_fraction(self) -> float:
        """Fraction of valid pixels, 0..1."""
        return float(np.count_nonzero(self.valid)) / self.valid.size


@dataclass(frozen=True)
class ArmStatus:
    """Error / warning state of a robot arm.

    Attributes:
        error_code: Vendor error code, 0 when there is none.
        warning_code: Vendor warning code, 0 when there is none.
        message: Human-readable meaning of the error (or warning), "" when clear.
        can_move: Whether the arm will accept a motion command now.
    """

    error_code: int = 0
    warning_code: int = 0
    message: str = ""
    can_move: bool = True

    @property
    def ok(self) -> bool:
        """True when there is no error and the arm can move."""
        return self.error_code == 0 and self.can_move
