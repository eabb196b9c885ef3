"""One backend's device discovery, run in a child process by ``cellcal devices --scan``.

A vendor SDK's native code can abort the whole process (depthai does, given a short
timeout); run in a child, the abort costs one line of the scan instead of the command.
Usage: ``python -m cellcal.core.cli.scan_child KIND NAME TIMEOUT_S``; prints one JSON
object on stdout: ``{"found": [...]}`` (None when the backend has no discovery) or
``{"error": "..."}``.
"""

from __future__ import annotations

import json
import sys
from typing import Any


def scan(kind: str, name: str, timeout: float) -> dict[str, Any]:
    """Ask backend ``kind``/``name`` for reachable devices; a JSON-ready reply."""
    from cellcal.devices.errors import CellcalError
    from cellcal.devices.registry import default_registry

    try:
        cls = default_registry().get(kind, name)  # type: ignore[arg-type]
        found = cls.discover(timeout)
    except CellcalError as exc:
        return {"error": str(exc)}
    if found is None:
        return {"found": None}
    return {"found": [{"vendor": d.vendor, "model": d.model, "serial": d.serial, "extra": dict(d.extra)}
                      for d in found]}


def main(argv: list[str]) -> int:
    """Entry point of the child: scan, print the reply as one JSON line."""
    kind, name, timeout = argv[0], argv[1], float(argv[2])
    print(json.dumps(scan(kind, name, timeout), default=str), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
