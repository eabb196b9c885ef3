"""The service's HTTP face (FastAPI): a thin adapter over :class:`~cellcal.core.service.cell.Service`, under ``/v1/``.

Its OpenAPI schema is served at ``/v1/openapi.json`` (a copy is kept in
``docs/service/openapi-v1.json``). Every error is a 4xx (or a 500 for a bug) with the body
``{"error": "<one line>"}``: 400 malformed JSON, 401 a state-changing request without the
token (when one is set), 404 no such cell, camera or run, 409 the cell is busy or the run
has ended, 413 a body over the bound, 422 a value of the wrong type or out of range, 429
too many requests. The history's routes and ``/metrics`` are :mod:`.http_history`'s. Imported only
when the service is served (fastapi is the ``serve`` extra).
"""

from __future__ import annotations

import asyncio
import json
import logging
import re
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

import numpy as np
from fastapi import FastAPI, Query, Request, Security
from fastapi.concurrency import run_in_threadpool
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response, StreamingResponse
from fastapi.security import HTTPBearer
from starlette.exceptions import HTTPException
from starlette.requests import ClientDisconnect

from cellcal.core.service import schemas
from cellcal.core.service.cell import PixelsOnPlane, Service
from cellcal.core.service.errors import RequestError, ServiceError
from cellcal.core.service.http_history import CalibrationAtOut, add_history_routes, calibration_at
from cellcal.core.service.http_watch import add_watch_routes
from cellcal.core.service.httpguard import (
    DEFAULT_BURST,
    DEFAULT_RATE_PER_S,
    MAX_BODY_BYTES,
    BodyLimit,
    RateLimit,
    Receive,
    Scope,
    Send,
    TokenBucket,
    check_bearer,
    error_body,
    send_error,
)
from cellcal.devices.errors import CellcalError

__all__ = ["API_PREFIX", "EVENT_KEEPALIVE_S", "create_app", "openapi_document"]

log = logging.getLogger(__name__)

API_PREFIX = "/v1"
#: Seconds between keep-alive comments of an idle event stream.
EVENT_KEEPALIVE_S = 15.0
#: Batches of more pixels than this are mapped off the event loop.
_INLINE_PIXELS = 2000
#: Requests that move the arm or change state: they need the token when one is set.
STATE_CHANGING = re.compile(r"/v1/cells/[^/]+/(runs|track|monitor|track/stop|monitor/stop)|/v1/runs/[^/]+/cancel")
#: ``DELETE`` requests that change state (stopping tracking or monitoring): they need the token too.
STOPPING = re.compile(r"/v1/cells/[^/]+/(track|monitor)")
_ERRORS: dict[int | str, dict[str, Any]] = {code: {"model": schemas.ErrorOut} for code in (400, 404, 413, 422, 429)}
_bearer = HTTPBearer(auto_error=False, description="the service's token (when one is set): needed by every request "
                     "that moves the arm or changes state")


class _Auth:
    """401 for a state-changing request without the right bearer token (checked before its body is read)."""

    def __init__(self, app: Any, token: str | None) -> None:
        self.app = app
        self.token = token

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        method, path = scope.get("method"), scope.get("path", "")
        if scope["type"] == "http" and ((method == "POST" and STATE_CHANGING.fullmatch(path))
                                        or (method == "DELETE" and STOPPING.fullmatch(path))):
            header = next((v.decode("latin-1") for k, v in scope.get("headers", ()) if k == b"authorization"), None)
            why = check_bearer(header, self.token)
            if why is not None:
                await send_error(send, 401, why, [(b"www-authenticate", b"Bearer")])
                return
        await self.app(scope, receive, send)


def _error(status: int, message: str, headers: dict[str, str] | None = None) -> Response:
    return Response(error_body(message), status_code=status, media_type="application/json", headers=headers)


def _validation_message(exc: RequestValidationError) -> tuple[int, str]:
    """400 for a body that is not JSON, 422 for a value of the wrong type: one line naming the first problem."""
    errors = exc.errors()
    first = errors[0] if errors else {}
    if first.get("type") == "json_invalid":
        return 400, f"malformed JSON: {first.get('ctx', {}).get('error', 'cannot be parsed')}"
    where = ".".join(str(p) for p in first.get("loc", ()))
    more = f" (and {len(errors) - 1} more)" if len(errors) > 1 else ""
    return 422, f"{where}: {first.get('msg', 'invalid')}{more}"


