"""O3R network discovery: which hosts answer the VPU's XML-RPC ``get`` with a device identity.

Ports: XML-RPC 80 and PCIC 50010 (protocols.md A1). The identity is
``get(["/device/info", "/device/swVersion"])``: ``productCode`` (e.g. OVP800), ``serialNumber``,
``name`` and the firmware; then ``get(["/ports"])`` lists every head (port, type, PCIC port,
state) as ``extra["heads"]``. Every value is checked before it is shown.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from typing import Any

from cellcal.devices import discovery
from cellcal.devices.errors import CellcalError, DeviceTimeoutError
from cellcal.devices.types import DeviceInfo

from .xmlrpc_config import O3RConfigClient

#: Standard ports by service name (``cellcal devices --ports o3r-rpc=N`` overrides).
PORTS: dict[str, int] = {"o3r-rpc": 80, "o3r-pcic": 50010}

#: The VPU's factory address: eth0 ships with the static address 192.168.0.69 (ifm's O3R
#: documentation, VPU network settings; also the driver's default ``O3RConfig.host``).
FACTORY_HOSTS: tuple[str, ...] = ("192.168.0.69",)

#: Largest identity reply accepted, bytes (the two sub-trees are well under 4 kB).
MAX_REPLY_BYTES = 64 * 1024
#: Largest ``/ports`` reply accepted, bytes (every setting of up to seven ports: tens of kB on a VPU).
MAX_PORTS_REPLY_BYTES = 1024 * 1024


def scan_hosts(hosts: Sequence[str] | None, timeout: float, ports: Mapping[str, int] | None = None
               ) -> discovery.HostScan:
    """O3R VPUs among ``hosts`` (None: :data:`FACTORY_HOSTS`), within ``timeout`` seconds.

    Args:
        hosts: IP addresses to probe.
        timeout: Seconds for the whole scan.
        ports: Port overrides by service name (keys of :data:`PORTS`; others are ignored).
    """
    chosen = {k: int((ports or {}).get(k, v)) for k, v in PORTS.items()}
    return discovery.scan(list(FACTORY_HOSTS if hosts is None else hosts), chosen, timeout, identify)


def identify(host: str, open_ports: Mapping[str, int], deadline: float) -> DeviceInfo | str | None:
    """The VPU at ``host`` from its XML-RPC identity, a one-line note, or None (nothing of an O3R)."""
    rpc = open_ports.get("o3r-rpc")
    pcic = open_ports.get("o3r-pcic")
    if rpc is None:
        return (f"{host}:{pcic}: the PCIC port is open but the XML-RPC port is closed (an O3R? not identified)"
                if pcic is not None else None)
    remaining = deadline - time.monotonic()
    if remaining <= 0:
        return f"{host}:{rpc}: open, not identified (no time left)"
    client = O3RConfigClient(host, rpc, timeout_s=remaining, max_reply_bytes=MAX_REPLY_BYTES)
    try:
        doc = client.get(["/device/info", "/device/swVersion"])
    except DeviceTimeoutError:
        return f"{host}:{rpc}: accepted, but no XML-RPC reply within {remaining:.2g} s (not an O3R)"
    except CellcalError as exc:
        return f"{host}:{rpc}: not an O3R ({_reason(exc)})"
    device = _node(doc, "device")
    info, sw = _node(device, "info"), _node(device, "swVersion")
    model = discovery.device_text(info.get("productCode"))
    if not model:
        return f"{host}:{rpc}: answers XML-RPC but names no /device/info/productCode (not an O3R)"
    extra: dict[str, Any] = {"host": host, "port": rpc, "pcic_port": pcic}
    name = discovery.device_text(info.get("name"))
    if name:
        extra["name"] = name
    extra.update(_heads(O3RConfigClient(host, rpc, timeout_s=remaining, max_reply_bytes=MAX_PORTS_REPLY_BYTES),
                        deadline))
    return DeviceInfo(backend="o3r", vendor="ifm electronic", model=model,
                      serial=discovery.device_text(info.get("serialNumber")) or "",
                      firmware=discovery.device_text(sw.get("firmware")) or "", extra=extra)


def _heads(client: O3RConfigClient, deadline: float) -> dict[str, Any]:
    """``{"heads": [...]}``: every port of the VPU (port, type, PCIC port, state), or ``{"heads_unread": why}``.

    A port whose values do not check out is listed with ``"unreadable"`` and the reason.
    """
    remaining = deadline - time.monotonic()
    if remaining <= 0:
        return {"heads_unread": "no time left"}
    try:
        ports, unread = client.ports(timeout=remaining)
    except CellcalError as exc:
        return {"heads_unread": _reason(exc)}
    heads: list[dict[str, Any]] = [{"port": p.name, "type": p.type, "pcic_port": p.pcic_port, "state": p.state}
                                   for p in ports]
    heads += [{"port": line.split(": ", 1)[0], "unreadable": line.split(": ", 1)[-1][:120]} for line in unread]
    return {"heads": sorted(heads, key=lambda h: str(h["port"]))}


def _node(doc: Any, key: str) -> dict[str, Any]:
    """``doc[key]`` if both are JSON objects, else an empty one."""
    value = doc.get(key) if isinstance(doc, dict) else None
    return value if isinstance(value, dict) else {}


def _reason(exc: CellcalError) -> str:
    """The error's message without the call it repeats (``O3R XML-RPC host:port get(...): ``)."""
    text = str(exc)
    return text.split("): ", 1)[-1][:120]
