"""The service's refusals, each with the HTTP status a face answers it with (a 4xx with one line)."""

from __future__ import annotations

from cellcal.devices.errors import CellcalError

__all__ = ["BusyError", "NotFoundError", "RequestError", "ServiceError"]


class ServiceError(CellcalError):
    """A request the service refuses; ``status`` is the HTTP status that says why."""

    status = 400


class RequestError(ServiceError):
    """The request is well-formed but asks for something invalid (a wrong value or option)."""

    status = 422


class NotFoundError(ServiceError):
    """No such cell, camera or run (or the camera has no calibration yet)."""

    status = 404


class BusyError(ServiceError):
    """The cell already runs something (or another process holds its output), or the run has ended."""

    status = 409