def _install_error_handlers(app: FastAPI) -> None:
    @app.exception_handler(RequestValidationError)
    async def invalid(_request: Request, exc: RequestValidationError) -> Response:
        return _error(*_validation_message(exc))

    @app.exception_handler(HTTPException)
    async def http_error(_request: Request, exc: HTTPException) -> Response:
        detail = exc.detail if isinstance(exc.detail, str) else json.dumps(exc.detail)
        return _error(exc.status_code, detail, getattr(exc, "headers", None))

    @app.exception_handler(ClientDisconnect)
    async def gone(_request: Request, _exc: ClientDisconnect) -> Response:
        return Response(status_code=499)  # nobody reads it (the body limit has answered 413, or the client left)

    @app.exception_handler(ServiceError)
    async def refused(_request: Request, exc: ServiceError) -> Response:
        return _error(exc.status, str(exc))

    @app.exception_handler(CellcalError)
    async def cellcal_error(_request: Request, exc: CellcalError) -> Response:
        return _error(409, f"cannot answer with the cell's current state: {exc}")

    @app.exception_handler(Exception)
    async def bug(_request: Request, exc: Exception) -> Response:
        log.error("internal error: %s: %s", type(exc).__name__, exc)
        return _error(500, f"internal error ({type(exc).__name__}); the service keeps running")


def _json(document: Any, status: int = 200) -> Response:
    return JSONResponse(document, status_code=status)


def _dumps_array(values: np.ndarray) -> str:
    """JSON text of an (N, 3) float array, NaN as null."""
    text = json.dumps(values.tolist())
    return text.replace("NaN", "null") if np.isnan(values).any() else text


def _pixels_body(cell: str, camera: str, result: PixelsOnPlane) -> bytes:
    c = result.calibration
    head = json.dumps({"cell": cell, "camera": camera,
                       "calibration": {"kind": c.kind, "file": str(c.path), "created_utc": c.created_utc}})
    # the arrays are written by hand: far faster than a generic encoder for 100 000 points
    return (f'{head[:-1]}, "points_m": {_dumps_array(result.points_m)}, '
            f'"sigma_m": {_dumps_array(result.sigma_m)}}}').encode()


def _inline_refs(schema: dict[str, Any]) -> dict[str, Any]:
    """``schema`` with its ``$defs`` references replaced by the definitions (an OpenAPI request body of its own)."""
    defs = schema.pop("$defs", {})

    def walk(node: Any) -> Any:
        if isinstance(node, dict):
            ref = node.get("$ref")
            if isinstance(ref, str) and ref.startswith("#/$defs/"):
                return walk(defs[ref.removeprefix("#/$defs/")])
            return {k: walk(v) for k, v in node.items()}
        if isinstance(node, list):
            return [walk(v) for v in node]
        return node

    return walk(schema)  # type: ignore[no-any-return]


def _add_routes(app: FastAPI, service: Service) -> None:
    """The ``/v1/`` routes, in the order the OpenAPI schema lists them."""
    _cell_routes(app, service)
    _run_routes(app, service)
    _camera_routes(app, service)


def _cell_routes(app: FastAPI, service: Service) -> None:
    v = API_PREFIX

    @app.get(f"{v}/health", response_model=schemas.HealthOut, tags=["service"])
    async def health() -> Response:
        """The service is up."""
        return _json(service.health())

    @app.get(f"{v}/cells", response_model=list[schemas.CellOut], tags=["cells"])
    async def cells() -> Response:
        """The cells served."""
        return _json([c.describe() for c in service.cells.values()])

    @app.get(f"{v}/cells/{{cell}}", response_model=schemas.CellOut, responses=_ERRORS, tags=["cells"])
    async def cell(cell: str) -> Response:
        """A cell, its cameras and its run in progress."""
        return _json(service.cell(cell).describe())

    @app.get(f"{v}/cells/{{cell}}/cameras", response_model=list[schemas.CameraOut], responses=_ERRORS,
             tags=["cells"])
    async def cameras(cell: str) -> Response:
        """The cell's cameras."""
        return _json(service.cell(cell).describe()["cameras"])


