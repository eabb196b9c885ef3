"""The installed cellcal version, for result documents and recordings."""

from __future__ import annotations

from functools import cache
from importlib.metadata import PackageNotFoundError, version

__all__ = ["cellcal_version"]


@cache
def cellcal_version() -> str:
    """The installed ``cellcal`` distribution's version, or ``"unknown"`` when it is not installed."""
    try:
        return version("cellcal")
    except PackageNotFoundError:  # pragma: no cover - running from a source tree
        return "unknown"
