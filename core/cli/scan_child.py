"""One backend's device discovery, run in a child process by ``cellcal devices --scan``.

A vendor SDK's native code can abort the whole process (depthai does, given a short
timeout); run in a child, the abort costs one line of the scan instead of the command.
Usage: ``python -m cellcal.core.cli.scan_child KIND NAME TIMEOUT_S [TARGET_JSON]``; with
``TARGET_JSON`` (``{"hosts": [...] or null, "ports": {...}}``) the backend's network scan
``scan_hosts`` runs instead of ``discover``. Prints one JSON object on stdout:
``{"found": [...], "notes": [...], "summary": "..."}`` (``found`` None when the backend
has no discovery) or ``{"error": "..."}``.
"""

from __future__ import annotations

import json
import sys
from typing import Any


def scan(kind: str, name: str, timeout: float, target: dict[str, Any] | None = None) -> dict[str, Any]:
    """Ask backend ``kind``/``name`` for reachable devices (on ``target``'s hosts); a JSON-ready reply."""
    from cellcal.devices.errors import CellcalError
    from cellcal.devices.registry import default_registry

    notes: list[str] = []
    summary = ""
    try:
        cls = default_registry().get(kind, name)  # type: ignore[arg-type]
        if target is not None:
            report = cls.scan_hosts(target["hosts"], timeout, target["ports"])  # type: ignore[attr-defined]
            found, notes, summary = report.found, report.notes, report.summary
        else:
            found = cls.discover(timeout)
    except CellcalError as exc:
        return {"error": str(exc)}
    if found is None:
        return {"found": None}
    return {"found": [{"vendor": d.vendor, "model": d.model, "serial": d.serial, "firmware": d.firmware,
                       "extra": dict(d.extra)} for d in found], "notes": notes, "summary": summary}


def main(argv: list[str]) -> int:
    """Entry point of the child: scan, print the reply as one JSON line."""
    kind, name, timeout = argv[0], argv[1], float(argv[2])
    target = json.loads(argv[3]) if len(argv) > 3 else None
    print(json.dumps(scan(kind, name, timeout, target), default=str), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
