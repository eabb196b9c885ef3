"""UR network discovery: the dashboard server (29999) names model and serial; RTDE (30004) confirms.

Plain sockets with a deadline (ur_rtde's clients cannot be bounded, see
:mod:`.rtde_probe`). The dashboard greets with ``Connected: Universal Robots Dashboard
Server``, then answers ``get robot model``, ``get serial number`` and ``PolyscopeVersion``
one line each; RTDE answers a protocol-version request (``V``, protocols.md C2). Every value
is checked before it is shown.
"""

from __future__ import annotations

import socket
import struct
from collections.abc import Mapping, Sequence
from typing import Any

from cellcal.devices import discovery
from cellcal.devices.types import DeviceInfo

#: Standard ports by service name (``cellcal devices --ports ur-dashboard=N,ur-rtde=M`` overrides).
PORTS: dict[str, int] = {"ur-dashboard": 29999, "ur-rtde": 30004}

#: No factory address: a UR controller ships with its network set to DHCP (PolyScope,
#: Settings > System > Network), so there is nothing fixed to look at.
FACTORY_HOSTS: tuple[str, ...] = ()
NO_FACTORY_ADDRESS = ("a UR controller has no factory address (it ships with DHCP): "
                      "give --hosts H,... or --subnet CIDR")

GREETING = b"Connected: Universal Robots Dashboard Server"
_HEADER = struct.Struct(">HB")
_RTDE_VERSION = 86  # 'V'


def scan_hosts(hosts: Sequence[str] | None, timeout: float, ports: Mapping[str, int] | None = None
               ) -> discovery.HostScan:
    """UR controllers among ``hosts`` within ``timeout`` seconds (None: no factory address, one note).

    Args:
        hosts: IP addresses to probe.
        timeout: Seconds for the whole scan.
        ports: Port overrides by service name (keys of :data:`PORTS`; others are ignored).
    """
    if hosts is None:
        return discovery.HostScan(notes=[NO_FACTORY_ADDRESS])
    chosen = {k: int((ports or {}).get(k, v)) for k, v in PORTS.items()}
    return discovery.scan(list(hosts), chosen, timeout, identify)


def identify(host: str, open_ports: Mapping[str, int], deadline: float) -> DeviceInfo | str | None:
    """The controller at ``host`` from its dashboard (and RTDE), a one-line note, or None."""
    dash, rtde = open_ports.get("ur-dashboard"), open_ports.get("ur-rtde")
    extra: dict[str, Any] = {"host": host}
    identity: dict[str, str] = {}
    notes: list[str] = []
    if dash is not None:
        extra["dashboard_port"] = dash
        try:
            identity = _dashboard(host, dash, deadline)
        except (OSError, ValueError) as exc:  # TimeoutError and ConnectionError are OSErrors
            notes.append(f"{host}:{dash}: {_what(exc)} (not a UR dashboard)")
    if rtde is not None:
        try:
            _rtde_version(host, rtde, deadline)
            extra["rtde_port"] = rtde
        except (OSError, ValueError) as exc:
            notes.append(f"{host}:{rtde}: {_what(exc)} (not UR RTDE)")
    if not identity and "rtde_port" not in extra:
        return "; ".join(notes) or None
    return DeviceInfo(backend="ur", vendor="Universal Robots", model=identity.get("model", ""),
                      serial=identity.get("serial", ""), firmware=identity.get("polyscope", ""), extra=extra)


def _what(exc: BaseException) -> str:
    if isinstance(exc, TimeoutError):
        return "accepted, but no reply in time"
    if isinstance(exc, ValueError):
        return str(exc)[:120]
    return f"connection failed ({getattr(exc, 'strerror', None) or type(exc).__name__})"


def _dashboard(host: str, port: int, deadline: float) -> dict[str, str]:
    """Model, serial and PolyScope version from the dashboard (an unknown command's reply is left out).

    Raises:
        ValueError: If the greeting is not the dashboard's.
        OSError: On a timeout or a failed connection.
    """
    with discovery.open_connection(host, port, deadline) as sock:
        greeting = discovery.read_line(sock, deadline)
        if not greeting.startswith(GREETING):
            shown = discovery.device_text(greeting[:40]) or "unreadable"
            raise ValueError(f"greeting {shown!r} is not the dashboard's")
        identity: dict[str, str] = {}
        for key, command in (("model", b"get robot model"), ("serial", b"get serial number"),
                             ("polyscope", b"PolyscopeVersion")):
            answer = _command(sock, command, deadline)
            if answer:
                identity[key] = answer
        return identity


def _command(sock: socket.socket, command: bytes, deadline: float) -> str:
    """One dashboard command's reply if it is short printable text and not a refusal, else ""."""
    sock.sendall(command + b"\n")
    text = discovery.device_text(discovery.read_line(sock, deadline), max_len=80)
    if not text or text.lower().startswith("could not understand"):
        return ""
    return text


def _rtde_version(host: str, port: int, deadline: float) -> None:
    """Ask RTDE for protocol version 2; return if it answers with a version reply.

    Raises:
        ValueError: If the reply is not RTDE's.
        OSError: On a timeout or a failed connection.
    """
    with discovery.open_connection(host, port, deadline) as sock:
        sock.sendall(_HEADER.pack(_HEADER.size + 2, _RTDE_VERSION) + struct.pack(">H", 2))
        size, kind = _HEADER.unpack(discovery.read_exact(sock, _HEADER.size, deadline))
        if kind != _RTDE_VERSION or size != _HEADER.size + 1:
            raise ValueError(f"reply type {kind}, size {size} is not an RTDE version reply")
        discovery.read_exact(sock, 1, deadline)  # accepted (1) or not (0): an RTDE server either way
