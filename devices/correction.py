"""A camera's depth correction applied to its frames: ``[camera.correction] file = "depthcal.json"`` (ADR 0058).

:func:`load_correction_file` reads the :class:`~cellcal.devices.systematic.SystematicError` a
``cellcal depthcal`` run wrote (``cellcal.depthcal/1``, its ``correction`` key) or a bare
``cellcal.systematic/1`` document; :func:`correct_frame` removes it from a frame (stereo: the
disparity ``d = f·B/Z`` of every valid pixel; ToF: its range), moving each point along its own
ray, and states in the frame's :class:`~cellcal.devices.measurement.MeasurementModel` the
allowance the correction leaves (its covariance); :class:`CorrectedCamera` is the wrapper the
registry puts around a camera whose ``[camera]`` table has a ``correction`` table, so that every
frame of every command is corrected before any fit (:func:`camera_with_correction`).
"""

from __future__ import annotations

import dataclasses
import math
import os
import stat
import threading
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from . import boundedjson
from .base import BackendContext
from .camera import Camera3D
from .config import parse_section
from .errors import CalibrationError, CellcalError, ConfigError
from .forwarding import ForwardingCamera
from .measurement import DEFAULT_WIGGLE, UNKNOWN_MODEL, MeasurementModel
from .systematic import SystematicError, field_basis, normalised_pixels
from .types import Frame, Intrinsics

__all__ = ["CORRECTION_KEY", "MAX_CORRECTION_BYTES", "CorrectedCamera", "CorrectionSection", "camera_with_correction",
           "correct_frame", "corrected_model", "leftover_allowance", "leftover_wiggle_m", "load_correction_file",
           "wiggle_passes"]

#: The dotted key every problem with the correction file is reported under.
CORRECTION_KEY = "camera.correction.file"
#: Largest correction file read, bytes (a depthcal result is a few tens of KB; its pictures are PNG files).
MAX_CORRECTION_BYTES = 4 << 20
#: Schema prefixes accepted: a ``cellcal depthcal`` result (its ``correction`` key) or the bare error.
DEPTHCAL_SCHEMA_PREFIX = "cellcal.depthcal/"
SYSTEMATIC_SCHEMA_PREFIX = "cellcal.systematic/"

F32 = NDArray[np.float32]


# ---------------------------------------------------------------------------------------------- the file
def _read_bounded(path: Path) -> bytes:
    """The bytes of the regular file ``path`` (at most :data:`MAX_CORRECTION_BYTES`); OSError/ValueError as raised."""
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)  # O_NONBLOCK: a FIFO opens at once
    try:
        mode = os.fstat(fd).st_mode
        if stat.S_ISDIR(mode):
            raise ValueError("is a directory, not a depthcal.json")
        if not stat.S_ISREG(mode):
            raise ValueError("not a regular file (a FIFO, device or socket)")
        chunks: list[bytes] = []
        size = 0
        while size <= MAX_CORRECTION_BYTES:
            chunk = os.read(fd, MAX_CORRECTION_BYTES + 1 - size)
            if not chunk:
                break
            chunks.append(chunk)
            size += len(chunk)
    finally:
        os.close(fd)
    if size > MAX_CORRECTION_BYTES:
        raise ValueError(f"larger than {MAX_CORRECTION_BYTES} bytes; not a depthcal.json")
    return b"".join(chunks)


