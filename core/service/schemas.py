"""The HTTP face's request and response documents (pydantic models: validation and the OpenAPI schema).

Imported only by :mod:`cellcal.core.service.http`, when the service is served. Units are SI
(metres, radians) unless a name says degrees.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from cellcal.core.service.planepoint import MAX_PIXELS

__all__ = ["CalibrationOut", "CellOut", "ErrorOut", "FlangePose", "HealthOut", "PixelRequest", "PixelsOut",
           "RunOptionsIn", "RunOut", "RunRequest", "RunResultOut"]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)


class ErrorOut(BaseModel):
    """Every error: one line saying why."""

    error: str


class RunOptionsIn(_Strict):
    """A run's options."""

    report: bool = Field(True, description="write the run's report beside its result")
    resume: bool = Field(False, description="continue the interrupted or cancelled run of this kind from its journal")
    plan: Literal["auto", "config"] = Field("auto", description="handeye: auto (inclinations x rolls) or the [plan]")


class RunRequest(_Strict):
    """Start a run on a camera of the cell."""

    kind: Literal["calibrate", "handeye", "depthcal"]
    camera: str = Field(..., max_length=64, description="a camera of the cell on the flange")
    options: RunOptionsIn = Field(default_factory=lambda: RunOptionsIn.model_validate({}))


class Progress(BaseModel):
    """The plan's progress."""

    poses_done: int
    poses_total: int


class RunOut(BaseModel):
    """A run: what was asked, where it stands."""

    id: str
    cell: str
    camera: str
    kind: str
    options: dict[str, Any]
    state: Literal["queued", "running", "ok", "failed", "cancelled"]
    progress: Progress
    error: str | None
    cancel_requested: bool
    result_file: str | None
    report_file: str | None
    created_utc: str
    started_utc: str | None
    finished_utc: str | None


class RunResultOut(BaseModel):
    """A finished run and its result document (as written to its result file)."""

    run: RunOut
    result: dict[str, Any]


class CameraOut(BaseModel):
    """A camera of the cell."""

    name: str
    on: Literal["flange", "base"]
    backend: str | None


class CellOut(BaseModel):
    """A cell: its configuration, cameras and run in progress."""

    name: str
    config: str
    cameras: list[CameraOut]
    active_run: str | None


class HealthOut(BaseModel):
    """The service is up: its cells' runs in progress and its event subscribers."""

    status: Literal["ok", "stopping"]
    cells: dict[str, str | None]
    subscribers: int


class CalibrationOut(BaseModel):
    """A camera's current calibration: the plane in the base frame and the mount, 1-sigma and 95 % half-widths;
    ``covariance`` is the 9x9 of ``parameters`` that ``pixel_to_base`` propagates."""

    kind: Literal["calibrate", "handeye"]
    file: str
    created_utc: str
    confidence: float
    plane_base: dict[str, Any]
    mount: dict[str, Any]
    covariance: list[list[float]]
    parameters: list[str]
    intrinsics: dict[str, Any]


class FlangePose(_Strict):
    """``T_base_flange``: where the flange was when the pixels were seen."""

    translation_m: list[float] = Field(..., min_length=3, max_length=3)
    quaternion_xyzw: list[float] = Field(..., min_length=4, max_length=4, description="a unit quaternion")


class PixelRequest(_Strict):
    """Pixels of the camera (distorted, as the image has them) seen from a flange pose."""

    pixels: list[list[float]] | list[float] = Field(
        ..., description=f"[u, v] or up to {MAX_PIXELS} of them, px")
    flange_pose: FlangePose


class PixelsOut(BaseModel):
    """Points on the calibrated plane in the base frame and their 1-sigma along the base axes (first order, from
    the mount's and plane's covariance; the lens and the flange pose taken as exact); null where the ray misses."""

    cell: str
    camera: str
    calibration: dict[str, str]
    points_m: list[list[float | None]]
    sigma_m: list[list[float | None]]
