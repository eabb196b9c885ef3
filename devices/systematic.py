"""A camera's systematic depth error in its native space: :class:`SystematicError` (issue #39, ADR 0053).

Stereo and structured light err in disparity (px), ToF in range along the ray (m)::

    stereo:  d_meas = (1 + fb_error) · d_true + disparity_offset_px + field(u, v)
    tof:     r_meas = (1 + scale_error) · r_true + offset_m
                      + wiggle_cos_m · cos(2π r_true / P) + wiggle_sin_m · sin(2π r_true / P) + field(u, v)

``field`` is a smooth surface over the image with no constant term (that is the offset): a sum of
monomials ``u^i v^j``, ``1 <= i + j <= field_order``, of the normalised pixel coordinates
``u = (col - cx) / (W / 2)``, ``v = (row - cy) / (H / 2)`` (the image corner near ``(±1, ±1)``).
Every term is linear in its coefficient, so a calibration is a linear problem in them and their
covariance is that of :attr:`SystematicError.vector`. The same object is what a sim draws
(:meth:`SystematicError.distort`) and what a correction removes (:meth:`SystematicError.correct`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import ConfigError

__all__ = ["FIELD_MAX_ORDER", "SystematicError", "field_basis", "field_terms", "normalised_pixels"]

FloatArray = NDArray[np.float64]
#: Highest order of the image field (held-out error picks the order up to this).
FIELD_MAX_ORDER = 4
#: Newton steps that invert the ToF wiggle: from an error of about the wiggle's amplitude (mm) the
#: first leaves ~1e-7 m, the second ~1e-14 m (quadratic convergence; the curvature is A·(2π/P)²).
_NEWTON_STEPS = 2


def field_terms(order: int) -> list[tuple[int, int]]:
    """Exponents ``(i, j)`` of the field's monomials ``u^i v^j``, ``1 <= i + j <= order``, by degree."""
    if not 0 <= order <= FIELD_MAX_ORDER:
        raise ConfigError(f"must be 0..{FIELD_MAX_ORDER}, got {order}", key="field_order")
    return [(deg - j, j) for deg in range(1, order + 1) for j in range(deg + 1)]


def field_basis(u: ArrayLike, v: ArrayLike, order: int) -> FloatArray:
    """The field's monomials at normalised pixel coordinates, shape ``(N, len(field_terms(order)))``."""
    uu = np.asarray(u, dtype=np.float64).ravel()
    vv = np.asarray(v, dtype=np.float64).ravel()
    terms = field_terms(order)
    out = np.empty((uu.size, len(terms)))
    for k, (i, j) in enumerate(terms):
        out[:, k] = uu ** i * vv ** j
    return out


def normalised_pixels(width: int, height: int, cx: float, cy: float) -> tuple[FloatArray, FloatArray]:
    """Normalised coordinates ``u = (col - cx) / (W/2)``, ``v = (row - cy) / (H/2)`` of every pixel, (H, W) each."""
    cols = (np.arange(width, dtype=np.float64) - cx) / (width / 2.0)
    rows = (np.arange(height, dtype=np.float64) - cy) / (height / 2.0)
    u, v = np.meshgrid(cols, rows)
    return u, v


def _names(kind: str, order: int) -> list[str]:
    head = (["fb_error", "disparity_offset_px"] if kind == "stereo"
            else ["scale_error", "offset_m", "wiggle_cos_m", "wiggle_sin_m"])
    return head + [f"field_u{i}v{j}" for i, j in field_terms(order)]