def _run_routes(app: FastAPI, service: Service) -> None:
    v = API_PREFIX

    @app.post(f"{v}/cells/{{cell}}/runs", status_code=202, response_model=schemas.RunOut,
              responses={**_ERRORS, 401: {"model": schemas.ErrorOut}, 409: {"model": schemas.ErrorOut}},
              dependencies=[Security(_bearer)], tags=["runs"])
    async def start_run(cell: str, body: schemas.RunRequest) -> Response:
        """Start a calibrate, handeye or depthcal run on a camera (one run at a time per cell: 409 otherwise)."""
        run = service.start_run(cell, body.kind, body.camera, body.options.model_dump())
        return _json(run.to_dict(), 202)

    @app.get(f"{v}/runs", response_model=list[schemas.RunOut], tags=["runs"])
    async def runs() -> Response:
        """The runs remembered, oldest first."""
        return _json([r.to_dict() for r in service.runs()])

    @app.get(f"{v}/runs/{{run_id}}", response_model=schemas.RunOut, responses=_ERRORS, tags=["runs"])
    async def run(run_id: str) -> Response:
        """A run's state and progress."""
        return _json(service.run(run_id).to_dict())

    @app.get(f"{v}/runs/{{run_id}}/result", response_model=schemas.RunResultOut,
             responses={**_ERRORS, 409: {"model": schemas.ErrorOut}}, tags=["runs"])
    async def run_result(run_id: str) -> Response:
        """A finished run's result document (409 while it runs, or when it did not end ok)."""
        found = service.run(run_id)
        info = found.to_dict()
        if found.result is None:
            why = "has not finished" if not found.final else f"ended {found.state}: {found.error or 'no result'}"
            return _error(409, f"run {run_id} {why}")
        return _json({"run": info, "result": found.result})

    @app.post(f"{v}/runs/{{run_id}}/cancel", status_code=202, response_model=schemas.RunOut,
              responses={**_ERRORS, 401: {"model": schemas.ErrorOut}, 409: {"model": schemas.ErrorOut}},
              dependencies=[Security(_bearer)], tags=["runs"])
    async def cancel(run_id: str) -> Response:
        """Cancel a run: it stops at its next safe point (before the next move) and tells the arm to stop."""
        return _json(service.cancel_run(run_id).to_dict(), 202)


def _camera_routes(app: FastAPI, service: Service) -> None:
    """A camera's calibration and ``pixel_to_base``, and the event stream."""
    v = API_PREFIX

    @app.get(f"{v}/cells/{{cell}}/cameras/{{camera}}/calibration",
             response_model=schemas.CalibrationOut | CalibrationAtOut,
             responses={**_ERRORS, 409: {"model": schemas.ErrorOut}}, tags=["calibration"])
    async def calibration(cell: str, camera: str, at: str | None = Query(
            None, max_length=64, description="ISO 8601 time with a zone: the calibration in use then, from the "
            "history (the mount and the plane applied last at or before it)")) -> Response:
        """The camera's current calibration (404 before its first result), or with ``at`` the one in use then."""
        if at is not None:
            return _json(await run_in_threadpool(calibration_at, service, cell, camera, at))
        found = await run_in_threadpool(service.cell(cell).calibration, camera)
        if found is None:
            return _error(404, f"camera {camera!r} of cell {cell!r} has no calibration yet (run calibrate or handeye)")
        return _json(found.to_dict())

    pixel_schema = _inline_refs(schemas.PixelRequest.model_json_schema())

    @app.post(f"{v}/cells/{{cell}}/cameras/{{camera}}/pixel_to_base", response_model=schemas.PixelsOut,
              responses={**_ERRORS, 409: {"model": schemas.ErrorOut}}, tags=["calibration"],
              openapi_extra={"requestBody": {"required": True,
                                             "content": {"application/json": {"schema": pixel_schema}}}})
    async def pixel_to_base(cell: str, camera: str, request: Request) -> Response:
        """Pixels -> points on the calibrated plane in the base frame with their 1-sigma."""
        data = _parse_json(await request.body())
        extra = sorted(set(data) - {"pixels", "flange_pose"})
        if extra or "pixels" not in data or "flange_pose" not in data:
            raise RequestError(f"unknown field {extra[0]!r}" if extra else "needs 'pixels' and 'flange_pose'")
        target = service.cell(cell)
        pixels = data["pixels"]
        if isinstance(pixels, list) and len(pixels) > _INLINE_PIXELS:
            result = await run_in_threadpool(target.pixel_to_base, camera, pixels, data["flange_pose"])
        else:
            result = target.pixel_to_base(camera, pixels, data["flange_pose"])
        return Response(_pixels_body(cell, camera, result), media_type="application/json")

    @app.get(f"{v}/events", tags=["service"], response_class=StreamingResponse,
             responses={200: {"content": {"text/event-stream": {}},
                              "description": "server-sent events: run.state, run.progress, run.cancel_requested, "
                                             "calibration.changed, track.state, track.change, "
                                             "track.camera_failed, monitor.state, monitor.drift, drift.<kind>, "
                                             "history.failed, events_lost"}})
    async def events() -> StreamingResponse:
        """The service's events as server-sent events (a slow reader loses the oldest and gets events_lost)."""
        return StreamingResponse(_event_stream(service), media_type="text/event-stream",
                                 headers={"Cache-Control": "no-cache"})


