"""Network discovery's vendor-free part: a bounded TCP connect sweep, bounded reads, the scan report.

A network backend's ``scan_hosts`` sweeps its vendor's standard ports with :func:`scan`
and identifies each host that has one open with its own protocol. Rationale:
docs/adr/0036-network-discovery.md.
"""

from __future__ import annotations

import errno
import ipaddress
import selectors
import socket
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

if TYPE_CHECKING:                  # types.py pulls numpy: `cellcal --help` and the scan's parser must not
    from .types import DeviceInfo

__all__ = ["MAX_HOSTS", "HostScan", "Identify", "device_text", "open_connection", "read_exact", "read_line",
           "scan", "sweep"]

#: Most hosts one scan probes (a /22).
MAX_HOSTS = 1024
#: Sockets connecting at once during a sweep (well below the usual 1024 file descriptors).
MAX_OPEN_SOCKETS = 256
#: Hosts identified at once (each a short conversation over its open ports).
MAX_IDENTIFY_WORKERS = 16
#: Longest wait for one connection to be accepted or refused, s (a LAN answers in milliseconds).
CONNECT_CAP_S = 1.0
#: Share of the scan's time the sweep may use; identification gets the rest.
SWEEP_SHARE = 0.5
#: Notes kept in one report (a subnet of web servers on port 80 would otherwise fill the screen).
MAX_NOTES = 20

#: What identifying one host returns: the device, a one-line note (an open port that is not
#: the vendor's), or None (nothing to report).
Identify = Callable[[str, Mapping[str, int], float], "DeviceInfo | str | None"]


@dataclass
class HostScan:
    """What one backend's network scan found.

    Attributes:
        found: The devices identified.
        notes: One line per open port that did not identify, and per limit reached.
        summary: The sweep in numbers, e.g. ``"1 host x 2 ports: 2 refused"``.
    """

    found: list[DeviceInfo] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    summary: str = ""


def _state(code: int) -> str:
    if code == 0:
        return "open"
    if code == errno.ECONNREFUSED:
        return "refused"
    if code in (errno.ETIMEDOUT, errno.EAGAIN):
        return "silent"
    return "unreachable"


def sweep(endpoints: Sequence[tuple[str, int]], timeout: float, *, max_open: int = MAX_OPEN_SOCKETS,
          connect_timeout: float = CONNECT_CAP_S) -> dict[tuple[str, int], str]:
    """Try a TCP connection to every endpoint, ``max_open`` at a time, all within ``timeout`` seconds.

    Args:
        endpoints: ``(IP address, port)`` pairs (addresses as literals: no name lookup).
        timeout: Seconds for the whole sweep.
        max_open: Sockets connecting at once.
        connect_timeout: Seconds one connection may take to be accepted or refused.

    Returns:
        Each endpoint's state: ``"open"``, ``"refused"``, ``"silent"`` (no answer within
        ``connect_timeout``), ``"unreachable"`` (the network said so) or ``"not tried"``
        (the sweep's time ran out first). Every socket is closed on return.
    """
    deadline = time.monotonic() + timeout
    states = dict.fromkeys(endpoints, "not tried")
    pending = list(reversed(states))
    sel = selectors.DefaultSelector()
    started: dict[socket.socket, tuple[tuple[str, int], float]] = {}
    try:
        while (pending or started) and time.monotonic() < deadline:
            while pending and len(started) < max_open:
                endpoint = pending.pop()
                sock = _start_connect(endpoint, states)
                if sock is not None:
                    started[sock] = (endpoint, min(deadline, time.monotonic() + connect_timeout))
                    sel.register(sock, selectors.EVENT_WRITE)
            if not started:
                continue
            wait = min(end for _, end in started.values()) - time.monotonic()
            for key, _ in sel.select(max(0.0, wait)):
                done = key.fileobj
                assert isinstance(done, socket.socket)
                endpoint, _ = started.pop(done)
                states[endpoint] = _state(done.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR))
                sel.unregister(done)
                done.close()
            now = time.monotonic()
            for sock, (endpoint, end) in list(started.items()):
                if end <= now:
                    states[endpoint] = "silent"
                    del started[sock]
                    sel.unregister(sock)
                    sock.close()
    finally:
        for sock in started:
            sock.close()
        sel.close()
    return states


def _start_connect(endpoint: tuple[str, int], states: dict[tuple[str, int], str]) -> socket.socket | None:
    """A socket connecting to ``endpoint`` without blocking, or None (its state already known)."""
    host, port = endpoint
    family = socket.AF_INET6 if ipaddress.ip_address(host).version == 6 else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setblocking(False)
    try:
        code = sock.connect_ex((host, port))
    except OSError as exc:
        code = exc.errno or errno.EHOSTUNREACH
    if code in (errno.EINPROGRESS, errno.EWOULDBLOCK, errno.EALREADY):
        return sock
    states[endpoint] = _state(code)
    sock.close()
    return None


