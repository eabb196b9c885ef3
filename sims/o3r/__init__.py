"""Emulated ifm O3R VPU (XML-RPC + PCIC over TCP) serving simulated cameras, one per 3D head:
:class:`O3REmulator`, and backend :class:`EmulatedO3RCamera` (``cameras: o3r-emulated``).
Standalone: ``python -m cellcal.sims.o3r``. Both names load on first use, so
``python -m cellcal.sims.o3r --help`` imports no numpy."""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from cellcal.sims.o3r.backend import EmulatedO3RCamera
    from cellcal.sims.o3r.emulator import O3REmulator

__all__ = ["EmulatedO3RCamera", "O3REmulator"]
_HOME = {"EmulatedO3RCamera": "backend", "O3REmulator": "emulator"}


def __getattr__(name: str) -> Any:
    if name in _HOME:
        return getattr(importlib.import_module(f"{__name__}.{_HOME[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