def _parse_json(body: bytes) -> dict[str, Any]:
    try:
        data = json.loads(body)
    except (ValueError, RecursionError) as exc:
        raise HTTPException(400, f"malformed JSON: {exc}") from None
    if not isinstance(data, dict):
        raise RequestError("the body must be a JSON object")
    return data


async def _event_stream(service: Service) -> AsyncIterator[bytes]:
    sub = service.bus.subscribe()
    try:
        yield b"retry: 2000\n\n"
        while not sub.closed:
            event = await sub.aget(EVENT_KEEPALIVE_S)
            if event is None:
                yield b": keep-alive\n\n"
                continue
            yield (f"id: {event.seq}\nevent: {event.type}\n"
                   f"data: {json.dumps(event.to_dict(), separators=(',', ':'))}\n\n").encode()
    finally:
        sub.close()


def create_app(service: Service, *, token: str | None = None, max_body_bytes: int = MAX_BODY_BYTES,
               rate_per_s: float = DEFAULT_RATE_PER_S, burst: int = DEFAULT_BURST) -> Any:
    """The ASGI application of ``service``: the guards in front of the FastAPI routes.

    Args:
        service: The service core (closed when the application shuts down: runs cancelled, arm stopped).
        token: The bearer token state-changing requests need (None: none needed; loopback only).
        max_body_bytes: Largest request body (413 beyond).
        rate_per_s, burst: Each client's token bucket (429 when empty).
    """

    @asynccontextmanager
    async def lifespan(_app: FastAPI) -> AsyncIterator[None]:
        yield
        await asyncio.to_thread(service.close)  # a run in progress is cancelled: its arm is told to stop

    app = FastAPI(title="cellcal service", version="1", openapi_url=f"{API_PREFIX}/openapi.json",
                  docs_url=f"{API_PREFIX}/docs", redoc_url=None, lifespan=lifespan,
                  description="The cell's calibration service: runs, their progress and cancellation, the current "
                  "calibration per camera, pixel_to_base and events. Errors: {\"error\": \"<one line>\"}.")
    _install_error_handlers(app)
    _add_routes(app, service)
    add_history_routes(app, service, API_PREFIX)  # /v1/history/..., /metrics
    add_watch_routes(app, service, API_PREFIX)  # /v1/cells/{cell}/track, /v1/cells/{cell}/monitor
    from cellcal.core.service.status import add_status_routes  # the status page (/) and the reports

    add_status_routes(app, service)
    app.state.service = service
    guarded = RateLimit(BodyLimit(_Auth(app, token), max_body_bytes), TokenBucket(rate_per_s, burst))
    guarded.fastapi = app  # type: ignore[attr-defined]  # the routes and their schema, behind the guards
    return guarded


def openapi_document() -> dict[str, Any]:
    """The OpenAPI schema of the HTTP face (the same whatever the cells: built over the packaged sim cell)."""
    app = create_app(Service([None], "."))
    return app.fastapi.openapi()  # type: ignore[no-any-return]
