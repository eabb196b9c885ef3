"""The HTTP face's history routes (``/v1/history/...``, "the calibration at time T") and ``/metrics``.

Registered by :func:`cellcal.core.service.http.create_app`. The history answers from the
service's :class:`~cellcal.core.service.history.HistoryStore`, where a camera is named
``<cell>/<camera>``; a service without a history answers 404. Times are ISO 8601 with a zone
(``2024-05-01T10:00:00Z``); a time without one is a 422. Listings are pages: pass
``next_cursor`` back as ``cursor`` for the next one.
"""

from __future__ import annotations

from typing import Any, Literal

from fastapi import FastAPI, Query
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse, Response
from pydantic import BaseModel

from cellcal.core.service import schemas
from cellcal.core.service.cell import Service
from cellcal.core.service.errors import NotFoundError, RequestError
from cellcal.core.service.history import MAX_PAGE, HistoryStore
from cellcal.core.service.recorder import history_camera
from cellcal.devices.errors import ConfigError

__all__ = ["CalibrationAtOut", "EventPage", "RunPage", "add_history_routes", "calibration_at"]

_ERRORS: dict[int | str, dict[str, Any]] = {code: {"model": schemas.ErrorOut} for code in (404, 422, 429)}


class RunRecordOut(BaseModel):
    """A run as the history keeps it (``camera`` is ``<cell>/<camera>``)."""

    id: int
    kind: str
    camera: str
    source: str
    started: str
    ended: str | None
    status: Literal["running", "ok", "failed", "cancelled"]
    result: Any
    reason: str | None


class RunPage(BaseModel):
    """One page of runs, newest first."""

    items: list[RunRecordOut]
    next_cursor: str | None


class EventRecordOut(BaseModel):
    """An event published on the service's bus, as the history keeps it."""

    id: int
    camera: str
    kind: str
    at: str
    detail: Any


class EventPage(BaseModel):
    """One page of events, oldest first."""

    items: list[EventRecordOut]
    next_cursor: str | None


class AppliedOut(BaseModel):
    """A calibration put into use: the mount (``T_flange_camera``) or the base-frame plane, with its covariance."""

    id: int
    camera: str
    what: str
    value: Any
    covariance: Any
    run_id: int | None
    applied: str


class CalibrationAtOut(BaseModel):
    """The calibration a camera used at time ``at``: the last mount and plane applied at or before it."""

    cell: str
    camera: str
    at: str
    mount: AppliedOut | None
    plane: AppliedOut | None


def _store(service: Service) -> HistoryStore:
    if service.history is None:
        raise NotFoundError("this service keeps no history (cellcal serve keeps one unless told otherwise)")
    return service.history


def _camera_key(service: Service, cell: str | None, camera: str | None) -> str | None:
    """The store's camera name for the filters given (``camera`` alone: the service's only cell)."""
    if cell is None and camera is None:
        return None
    if cell is None:
        if len(service.cells) != 1:
            raise RequestError("give 'cell' with 'camera': this service has several cells")
        cell = next(iter(service.cells))
    found = service.cell(cell)
    if camera is None:
        raise RequestError("give 'camera' with 'cell' (the history is kept per camera)")
    found.camera_config(camera)
    key: str = history_camera(cell, camera)
    return key


def _asked(call: Any) -> Any:
    """Run a store call; a bad time, cursor or page size is the client's (422)."""
    try:
        return call()
    except ConfigError as exc:
        raise RequestError(str(exc)) from None


def calibration_at(service: Service, cell: str, camera: str, at: str) -> dict[str, Any]:
    """JSON of :class:`CalibrationAtOut`: camera ``camera`` of ``cell`` as it was at ``at`` (ISO 8601 with a zone).

    Raises:
        NotFoundError: No such cell or camera, no history, or nothing applied by then.
        RequestError: ``at`` is not an ISO 8601 time with a zone.
    """
    service.cell(cell).camera_config(camera)
    store = _store(service)
    found = _asked(lambda: store.state_at(history_camera(cell, camera), at))
    if not found:
        raise NotFoundError(f"camera {camera!r} of cell {cell!r} had no calibration in use at {at}")
    return {"cell": cell, "camera": camera, "at": at,
            **{what: (found[what].as_dict() if what in found else None) for what in ("mount", "plane")}}


def add_history_routes(app: FastAPI, service: Service, prefix: str) -> None:
    """Register ``GET {prefix}/history/runs``, ``.../runs/{id}``, ``.../events`` and ``GET /metrics``."""

    @app.get(f"{prefix}/history/runs", response_model=RunPage, responses=_ERRORS, tags=["history"])
    async def history_runs(cell: str | None = None, camera: str | None = None,
                           kind: Literal["calibrate", "handeye", "depthcal", "fixed-handeye"] | None = None,
                           status: Literal["running", "ok", "failed", "cancelled"] | None = None,
                           limit: int = Query(50, ge=1, le=MAX_PAGE), cursor: str | None = None) -> Response:
        """The runs the history keeps, newest first (filters: the cell and camera, the kind, the status)."""
        key = _camera_key(service, cell, camera)
        store = _store(service)
        page = await run_in_threadpool(_asked, lambda: store.list_runs(camera=key, kind=kind, status=status,
                                                                       limit=limit, cursor=cursor))
        return JSONResponse({"items": [r.as_dict() for r in page.items], "next_cursor": page.next_cursor})

    @app.get(f"{prefix}/history/runs/{{history_id}}", response_model=RunRecordOut, responses=_ERRORS,
             tags=["history"])
    async def history_run(history_id: int) -> Response:
        """One run of the history, with its result document or the reason it did not end ok."""
        store = _store(service)
        found = await run_in_threadpool(store.run, history_id)
        if found is None:
            raise NotFoundError(f"no run {history_id} in the history")
        return JSONResponse(found.as_dict())

    @app.get(f"{prefix}/history/events", response_model=EventPage, responses=_ERRORS, tags=["history"])
    async def history_events(since: str | None = None, until: str | None = None, cell: str | None = None,
                             camera: str | None = None, kind: str | None = Query(None, max_length=200),
                             limit: int = Query(MAX_PAGE, ge=1, le=MAX_PAGE), cursor: str | None = None) -> Response:
        """The events published on the service's bus with ``since <= at < until``, oldest first."""
        key = _camera_key(service, cell, camera)
        store = _store(service)
        page = await run_in_threadpool(_asked, lambda: store.events(since, until, camera=key, kind=kind,
                                                                    limit=limit, cursor=cursor))
        return JSONResponse({"items": [e.as_dict() for e in page.items], "next_cursor": page.next_cursor})

    @app.get("/metrics", include_in_schema=False)  # outside the versioned API: Prometheus' own format and path
    async def metrics() -> Response:
        """The service's metrics in Prometheus' text format (no token needed: it only reads)."""
        if service.metrics is None:
            raise NotFoundError("no metrics: prometheus-client is not installed (the 'serve' extra)")
        from cellcal.core.service.metrics import CONTENT_TYPE

        body = await run_in_threadpool(service.metrics.exposition)
        return Response(body, media_type=CONTENT_TYPE)
