"""The service's status page: ``/`` (plain HTML and JS, no external resource), ``/v1/status`` and the reports.

The page shows each cell's run (its state and progress, its error, its report) and each camera's
current plane and mount with their 95 % half-widths (the values the OPC UA face publishes), and
follows ``/v1/events`` with an ``EventSource``: a run's progress shows without a reload.
A run's report is served at ``/v1/runs/{id}/report`` and a camera's latest at
``/v1/cells/{cell}/cameras/{camera}/reports/{report.html | depthcal-report.html}``; only regular
files inside the service's output directory are served (a path that resolves elsewhere, through
a symbolic link or otherwise, is a 404). Added to the HTTP face's FastAPI application by
:func:`add_status_routes` (imported only when served).
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import Any

from fastapi import FastAPI
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, Response

from cellcal.core.service.cell import Service
from cellcal.core.service.httpguard import error_body
from cellcal.core.service.opcua_nodes import camera_values
from cellcal.devices.errors import CellcalError

__all__ = ["REPORT_NAMES", "add_status_routes", "inside", "status_document"]

#: The report files a camera's directory may hold (calibrate and handeye: report.html; depthcal its own).
REPORT_NAMES = ("report.html", "depthcal-report.html")
#: Largest report served, bytes (a calibrate report with its pictures inlined is a few MB).
MAX_REPORT_BYTES = 64 << 20
_PAGE = "static/status.html"
_HTML_HEADERS = {"Cache-Control": "no-cache", "X-Content-Type-Options": "nosniff",
                 "Content-Security-Policy": "default-src 'self'; img-src 'self' data:; style-src 'self' "
                 "'unsafe-inline'; script-src 'self' 'unsafe-inline'; frame-ancestors 'none'"}


def inside(root: Path, path: Path | str | None) -> Path | None:
    """``path`` resolved if it is a regular file inside ``root`` (symbolic links followed), else None."""
    if path is None:
        return None
    try:
        found = Path(path).resolve(strict=True)
        base = root.resolve(strict=True)
    except (OSError, RuntimeError):
        return None
    if not found.is_relative_to(base) or not found.is_file():
        return None
    return found


def _camera(service: Service, cell: str, camera: str) -> dict[str, Any]:
    """A camera's current calibration values and its reports (links)."""
    target = service.cells[cell]
    out: dict[str, Any] = {"name": camera, "on": target.configs[camera].camera_entry.on, "error": None}
    try:
        calibration = target.calibration(camera)
    except CellcalError as exc:
        calibration, out["error"] = None, str(exc).replace("\n", " ")
    out["calibration"] = None if calibration is None else {
        "kind": calibration.kind, "created_utc": calibration.created_utc, "file": str(calibration.path),
        "values": camera_values(calibration)}
    directory = target.directory / camera
    out["reports"] = [f"/v1/cells/{cell}/cameras/{camera}/reports/{name}" for name in REPORT_NAMES
                      if inside(service.out_dir, directory / name) is not None]
    return out


def _run(service: Service, run: Any) -> dict[str, Any]:
    info: dict[str, Any] = run.to_dict()
    info["report_url"] = (f"/v1/runs/{run.id}/report" if inside(service.out_dir, info["report_file"]) is not None
                          else None)
    return info


def _watch(service: Service, cell: str, kind: str) -> dict[str, Any] | None:
    """The cell's latest tracking or monitoring session in short (None before one): state, per camera its frames,
    open change, drift events and the last one in words."""
    found = service.watches.latest(cell, kind)
    if found is None:
        return None
    data = found.to_dict()
    keep = ("frames", "change_open", "drift_events", "last_drift", "failed")
    return {"id": data["id"], "state": data["state"], "error": data["error"],
            "cameras": {name: {k: values.get(k) for k in keep} for name, values in data["cameras"].items()}}


def status_document(service: Service) -> dict[str, Any]:
    """JSON form of what the page shows: the service's state, each cell's run in progress or latest, its tracking
    and monitoring (``track``, ``monitor``: None before a session), its cameras.

    A camera's ``calibration.values`` are the OPC UA face's variables (``PlaneTiltX``, rad; ``PlaneHeight``, m;
    ``MountX``, m; ``MountRoll``, rad; each with its 95 % ``...HalfWidth``).
    """
    runs = service.runs()
    cells = []
    for name, cell in service.cells.items():
        mine = [r for r in runs if r.cell == name]
        latest = cell.active or (mine[-1] if mine else None)
        cells.append({"name": name, "active_run": None if cell.active is None else cell.active.id,
                      "run": None if latest is None else _run(service, latest),
                      "track": _watch(service, name, "track"), "monitor": _watch(service, name, "monitor"),
                      "cameras": [_camera(service, name, camera) for camera in cell.configs]})
    return {"status": service.health()["status"], "cells": cells}


def _error(status: int, message: str) -> Response:
    return Response(error_body(message), status_code=status, media_type="application/json")


def _report(path: Path | None, what: str) -> Response:
    if path is None:
        return _error(404, f"no report for {what} (or not inside the service's output directory)")
    if path.stat().st_size > MAX_REPORT_BYTES:
        return _error(409, f"the report of {what} is larger than {MAX_REPORT_BYTES} bytes")
    return FileResponse(path, media_type="text/html; charset=utf-8", headers=_HTML_HEADERS)


def add_status_routes(app: FastAPI, service: Service) -> None:
    """Add ``/``, ``/v1/status`` and the report routes to the HTTP face's application (GET only: no token)."""
    page = resources.files("cellcal.core.service").joinpath(_PAGE).read_text(encoding="utf-8")

    @app.get("/", include_in_schema=False)
    async def status_page() -> Response:
        return HTMLResponse(page, headers=_HTML_HEADERS)

    @app.get("/v1/status", include_in_schema=False)
    async def status() -> Response:
        return JSONResponse(await run_in_threadpool(status_document, service))

    @app.get("/v1/runs/{run_id}/report", include_in_schema=False)
    async def run_report(run_id: str) -> Response:
        run = service.run(run_id)  # NotFoundError: 404
        return _report(inside(service.out_dir, run.report_file), f"run {run_id}")

    @app.get("/v1/cells/{cell}/cameras/{camera}/reports/{name}", include_in_schema=False)
    async def camera_report(cell: str, camera: str, name: str) -> Response:
        target = service.cell(cell)
        target.camera_config(camera)  # NotFoundError: 404
        if name not in REPORT_NAMES:
            return _error(404, f"no report {name!r} (known: {', '.join(REPORT_NAMES)})")
        return _report(inside(service.out_dir, target.directory / camera / name), f"{cell}/{camera}")