def load_correction_file(path: str | Path, *, source: str | None = None, key: str = CORRECTION_KEY
                         ) -> SystematicError:
    """The correction in ``path``: a ``cellcal.depthcal/1`` result's ``correction`` or a bare ``cellcal.systematic/1``.

    The read is bounded (a regular file of at most :data:`MAX_CORRECTION_BYTES`, JSON nested at
    most :data:`~cellcal.devices.boundedjson.MAX_DEPTH` deep). ``core.depthcal.load_correction``
    reads through this function.

    Args:
        path: The file (already resolved against the configuration's directory).
        source: The configuration the key comes from, for the message.
        key: The key the message names.

    Raises:
        ConfigError: One line naming ``key``, the file and what was wrong (missing, unreadable,
            not JSON, another schema, no correction, a bad value in it).
    """
    shown = str(path)
    try:
        raw = _read_bounded(Path(path))
    except FileNotFoundError:
        raise ConfigError(f"{shown}: file not found", source=source, key=key) from None
    except (OSError, ValueError) as exc:  # ValueError: a NUL byte in the path, or ours above
        raise ConfigError(f"{shown}: cannot read: {getattr(exc, 'strerror', None) or exc}", source=source,
                          key=key) from None
    try:
        data = boundedjson.loads(raw)
    except (ValueError, RecursionError) as exc:
        raise ConfigError(f"{shown}: not JSON ({str(exc).splitlines()[0][:120]})", source=source, key=key) from None
    if not isinstance(data, Mapping):
        raise ConfigError(f"{shown}: expected a JSON object, got {type(data).__name__}", source=source, key=key)
    schema = str(data.get("schema", ""))
    if schema.startswith(DEPTHCAL_SCHEMA_PREFIX):
        table = data.get("correction")
        if table is None:
            raise ConfigError(f"{shown}: the depthcal result holds no correction (did the run fail?)",
                              source=source, key=key)
        where = "correction"
    elif schema.startswith(SYSTEMATIC_SCHEMA_PREFIX):
        table, where = data, "systematic"
    else:
        raise ConfigError(f"{shown}: schema {schema or 'missing'!r} is neither {DEPTHCAL_SCHEMA_PREFIX}N "
                          f"(cellcal depthcal's result) nor {SYSTEMATIC_SCHEMA_PREFIX}N", source=source, key=key)
    try:
        return SystematicError.from_dict(table, where=where)
    except ConfigError as exc:
        raise ConfigError(f"{shown}: {exc.key or where}: {exc.reason}", source=source, key=key) from None


@dataclass(frozen=True)
class CorrectionSection:
    """The ``[camera.correction]`` table: a depth correction removed from every frame before every fit (ADR 0058).

    The camera is wrapped so that calibrate, handeye, monitor, track, record and the live view see
    corrected frames, whose measurement model states the systematic allowance the correction's
    covariance leaves (scale, offset, the field at the image corner) in place of the vendor's.
    ``cellcal calibrate --check`` shows the correction; a missing or bad file stops every command
    with one line naming ``camera.correction.file``.
    """

    file: str = field(metadata={
        "doc": "the depthcal.json of 'cellcal depthcal' (its correction) or a cellcal.systematic/1 JSON; "
               "a relative path is read from the configuration file's folder"})


def correction_from_table(table: Any, context: BackendContext) -> tuple[SystematicError, str]:
    """A ``[camera.correction]`` table (:class:`CorrectionSection`): the correction and its resolved path.

    Raises:
        ConfigError: Naming ``camera.correction`` (not a table, an unknown key) or
            ``camera.correction.file`` (missing, not a string, a bad file).
    """
    where = f"{context.section or 'camera'}.correction"
    if not isinstance(table, Mapping):
        raise ConfigError(f"expected a table with file = \"depthcal.json\", got {type(table).__name__}",
                          source=context.source, key=where)
    section = parse_section(CorrectionSection, table, where=where, source=context.source)
    if not section.file.strip():
        raise ConfigError("empty; expected the path of a depthcal.json", source=context.source, key=f"{where}.file")
    path = Path(section.file).expanduser()
    if not path.is_absolute() and context.source and Path(context.source).is_file():
        path = context.base_dir / path  # relative to the configuration file
    return load_correction_file(path, source=context.source, key=f"{where}.file"), str(path)


# ---------------------------------------------------------------------------------------------- the model
def leftover_allowance(correction: SystematicError) -> tuple[float, float, float] | None:
    """``(scale, offset, field)`` 1-sigma the correction leaves, from its covariance; None without one.

    scale: of ``fb_error`` / ``scale_error``; offset: of the disparity offset (px) or of the range
    offset (m) (the wiggle's is :func:`leftover_wiggle_m`); field: the largest 1-sigma of the field over the four
    image corners ``u, v = ±1`` (``b^T Σ b``, ``b`` the field's monomials there; 0 without a field).
    """
    if correction.covariance is None:
        return None
    cov = np.asarray(correction.covariance, dtype=np.float64)
    names = correction.names
    index = {n: i for i, n in enumerate(names)}
    scale_name, offset_name = (("fb_error", "disparity_offset_px") if correction.kind == "stereo"
                               else ("scale_error", "offset_m"))
    scale = math.sqrt(max(cov[index[scale_name], index[scale_name]], 0.0))
    offset_var = max(cov[index[offset_name], index[offset_name]], 0.0)
    field = 0.0
    if correction.field_order > 0:
        f = [i for i, n in enumerate(names) if n.startswith("field_")]
        basis = field_basis([1.0, -1.0, 1.0, -1.0], [1.0, 1.0, -1.0, -1.0], correction.field_order)
        var = np.einsum("ni,ij,nj->n", basis, cov[np.ix_(f, f)], basis)
        field = math.sqrt(max(float(var.max()), 0.0))
    return scale, math.sqrt(offset_var), field


