"""The HTTP face's tracking and monitoring routes: ``/v1/cells/{cell}/track`` and ``/v1/cells/{cell}/monitor``.

Registered by :func:`cellcal.core.service.http.create_app`. For each activity (:mod:`.watch`):
``POST`` starts a session (202; 409 while the cell runs something), ``GET`` its state (``idle``
before the first), ``DELETE`` or ``POST .../stop`` stops it and answers its state once it has
ended (at most :data:`~cellcal.core.service.watch.STOP_WAIT_S`; 409 when none runs). Starting and
stopping need the token when one is set.
"""

from __future__ import annotations

from enum import Enum
from typing import Any, Literal

from fastapi import FastAPI, Security
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse, Response
from fastapi.security import HTTPBearer
from pydantic import BaseModel, ConfigDict, Field

from cellcal.core.service import schemas
from cellcal.core.service.cell import Service
from cellcal.core.service.watch import ACTIVITIES, MAX_DURATION_S, MAX_FRAMES

__all__ = ["WatchOut", "WatchRequest", "add_watch_routes"]

_ERRORS: dict[int | str, dict[str, Any]] = {code: {"model": schemas.ErrorOut} for code in (400, 404, 413, 422, 429)}
_CHANGING: dict[int | str, dict[str, Any]] = {**_ERRORS, 401: {"model": schemas.ErrorOut},
                                              409: {"model": schemas.ErrorOut}}
_bearer = HTTPBearer(auto_error=False, description="the service's token (when one is set): needed by every request "
                     "that moves the arm or changes state")
_WHAT = {"track": ("tracking", "keep the mount and the plane estimated from the cell's own work (cellcal track: the "
                   "arm read, never moved); change events as track.change and drift.<kind>"),
         "monitor": ("monitoring", "watch the plane for drift against a baseline (cellcal monitor); drift events as "
                     "monitor.drift and drift.monitor")}


class WatchRequest(BaseModel):
    """Start tracking or monitoring (every field optional: an empty body or none is every camera, until stopped)."""

    model_config = ConfigDict(extra="forbid", strict=True)

    camera: str | None = Field(None, max_length=64, description="this camera only (default: every camera)")
    duration_s: float | None = Field(None, gt=0, le=MAX_DURATION_S, description="stop after this many seconds "
                                     "(tracking: of frame time; monitoring: of wall time); default: until stopped")
    max_frames: int | None = Field(None, ge=1, le=MAX_FRAMES, description="stop after this many frames")
    baseline: Literal["frames", "calibration"] = Field(
        "frames", description="monitor: the mean of the first frames, or the camera's calibrated plane seen from the "
        "arm's pose at the start")


class WatchOut(BaseModel):
    """A cell's latest tracking or monitoring session: its state and, per camera, frames, the current estimate
    (tracking: the figures of its track.json, SI units but ``*_deg``; monitoring: the camera's summary), changes,
    whether one is open and the drift events counted."""

    id: str
    kind: Literal["track", "monitor"]
    cell: str
    state: Literal["idle", "starting", "running", "stopping", "stopped", "failed"]
    error: str | None
    options: dict[str, Any] | None
    created_utc: str | None
    finished_utc: str | None
    stop_requested: bool
    cameras: dict[str, dict[str, Any]]
    files: dict[str, list[str]]


def add_watch_routes(app: FastAPI, service: Service, prefix: str) -> None:
    """Add the start, state and stop routes of tracking and monitoring under ``prefix`` (``/v1``)."""
    for kind in ACTIVITIES:
        _add(app, service, prefix, kind)


def _add(app: FastAPI, service: Service, prefix: str, kind: str) -> None:
    path = f"{prefix}/cells/{{cell}}/{kind}"
    doing, what = _WHAT[kind]
    tags: list[str | Enum] = [doing]

    async def start(cell: str, body: WatchRequest | None = None) -> Response:
        options = None if body is None else body.model_dump(exclude_none=True)
        activity = service.watches.start(cell, kind, options)
        return JSONResponse(activity.to_dict(), status_code=202)

    async def state(cell: str) -> Response:
        return JSONResponse(service.watches.state(cell, kind))

    async def stop(cell: str) -> Response:
        return JSONResponse(await run_in_threadpool(service.watches.stop, cell, kind))

    start.__doc__ = f"Start {doing} the cell: {what} (409 while it runs something)."
    state.__doc__ = f"The cell's latest {doing} session: its state, frames, estimate and events (idle before one)."
    stop.__doc__ = f"Stop {doing} and answer its state once it has ended (409 when the cell is not {doing})."
    app.post(path, status_code=202, response_model=WatchOut, responses=_CHANGING, dependencies=[Security(_bearer)],
             tags=tags, operation_id=f"start_{kind}")(start)
    app.get(path, response_model=WatchOut, responses=_ERRORS, tags=tags, operation_id=f"{kind}_state")(state)
    app.delete(path, response_model=WatchOut, responses=_CHANGING, dependencies=[Security(_bearer)], tags=tags,
               operation_id=f"stop_{kind}")(stop)
    app.post(f"{path}/stop", response_model=WatchOut, responses=_CHANGING, dependencies=[Security(_bearer)],
             tags=tags, operation_id=f"stop_{kind}_post")(stop)
