"""``cellcal devices``: list registered backends (and, with --scan, reachable devices).

A network backend (one with ``scan_hosts``: o3r, xarm, ur) probes ``--hosts``, ``--subnet``
or, by default, its vendor's factory addresses on its vendor's ports (``--ports NAME=PORT``
overrides); ADR 0036. A device that drives several heads (an O3R VPU) lists each on a line of its
own: port, type, PCIC port, state.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from cellcal.core.cli.argtypes import real
from cellcal.core.cli.scan_targets import parse_hosts, parse_ports, parse_subnet
from cellcal.core.cli.text import one_line
from cellcal.devices.errors import CellcalError, ConfigError

if TYPE_CHECKING:
    from cellcal.devices.registry import Kind, Registry


def register(sub: Any) -> None:
    """Add the ``devices`` subcommand."""
    p = sub.add_parser("devices", help="list camera and arm backends and where they come from")
    p.add_argument("--scan", action="store_true", help="also look for reachable devices of each backend")
    p.add_argument("--timeout", type=real(gt=0, le=60), default=2.0, metavar="S", help="seconds per backend scan")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--hosts", type=parse_hosts, metavar="H,H...",
                       help="network backends probe these IP addresses (with --scan)")
    where.add_argument("--subnet", type=parse_subnet, metavar="CIDR",
                       help="network backends probe this subnet, at most a /22 (with --scan)")
    where.add_argument("--factory", action="store_true",
                       help="network backends probe their vendor's factory addresses (the default of --scan)")
    p.add_argument("--ports", type=parse_ports, metavar="NAME=PORT,...",
                   help="non-standard ports by service: o3r-rpc, o3r-pcic, xarm, ur-dashboard, ur-rtde")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Print the registry; with ``--scan`` ask every backend to discover devices."""
    from cellcal.devices.registry import default_registry  # the interfaces (numpy), not for `cellcal --help`

    registry = default_registry()
    entries = registry.entries()
    if not args.scan and (args.hosts or args.subnet or args.factory or args.ports):
        raise ConfigError("--hosts, --subnet, --factory and --ports say where --scan looks: add --scan")
    # where network backends look: the given addresses, else (also with --factory) their factory addresses
    target = NetworkTarget(hosts=args.hosts or args.subnet, ports=dict(args.ports or {}))
    _check_services(registry, target.ports)
    width = max((len(e.name) for e in entries), default=4)
    for kind in ("camera", "arm"):
        print(f"{kind}s:")
        for e in (e for e in entries if e.kind == kind):
            note = _unavailable(registry, e.kind, e.name)
            print(f"  {e.name:<{width}}  {e.target}  [{e.origin}]" + (f"  (unavailable: {note})" if note else ""))
    if not args.scan:
        return 0
    print("scan:")
    from concurrent.futures import ThreadPoolExecutor  # here: not at `cellcal --help`

    # one child process per backend, a few at a time; the report keeps the listing's order
    with ThreadPoolExecutor(max_workers=_SCAN_WORKERS) as pool:
        reports = pool.map(lambda e: _scan_entry(registry, e.kind, e.name, args.timeout, target), entries)
        for e, lines in zip(entries, reports, strict=True):
            for line in lines:
                print(f"  {e.kind} {e.name}: {line}", flush=True)
    return 0


@dataclass(frozen=True)
class NetworkTarget:
    """Where network backends look.

    Attributes:
        hosts: IP addresses, or None for each backend's factory addresses.
        ports: Port overrides by service name.
    """

    hosts: list[str] | None
    ports: dict[str, int]


def _check_services(registry: Registry, ports: dict[str, int]) -> None:
    """Refuse a ``--ports`` service name that no network backend has (one line, exit 2)."""
    known: set[str] = set()
    for e in registry.entries():
        with contextlib.suppress(CellcalError):
            known |= set(getattr(registry.get(e.kind, e.name), "scan_ports", {}))
    unknown = sorted(set(ports) - known)
    if unknown:
        raise ConfigError(f"--ports: unknown service {', '.join(map(repr, unknown))} "
                          f"(known: {', '.join(sorted(known)) or 'none'})")


def _scan_entry(registry: Registry, kind: Kind, name: str, timeout: float, target: NetworkTarget) -> list[str]:
    """Report lines for one backend: no child process for a backend that has no discovery."""
    from cellcal.devices.base import Device

    try:
        cls = registry.get(kind, name)
    except CellcalError as exc:
        return [f"unavailable: {one_line(str(exc))}"]
    if callable(getattr(cls, "scan_hosts", None)):
        return scan_lines(kind, name, timeout, target)
    if getattr(cls.discover, "__func__", None) is getattr(Device.discover, "__func__", None):
        return [NO_DISCOVERY]
    return scan_lines(kind, name, timeout)