def _check_kind(model: MeasurementModel, correction: SystematicError) -> None:
    if correction.kind == "stereo" and not model.triangulating:
        raise CalibrationError(f"{CORRECTION_KEY}: a stereo correction needs a camera that measures a disparity "
                               f"(stereo or structured_light with f·B); this one states {model.kind}")
    if correction.kind == "tof" and model.kind not in ("tof", "unknown"):
        raise CalibrationError(f"{CORRECTION_KEY}: a tof (range) correction on a {model.kind} camera; "
                               "correct a disparity camera with a stereo correction")


def corrected_model(model: MeasurementModel, correction: SystematicError) -> MeasurementModel:
    """``model`` with the systematic allowance the correction leaves (unchanged when it has no covariance).

    Raises:
        CalibrationError: If the correction's kind does not fit the model's (a stereo correction needs f·B).
    """
    _check_kind(model, correction)
    left = leftover_allowance(correction)
    if left is None:
        return model
    out = dataclasses.replace(model, scale_allowance=left[0], offset_allowance=left[1], field_allowance=left[2])
    if correction.kind == "tof":
        out = dataclasses.replace(out, wiggle_allowance_m=leftover_wiggle_m(correction),
                                  wiggle_period_m=correction.wiggle_period_m or model.wiggle[1])
    return out


def leftover_wiggle_m(correction: SystematicError) -> float:
    """ToF: the wiggle's 1-sigma amplitude the correction leaves (largest eigenvalue of its cos/sin block), m.

    A correction that fitted no wiggle (period 0) or has no covariance leaves it unknown: the
    default allowance (:data:`~cellcal.devices.measurement.DEFAULT_WIGGLE`), never 0.
    """
    if correction.covariance is None or correction.wiggle_period_m <= 0.0:
        return DEFAULT_WIGGLE[0]
    cov = np.asarray(correction.covariance, dtype=np.float64)
    index = {n: i for i, n in enumerate(correction.names)}
    w = [index["wiggle_cos_m"], index["wiggle_sin_m"]]
    return math.sqrt(max(float(np.linalg.eigvalsh(cov[np.ix_(w, w)])[-1]), 0.0))


# ---------------------------------------------------------------------------------------------- the frame
class _Maps:
    """Per (intrinsics, correction): the offset map (constant + field) as the arithmetic takes it, and the model.

    Stereo: ``offset + field`` (px); ToF: ``(offset + field) / (1 + scale_error)`` (m), float32 (H, W).
    """

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.offsets: dict[tuple[Any, ...], F32] = {}
        self.models: tuple[MeasurementModel, SystematicError, MeasurementModel] | None = None

    def offset(self, intr: Intrinsics, correction: SystematicError) -> F32:
        key = (intr.width, intr.height, intr.cx, intr.cy, correction)
        with self.lock:
            found = self.offsets.get(key)
        if found is not None:
            return found
        u, v = normalised_pixels(intr.width, intr.height, intr.cx, intr.cy)
        if correction.kind == "stereo":
            full = correction.disparity_offset_px + correction.field_at(u, v)
        else:
            full = (correction.offset_m + correction.field_at(u, v)) / (1.0 + correction.scale_error)
        out: F32 = np.ascontiguousarray(full, dtype=np.float32)
        out.setflags(write=False)
        with self.lock:
            if len(self.offsets) >= 8:
                self.offsets.clear()
            self.offsets[key] = out
        return out

    def model(self, model: MeasurementModel, correction: SystematicError) -> MeasurementModel:
        last = self.models
        if last is not None and last[0] is model and last[1] is correction:
            return last[2]
        out = corrected_model(model, correction)
        self.models = (model, correction, out)
        return out


_MAPS = _Maps()
#: The ToF wiggle is inverted by fixed-point passes until their error bound ``R s^n`` is below this, m (below
#: half a float32 step of a range beyond 1 m: the frame stores no finer).
_WIGGLE_TOLERANCE_M = 5e-8
_MAX_WIGGLE_PASSES = 8


