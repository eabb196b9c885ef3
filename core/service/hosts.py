"""What the tracking and monitoring sessions need of the service and of a cell (:mod:`.cell` provides both),
as protocols, so the sessions' modules do not import the service that starts them."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, Protocol

from cellcal.core.calibration.config import CellConfig
from cellcal.core.service.events import EventBus

__all__ = ["CellHost", "ServiceHost"]


class CellHost(Protocol):
    """A cell of the service (:class:`~cellcal.core.service.cell.CellService`)."""

    @property
    def name(self) -> str:
        """The cell's name."""

    @property
    def directory(self) -> Path:
        """Where the cell writes (``OUT/<cell>``)."""

    @property
    def configs(self) -> Mapping[str, CellConfig]:
        """The cell's configuration per camera."""

    @property
    def builder(self) -> Callable[[CellConfig], Any]:
        """``config -> (camera, SafeArm)``: how the cell's devices are built."""

    def occupy(self, holder: Any, what: str) -> Any:
        """Take the cell for a session (its lock held until :meth:`vacate`)."""

    def vacate(self, holder: Any, lock: Any) -> None:
        """Give the cell back."""

    def camera_config(self, camera: str) -> CellConfig:
        """The configuration of ``camera`` (NotFoundError naming the cell's cameras)."""

    def calibration(self, camera: str) -> Any:
        """The camera's current calibration, or None."""


class ServiceHost(Protocol):
    """The service (:class:`~cellcal.core.service.cell.Service`): its cells, bus and metrics."""

    @property
    def closed(self) -> bool:
        """Whether the service is shutting down."""

    @property
    def bus(self) -> EventBus:
        """The service's event bus."""

    @property
    def metrics(self) -> Any:
        """The service's Prometheus metrics, or None."""

    def cell(self, name: str) -> CellHost:
        """The cell named ``name`` (NotFoundError naming the cells)."""