#: What the scan says of a backend that cannot look for devices.
NO_DISCOVERY = "no discovery (this backend cannot look for devices; configure its address)"


def scan_lines(kind: str, name: str, timeout: float, target: NetworkTarget | None = None) -> list[str]:
    """What one backend's discovery found, as report lines (run in a child process).

    The child's stderr (SDK chatter) is kept out of the report; a child that dies (a
    native abort in an SDK) or overruns ``timeout`` plus its start-up allowance is one line.
    With ``target`` the child runs the backend's network scan (``scan_hosts``) there.
    """
    import json
    import signal
    import subprocess

    cmd = [sys.executable, "-m", "cellcal.core.cli.scan_child", kind, name, repr(timeout)]
    if target is not None:
        cmd.append(json.dumps({"hosts": target.hosts, "ports": target.ports}))
    try:
        done = subprocess.run(cmd, capture_output=True, text=True, errors="backslashreplace",
                              timeout=timeout + _CHILD_STARTUP_S, check=False)
    except subprocess.TimeoutExpired:
        return [f"unavailable: discovery did not finish within {timeout + _CHILD_STARTUP_S:g} s"]
    reply = _reply(done.stdout)
    if reply is None:
        how = (f"signal {signal.Signals(-done.returncode).name}" if done.returncode < 0
               else f"exit status {done.returncode}")
        return [f"unavailable: discovery crashed ({how}){_last_line(done.stderr)}"]
    if "error" in reply:
        return [f"unavailable: {one_line(str(reply['error']))}"]
    found = reply.get("found")
    if found is None:
        return [NO_DISCOVERY]
    notes = [one_line(str(n)) for n in reply.get("notes", [])]
    if not found:  # an open port that did not identify says so itself, in one line
        summary = reply.get("summary")
        return notes or [f"no devices found ({one_line(str(summary))})" if summary else "no devices found"]
    lines = []
    for d in found:
        fields = dict(d.get("extra", {}))
        heads, unread = fields.pop("heads", None), fields.pop("heads_unread", None)
        extra = ", ".join(f"{k}={v}" for k, v in fields.items())
        firmware = f"firmware {d['firmware']}, " if d.get("firmware") else ""
        lines.append(one_line(f"{d.get('vendor', '')} {d.get('model', '')} {d.get('serial', '')} "
                              f"{firmware}{extra}".rstrip()))
        lines += head_lines(heads, unread)
    return [*lines, *notes]


def head_lines(heads: Any, unread: Any = None) -> list[str]:
    """One indented line per head of a device that drives several (an O3R VPU's ports), from ``extra["heads"]``.

    Each head is a mapping with ``port``, ``type``, ``pcic_port`` and ``state`` (or ``unreadable``,
    the reason); ``unread`` says why the heads could not be listed at all.
    """
    if unread:
        return [one_line(f"  heads not read ({unread})")]
    if not isinstance(heads, list):
        return []
    out = []
    for h in heads:
        if not isinstance(h, dict):
            continue
        what = (f"unreadable ({h['unreadable']})" if "unreadable" in h
                else f"{h.get('type', '?')}, PCIC port {h.get('pcic_port', '?')}, {h.get('state', '?')}")
        out.append(one_line(f"  head {h.get('port', '?')}: {what}"))
    return out


def _unavailable(registry: Registry, kind: Kind, name: str) -> str | None:
    """Why backend ``name`` cannot be used here (its own cheap check), or None."""
    try:
        return registry.get(kind, name).unavailable_reason()
    except CellcalError as exc:  # the backend's module does not even load
        return one_line(str(exc))


#: Backends scanned at once (each in its own child process).
_SCAN_WORKERS = 4

#: Seconds a scan child may take beyond its discovery timeout (interpreter start, imports).
_CHILD_STARTUP_S = 10.0


def _reply(stdout: str) -> dict[str, Any] | None:
    """The child's JSON reply (its last stdout line), or None if it printed none."""
    import json

    for line in reversed(stdout.splitlines()):
        try:
            value = json.loads(line)
        except ValueError:
            continue
        if isinstance(value, dict):
            return value
    return None


def _last_line(stderr: str) -> str:
    """``: <last stderr line>`` of a crashed child, or nothing."""
    lines = [ln for ln in stderr.splitlines() if ln.strip()]
    return f": {one_line(lines[-1])}" if lines else ""