def _stereo_ratio(frame: Frame, correction: SystematicError, offset: F32) -> tuple[F32, NDArray[np.bool_]]:
    """``Z'/Z = d/d' = f·B (1 + e) / (f·B - Z (offset + field))``, NaN where that is not positive; and where."""
    fb = frame.measurement.fb_px_m
    den = frame.xyz[..., 2] * offset                      # Z (offset + field)
    np.subtract(np.float32(fb), den, out=den)
    bad = ~(den > 0)                                      # NaN (invalid) or a disparity corrected to <= 0
    den[bad] = np.nan
    ratio: F32 = np.divide(np.float32(fb * (1.0 + correction.fb_error)), den, out=den)
    return ratio, bad


def wiggle_passes(correction: SystematicError) -> int:
    """Fixed-point passes :func:`correct_frame` makes to invert the ToF wiggle (0 without one).

    ``r' = b - R cos(ω r' - ψ)`` (``R`` the wiggle's amplitude over ``1 + k``, ``ω = 2π/P``) contracts
    by ``s = ωR`` per pass from an error of at most ``R``: ``n`` passes leave ``R s^n``, made at most
    :data:`_WIGGLE_TOLERANCE_M`.
    """
    if correction.wiggle_period_m <= 0.0:
        return 0
    amp = math.hypot(correction.wiggle_cos_m, correction.wiggle_sin_m) / (1.0 + correction.scale_error)
    if amp <= _WIGGLE_TOLERANCE_M:
        return 0
    rate = 2.0 * math.pi / correction.wiggle_period_m * amp
    if rate >= 0.5:
        return _MAX_WIGGLE_PASSES
    return min(_MAX_WIGGLE_PASSES, max(1, math.ceil(math.log(_WIGGLE_TOLERANCE_M / amp) / math.log(rate))))


def _tof_ratio(frame: Frame, correction: SystematicError, offset: F32) -> tuple[F32, NDArray[np.bool_]]:
    """``r'/r = (r - offset - field) / ((1 + k) r)`` (wiggle: fixed-point passes); NaN where ``r' <= 0``."""
    r = frame.distance
    k1 = 1.0 + correction.scale_error
    passes = wiggle_passes(correction)
    if passes:
        base = r / np.float32(k1)
        base -= offset                                     # (r - offset - field) / (1 + k)
        omega = np.float32(2.0 * math.pi / correction.wiggle_period_m)
        amp = np.float32(math.hypot(correction.wiggle_cos_m, correction.wiggle_sin_m) / k1)
        psi = np.float32(math.atan2(correction.wiggle_sin_m, correction.wiggle_cos_m))
        new = base.copy()
        for _ in range(passes):   # r' = base - (c cos ωr' + s sin ωr')/(1+k) = base - R cos(ωr' - ψ)
            np.multiply(new, omega, out=new)
            np.subtract(new, psi, out=new)
            np.cos(new, out=new)
            np.multiply(new, amp, out=new)
            np.subtract(base, new, out=new)
        ratio: F32 = np.divide(new, r, out=new)
    else:
        ratio = np.divide(offset, r)
        np.subtract(np.float32(1.0 / k1), ratio, out=ratio)   # 1/(1+k) - (offset + field) / ((1+k) r)
    bad = ~(ratio > 0)
    ratio[bad] = np.nan
    return ratio, bad


def correct_frame(frame: Frame, correction: SystematicError, *, file: str | None = None) -> Frame:
    """``frame`` with ``correction`` removed: each valid pixel's point moved along its ray to the corrected depth.

    Stereo: ``d = f·B/Z`` (``Z`` the point's z, ``f·B`` the frame's model) is corrected to
    ``d' = (d - offset - field(u, v)) / (1 + fb_error)`` and the point scaled by ``Z'/Z = d/d'``;
    ToF: the range ``r`` (``distance``) to ``r'`` (the wiggle inverted as :func:`wiggle_passes` says) and
    the point scaled by ``r'/r``. ``u, v`` are the normalised pixel coordinates of the frame's
    intrinsics (the offset map is computed once per intrinsics and correction). A pixel whose
    corrected value is not finite or not positive becomes invalid (NaN). The arithmetic is float32
    (the frame's): the corrected point agrees with :meth:`SystematicError.correct` to a relative
    ``1e-6`` (a few float32 ulps). Metadata gains ``depth_correction``; the model states the
    allowance the correction leaves (:func:`corrected_model`).

    Raises:
        CalibrationError: If the frame was corrected already, or the correction's kind does not fit
            the frame's model.
    """
    done = frame.metadata.get("depth_correction")
    if isinstance(done, Mapping) and done.get("applied"):
        raise CalibrationError(f"{CORRECTION_KEY}: the frame was corrected already (a correction applied twice)")
    model = _MAPS.model(frame.measurement, correction)
    offset = _MAPS.offset(frame.intrinsics, correction)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        ratio, bad = (_stereo_ratio if correction.kind == "stereo" else _tof_ratio)(frame, correction, offset)
        xyz = np.stack((ratio, ratio, ratio), axis=-1)     # (H, W, 3) contiguous: 3-8x a broadcast multiply
        np.multiply(xyz, frame.xyz, out=xyz)
        distance = np.multiply(frame.distance, ratio, out=ratio)
    valid = frame.valid
    if np.count_nonzero(bad) != valid.size - np.count_nonzero(valid):   # a valid pixel corrected to nothing
        valid = valid & ~bad
    note: dict[str, Any] = {"applied": True, "kind": correction.kind, "field_order": correction.field_order,
                            "names": correction.names, "vector": [float(x) for x in correction.vector],
                            "allowance": list(model.allowance)}
    if file is not None:
        note["file"] = file
    return dataclasses.replace(frame, xyz=xyz, distance=distance, valid=valid, measurement=model,
                               metadata={**frame.metadata, "depth_correction": note})