def scan(hosts: Sequence[str], ports: Mapping[str, int], timeout: float, identify: Identify, *,
         workers: int = MAX_IDENTIFY_WORKERS) -> HostScan:
    """Sweep ``hosts`` x ``ports``, then identify every host with an open port, all within ``timeout``.

    Args:
        hosts: IP address literals (at most :data:`MAX_HOSTS`).
        ports: Service name -> TCP port, e.g. ``{"xarm": 502}``.
        timeout: Seconds for the whole scan.
        identify: ``identify(host, open ports by service, deadline)`` (``time.monotonic()``
            deadline); must return by the deadline and never raise.
        workers: Hosts identified at once.

    Raises:
        ValueError: If there are more than :data:`MAX_HOSTS` hosts or a host is not an IP address.
    """
    if len(hosts) > MAX_HOSTS:
        raise ValueError(f"{len(hosts)} hosts: at most {MAX_HOSTS} (a /22) in one scan")
    for host in hosts:
        ipaddress.ip_address(host)
    deadline = time.monotonic() + timeout
    endpoints = [(h, p) for h in hosts for p in dict.fromkeys(ports.values())]
    states = sweep(endpoints, timeout * SWEEP_SHARE, connect_timeout=min(CONNECT_CAP_S, timeout / 4))
    report = HostScan(summary=_summary(len(hosts), len(set(ports.values())), states))
    open_hosts: dict[str, dict[str, int]] = {}
    for service, port in ports.items():
        for host in hosts:
            if states[(host, port)] == "open":
                open_hosts.setdefault(host, {})[service] = port
    if open_hosts:
        from .types import DeviceInfo  # numpy only once something answered

        with ThreadPoolExecutor(max_workers=max(1, min(workers, len(open_hosts)))) as pool:
            results = list(pool.map(lambda h: _identify_safely(identify, h, open_hosts[h], deadline), open_hosts))
        for result in results:
            if isinstance(result, DeviceInfo):
                report.found.append(result)
            elif result:
                report.notes.append(result)
    if len(report.notes) > MAX_NOTES:
        more = len(report.notes) - MAX_NOTES
        report.notes[MAX_NOTES:] = [f"... and {more} more open ports that did not identify"]
    return report


def _identify_safely(identify: Identify, host: str, ports: Mapping[str, int],
                     deadline: float) -> DeviceInfo | str | None:
    """``identify``'s answer; a bug or an unexpected peer in it costs one note, never the scan."""
    try:
        return identify(host, ports, deadline)
    except Exception as exc:  # a hostile peer must not end the scan with a traceback
        return f"{host}: not identified ({type(exc).__name__}: {exc})"


def _summary(n_hosts: int, n_ports: int, states: Mapping[tuple[str, int], str]) -> str:
    counts: dict[str, int] = {}
    for state in states.values():
        counts[state] = counts.get(state, 0) + 1
    shown = ", ".join(f"{counts[s]} {s}" for s in ("open", "refused", "silent", "unreachable", "not tried")
                      if s in counts)
    return (f"{n_hosts} host{'s' * (n_hosts != 1)} x {n_ports} port{'s' * (n_ports != 1)}: {shown}")


# ------------------------------------------------------------ bounded I/O for the identify step
def open_connection(host: str, port: int, deadline: float) -> socket.socket:
    """A connected blocking socket; every later read must set its own timeout from ``deadline``.

    Raises:
        TimeoutError: If the deadline has passed or the connection is not made by then.
        OSError: If the connection fails.
    """
    remaining = deadline - time.monotonic()
    if remaining <= 0:
        raise TimeoutError
    return socket.create_connection((host, port), timeout=remaining)


def read_exact(sock: socket.socket, n: int, deadline: float) -> bytes:
    """Exactly ``n`` bytes by ``deadline``.

    Raises:
        TimeoutError: If they do not arrive in time.
        ConnectionError: If the peer closes first.
    """
    buf = bytearray()
    while len(buf) < n:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise TimeoutError
        sock.settimeout(remaining)
        chunk = sock.recv(n - len(buf))
        if not chunk:
            raise ConnectionError("the peer closed the connection")
        buf += chunk
    return bytes(buf)


def read_line(sock: socket.socket, deadline: float, max_bytes: int = 256) -> bytes:
    """One ``\\n``-terminated line (without its line end) of at most ``max_bytes`` by ``deadline``.

    Raises:
        TimeoutError: If no whole line arrives in time.
        ConnectionError: If the peer closes first.
        ValueError: If ``max_bytes`` arrive without a line end.
    """
    buf = bytearray()
    while True:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise TimeoutError
        sock.settimeout(remaining)
        chunk = sock.recv(1)  # a line at a time: nothing after it is consumed
        if not chunk:
            raise ConnectionError("the peer closed the connection")
        if chunk == b"\n":
            return bytes(buf).rstrip(b"\r")
        buf += chunk
        if len(buf) >= max_bytes:
            raise ValueError(f"no line end within {max_bytes} bytes")


def device_text(value: object, max_len: int = 64) -> str | None:
    """``value`` if it is a short printable ASCII string (stripped), else None (never trust a peer)."""
    if isinstance(value, bytes):
        try:
            value = value.decode("ascii")
        except UnicodeDecodeError:
            return None
    if not isinstance(value, str):
        return None
    text = value.strip()
    if len(text) > max_len or not all(" " <= ch <= "~" for ch in text):
        return None
    return text