@dataclass(frozen=True)
class SystematicError:
    """A camera's systematic depth error (see the module docstring for the equations).

    Attributes:
        kind: ``"stereo"`` (structured light too: both measure a disparity) or ``"tof"``.
        fb_error: Stereo: relative error of ``f·B`` (0.01: disparities 1 % too large), dimensionless.
        disparity_offset_px: Stereo: constant disparity offset, px.
        scale_error: ToF: relative range scale error, dimensionless.
        offset_m: ToF: constant range offset, m.
        wiggle_cos_m: ToF: wiggling, the ``cos(2π r / P)`` amplitude, m.
        wiggle_sin_m: ToF: wiggling, the ``sin(2π r / P)`` amplitude, m.
        wiggle_period_m: ToF: the wiggling's period ``P`` in range, m (0: no wiggling term).
        field_order: Order of the image field (0: none).
        field_coeffs: The field's coefficients in :func:`field_terms` order, px (stereo) or m (ToF).
        covariance: Covariance of :attr:`vector` (same order as :attr:`names`), or None when not estimated.
    """

    kind: Literal["stereo", "tof"]
    fb_error: float = 0.0
    disparity_offset_px: float = 0.0
    scale_error: float = 0.0
    offset_m: float = 0.0
    wiggle_cos_m: float = 0.0
    wiggle_sin_m: float = 0.0
    wiggle_period_m: float = 0.0
    field_order: int = 0
    field_coeffs: tuple[float, ...] = ()
    covariance: tuple[tuple[float, ...], ...] | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        if self.kind not in ("stereo", "tof"):
            raise ConfigError(f"must be 'stereo' or 'tof', got {self.kind!r}", key="systematic.kind")
        for name in ("fb_error", "scale_error"):
            value = float(getattr(self, name))
            if not math.isfinite(value) or abs(value) >= 0.5:
                raise ConfigError(f"must be a finite relative error below 0.5, got {value!r}", key=f"systematic.{name}")
        for name in ("disparity_offset_px", "offset_m", "wiggle_cos_m", "wiggle_sin_m", "wiggle_period_m"):
            if not math.isfinite(float(getattr(self, name))):
                raise ConfigError("must be finite", key=f"systematic.{name}")
        if self.wiggle_period_m < 0.0:
            raise ConfigError(f"must be >= 0, got {self.wiggle_period_m}", key="systematic.wiggle_period_m")
        if self.wiggle_period_m > 0.0 and 2.0 * math.pi * math.hypot(self.wiggle_cos_m, self.wiggle_sin_m) \
                >= 0.5 * self.wiggle_period_m:
            # the measured range must grow with the true one, or the error cannot be inverted
            raise ConfigError("wiggle amplitude too large for its period (2π·A/P must stay below 0.5)",
                              key="systematic.wiggle_cos_m")
        n_field = len(field_terms(int(self.field_order)))
        coeffs = tuple(float(c) for c in self.field_coeffs) or (0.0,) * n_field
        if len(coeffs) != n_field or not all(math.isfinite(c) for c in coeffs):
            raise ConfigError(f"order {self.field_order} needs {n_field} finite coefficients, got {len(coeffs)}",
                              key="systematic.field_coeffs")
        object.__setattr__(self, "field_coeffs", coeffs)
        if self.covariance is not None:
            cov = np.asarray(self.covariance, dtype=np.float64)
            k = len(self.names)
            if cov.shape != (k, k) or not np.all(np.isfinite(cov)):
                raise ConfigError(f"must be a finite {k}x{k} matrix, got shape {cov.shape}",
                                  key="systematic.covariance")
            object.__setattr__(self, "covariance", tuple(tuple(float(x) for x in row) for row in cov))

    # ------------------------------------------------------------------ parameters
    @property
    def names(self) -> list[str]:
        """Names of :attr:`vector`'s entries (units in the names; the field's in px or m)."""
        return _names(self.kind, self.field_order)

    @property
    def vector(self) -> FloatArray:
        """The parameters as one vector, in :attr:`names` order."""
        head = ([self.fb_error, self.disparity_offset_px] if self.kind == "stereo"
                else [self.scale_error, self.offset_m, self.wiggle_cos_m, self.wiggle_sin_m])
        return np.array(head + list(self.field_coeffs), dtype=np.float64)

    @classmethod
    def from_vector(cls, kind: Literal["stereo", "tof"], vector: ArrayLike, *, field_order: int,
                    wiggle_period_m: float = 0.0, covariance: ArrayLike | None = None) -> SystematicError:
        """Build from :attr:`vector` (the inverse of it), with an optional covariance."""
        x = np.asarray(vector, dtype=np.float64).ravel()
        head = 2 if kind == "stereo" else 4
        cov = None if covariance is None else tuple(map(tuple, np.asarray(covariance, dtype=np.float64)))
        field_coeffs = tuple(float(c) for c in x[head:])
        if kind == "stereo":
            return cls(kind, fb_error=float(x[0]), disparity_offset_px=float(x[1]), field_order=field_order,
                       field_coeffs=field_coeffs, covariance=cov)
        return cls(kind, scale_error=float(x[0]), offset_m=float(x[1]), wiggle_cos_m=float(x[2]),
                   wiggle_sin_m=float(x[3]), wiggle_period_m=wiggle_period_m, field_order=field_order,
                   field_coeffs=field_coeffs, covariance=cov)

    @property
    def is_zero(self) -> bool:
        """Whether every term is zero (an ideal camera)."""
        return not np.any(self.vector)

    # ------------------------------------------------------------------ the model
    def field_at(self, u: ArrayLike, v: ArrayLike) -> FloatArray:
        """The image field at normalised pixel coordinates, px (stereo) or m (ToF), shaped like ``u``."""
        shape = np.shape(u)
        if self.field_order == 0:
            return np.zeros(shape)
        out: FloatArray = (field_basis(u, v, self.field_order) @ np.asarray(self.field_coeffs)).reshape(shape)
        return out

    def _wiggle(self, r: FloatArray) -> FloatArray:
        if self.wiggle_period_m <= 0.0:
            return np.zeros_like(r)
        phase = 2.0 * math.pi * r / self.wiggle_period_m
        return self.wiggle_cos_m * np.cos(phase) + self.wiggle_sin_m * np.sin(phase)

    def distort(self, true: ArrayLike, u: ArrayLike, v: ArrayLike) -> FloatArray:
        """True disparity (px) or range (m) to what the camera measures, at normalised pixels ``u, v``."""
        t = np.asarray(true, dtype=np.float64)
        if self.kind == "stereo":
            return (1.0 + self.fb_error) * t + self.disparity_offset_px + self.field_at(u, v)
        return (1.0 + self.scale_error) * t + self.offset_m + self._wiggle(t) + self.field_at(u, v)

    def correct(self, measured: ArrayLike, u: ArrayLike, v: ArrayLike) -> FloatArray:
        """Measured disparity (px) or range (m) to the true one: the inverse of :meth:`distort`."""
        m = np.asarray(measured, dtype=np.float64)
        if self.kind == "stereo":
            return (m - self.disparity_offset_px - self.field_at(u, v)) / (1.0 + self.fb_error)
        base = m - self.offset_m - self.field_at(u, v)
        r = base / (1.0 + self.scale_error)
        if self.wiggle_period_m <= 0.0:
            return r
        w = 2.0 * math.pi / self.wiggle_period_m
        for _ in range(_NEWTON_STEPS):
            # Newton on g(r) = (1 + k) r + wiggle(r) - base; g' >= 1 + k - 2πA/P stays near 1
            phase = w * r
            g = (1.0 + self.scale_error) * r + self.wiggle_cos_m * np.cos(phase) + self.wiggle_sin_m * np.sin(phase)
            slope = 1.0 + self.scale_error + w * (self.wiggle_sin_m * np.cos(phase) - self.wiggle_cos_m * np.sin(phase))
            r = r - (g - base) / slope
        return r

    def jacobian(self, true: ArrayLike, u: ArrayLike, v: ArrayLike) -> FloatArray:
        """d(measured)/d(:attr:`vector`) at true values and pixels, shape ``(N, len(names))``."""
        t = np.asarray(true, dtype=np.float64).ravel()
        basis = field_basis(u, v, self.field_order)
        if self.kind == "stereo":
            return np.column_stack([t, np.ones_like(t), basis])
        if self.wiggle_period_m > 0.0:
            phase = 2.0 * math.pi * t / self.wiggle_period_m
            cos, sin = np.cos(phase), np.sin(phase)
        else:
            cos = sin = np.zeros_like(t)
        return np.column_stack([t, np.ones_like(t), cos, sin, basis])

    # ------------------------------------------------------------------ JSON
    def to_dict(self) -> dict[str, Any]:
        """JSON form (``cellcal.systematic/1``): the terms, names, vector and covariance."""
        out: dict[str, Any] = {"schema": "cellcal.systematic/1"}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            out[f.name] = [list(row) for row in value] if f.name == "covariance" and value is not None else (
                list(value) if isinstance(value, tuple) else value)
        out["names"] = self.names
        return out

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], *, where: str = "systematic") -> SystematicError:
        """Parse :meth:`to_dict`'s form; a bad or missing key is one :class:`ConfigError` naming it."""
        if not isinstance(data, Mapping):
            raise ConfigError(f"expected a table, got {type(data).__name__}", key=where)
        known = {f.name for f in dataclasses.fields(cls)}
        kwargs: dict[str, Any] = {}
        for key, value in data.items():
            if key in ("schema", "names"):
                continue
            if key not in known:
                raise ConfigError(f"unknown key {key!r}", key=f"{where}.{key}")
            kwargs[key] = _checked(key, value, where)
        if "kind" not in kwargs:
            raise ConfigError("missing (stereo or tof)", key=f"{where}.kind")
        try:
            return cls(**kwargs)
        except ConfigError as exc:
            raise ConfigError(exc.reason, key=(exc.key or "").replace("systematic", where, 1) or where) from None

    def leftover_sigma(self, names: Sequence[str]) -> FloatArray:
        """1-sigma of the named parameters from :attr:`covariance` (0 where none was estimated)."""
        if self.covariance is None:
            return np.zeros(len(names))
        diag = np.sqrt(np.maximum(np.diag(np.asarray(self.covariance)), 0.0))
        index = {n: i for i, n in enumerate(self.names)}
        return np.array([diag[index[n]] if n in index else 0.0 for n in names])


def _checked(key: str, value: Any, where: str) -> Any:
    """Type-check one JSON value of a :class:`SystematicError` (bools are not numbers)."""
    if key == "kind":
        if not isinstance(value, str):
            raise ConfigError("must be a string", key=f"{where}.kind")
        return value
    if key == "field_order":
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"must be an integer, got {value!r}", key=f"{where}.field_order")
        return value
    if key in ("field_coeffs", "covariance"):
        if value is None and key == "covariance":
            return None
        try:
            arr = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise ConfigError("must be numbers", key=f"{where}.{key}") from None
        if arr.ndim != (1 if key == "field_coeffs" else 2) and arr.size:
            raise ConfigError("has the wrong shape", key=f"{where}.{key}")
        return tuple(arr.tolist()) if key == "field_coeffs" else tuple(map(tuple, arr.tolist()))
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f"must be a number, got {value!r}", key=f"{where}.{key}")
    return float(value)