# ---------------------------------------------------------------------------------------------- the camera
class CorrectedCamera(ForwardingCamera):
    """A camera whose every frame has the configured correction removed (:func:`correct_frame`).

    Its :attr:`measurement_model` is the inner camera's with the allowance the correction leaves.
    :meth:`raw_capture` (and :attr:`raw`) give the uncorrected frames (``cellcal depthcal`` fits on
    them). Other attributes (a simulated camera's ``world``, a backend's ``config``) are the inner
    camera's.

    Args:
        inner: The configured camera.
        correction: What to remove.
        file: Where the correction was read from (in each frame's metadata and in ``--check``).
    """

    def __init__(self, inner: Camera3D, correction: SystematicError, *, file: str | None = None) -> None:
        super().__init__(inner)
        self.correction = correction
        self.correction_file = file
        try:
            known = inner.measurement_model
        except CellcalError:   # a backend that can only tell once connected: checked at the first frame
            known = UNKNOWN_MODEL
        if known.known:   # a mismatch the configuration alone shows is a configuration error, before connecting
            try:
                _check_kind(known, correction)
            except CalibrationError as exc:
                raise ConfigError(str(exc).split(": ", 1)[1], key=CORRECTION_KEY) from None

    def __getattr__(self, name: str) -> Any:
        inner = self.__dict__.get("inner")
        if inner is None or name.startswith("_"):
            raise AttributeError(name)
        return getattr(inner, name)

    @property
    def raw(self) -> Camera3D:
        """The uncorrected camera (connected and closed through this wrapper)."""
        return self.inner

    def raw_capture(self, timeout: float | None = None) -> Frame:
        """An uncorrected frame (what ``cellcal depthcal`` fits on)."""
        self._require_connected("capture")
        return self.inner.capture(timeout)

    def _capture(self, timeout: float) -> Frame:
        return correct_frame(self.inner.capture(timeout), self.correction, file=self.correction_file)

    def _measurement_model(self) -> MeasurementModel:
        return _MAPS.model(self.inner.measurement_model, self.correction)

    def describe_correction(self) -> str:
        """One line for ``--check``: the file, the kind, the field order and the allowance it leaves."""
        left = leftover_allowance(self.correction)
        unit = "px" if self.correction.kind == "stereo" else "m"
        rest = ("no covariance: the model's allowance kept" if left is None else
                f"leaves scale {left[0]:.3g}, offset {left[1]:.3g} {unit}, field {left[2]:.3g} {unit} (1-sigma)")
        return (f"{self.correction_file or '(in memory)'}: {self.correction.kind}, field order "
                f"{self.correction.field_order}; {rest}")


def camera_with_correction(camera: Camera3D, table: Any, context: BackendContext, *, apply: bool = True
                           ) -> Camera3D:
    """``camera`` wrapped in :class:`CorrectedCamera` for the ``[camera.correction]`` ``table``.

    The table is read and checked even when ``apply`` is False (``cellcal depthcal`` takes the raw camera).

    Raises:
        ConfigError: See :func:`correction_from_table`; a correction whose kind does not fit the
            camera's stated model.
    """
    correction, file = correction_from_table(table, context)
    if not apply:
        return camera
    try:
        return CorrectedCamera(camera, correction, file=file)
    except ConfigError as exc:
        raise ConfigError(exc.reason, source=context.source,
                          key=f"{context.section or 'camera'}.correction.file") from None
