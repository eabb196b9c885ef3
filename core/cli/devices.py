"""``cellcal devices``: list registered backends (and, with --scan, reachable devices)."""

from __future__ import annotations

import argparse
from typing import Any

from cellcal.core.cli.argtypes import real
from cellcal.devices.errors import CellcalError
from cellcal.devices.registry import default_registry


def register(sub: Any) -> None:
    """Add the ``devices`` subcommand."""
    p = sub.add_parser("devices", help="list camera and arm backends and where they come from")
    p.add_argument("--scan", action="store_true", help="also look for reachable devices of each backend")
    p.add_argument("--timeout", type=real(gt=0), default=2.0, metavar="S", help="seconds per backend scan")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Print the registry; with ``--scan`` ask every backend to discover devices."""
    registry = default_registry()
    entries = registry.entries()
    width = max((len(e.name) for e in entries), default=4)
    for kind in ("camera", "arm"):
        print(f"{kind}s:")
        for e in (e for e in entries if e.kind == kind):
            print(f"  {e.name:<{width}}  {e.target}  [{e.origin}]")
    if not args.scan:
        return 0
    print("scan:")
    for e in entries:
        try:
            cls = registry.get(e.kind, e.name)
            found = cls.discover(args.timeout)
        except CellcalError as exc:
            print(f"  {e.kind} {e.name}: unavailable: {exc}")
            continue
        if found is None:
            continue
        if not found:
            print(f"  {e.kind} {e.name}: no devices found")
        for info in found:
            extra = ", ".join(f"{k}={v}" for k, v in info.extra.items())
            print(f"  {e.kind} {e.name}: {info.vendor} {info.model} {info.serial} {extra}".rstrip())
    return 0
