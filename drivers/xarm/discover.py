"""xArm network discovery: which hosts answer GET_VERSION and GET_ROBOT_SN on the control port (TCP 502).

The same register protocol the driver speaks (:mod:`.tcp_protocol`): one request at a
time, frames cut by :class:`~.tcp_protocol.TcpFrameSplitter` (bounded), feedback frames
skipped, the reply matched by transaction id and register; every value is checked before
it is shown.
"""

from __future__ import annotations

import ipaddress
import socket
import time
from collections.abc import Mapping, Sequence
from typing import Any

from cellcal.devices import discovery
from cellcal.devices.errors import ProtocolError
from cellcal.devices.types import DeviceInfo

from .registers import VERSION_LEN, Reg, decode_serials, decode_text, parse_version
from .tcp_protocol import FEEDBACK_REGISTER, PROTOCOL_ID, TcpFrameSplitter, encode_tcp_request, parse_tcp_reply

#: Standard port by service name (``cellcal devices --ports xarm=N`` overrides).
PORTS: dict[str, int] = {"xarm": 502}

#: The control box's factory address is 192.168.1.xxx, xxx printed on the box's label
#: (UFACTORY xArm user manual, "Network connection"; ADR 0019): the whole 192.168.1.0/24.
FACTORY_HOSTS: tuple[str, ...] = tuple(str(h) for h in ipaddress.ip_network("192.168.1.0/24").hosts())

#: Frames read for one reply before giving up (feedback frames may come first).
MAX_FRAMES = 8
#: Bytes read at a time.
_CHUNK = 1024


def scan_hosts(hosts: Sequence[str] | None, timeout: float, ports: Mapping[str, int] | None = None
               ) -> discovery.HostScan:
    """xArm controllers among ``hosts`` (None: :data:`FACTORY_HOSTS`), within ``timeout`` seconds.

    Args:
        hosts: IP addresses to probe.
        timeout: Seconds for the whole scan.
        ports: Port overrides by service name (key ``"xarm"``; others are ignored).
    """
    chosen = {k: int((ports or {}).get(k, v)) for k, v in PORTS.items()}
    return discovery.scan(list(FACTORY_HOSTS if hosts is None else hosts), chosen, timeout, identify)


def identify(host: str, open_ports: Mapping[str, int], deadline: float) -> DeviceInfo | str | None:
    """The xArm at ``host`` from its version and serial registers, a one-line note, or None."""
    port = open_ports.get("xarm")
    if port is None:
        return None
    where = f"{host}:{port}"
    try:
        with discovery.open_connection(host, port, deadline) as sock:
            splitter = TcpFrameSplitter()
            version_data = _ask(sock, splitter, 1, Reg.GET_VERSION, deadline)
            serial_data = _ask(sock, splitter, 2, Reg.GET_ROBOT_SN, deadline)
    except TimeoutError:
        return f"{where}: accepted, but no xArm reply in time (not an xArm)"
    except ProtocolError as exc:
        return f"{where}: not an xArm ({str(exc)[:120]})"
    except OSError as exc:
        return f"{where}: not an xArm ({exc.strerror or type(exc).__name__})"
    text = discovery.device_text(decode_text(version_data), max_len=VERSION_LEN)
    version = parse_version(text or "")
    if not text or version.firmware is None:
        return f"{where}: not an xArm (its version reply is not 'axes,type,serial,box,vX.Y.Z')"
    robot_sn, _box = decode_serials(serial_data)
    serial = discovery.device_text(robot_sn) or discovery.device_text(version.robot_sn) or ""
    axes = version.axes if version.axes in (5, 6, 7) else None
    extra: dict[str, Any] = {"host": host, "port": port}
    if version.arm_type is not None:
        extra["arm_type"] = version.arm_type
    box = discovery.device_text(_box) or discovery.device_text(version.box_sn)
    if box:
        extra["control_box"] = box
    return DeviceInfo(backend="xarm", vendor="UFACTORY", model=f"xArm{axes}" if axes else "xArm",
                      serial=serial, firmware="{}.{}.{}".format(*version.firmware), extra=extra)


def _ask(sock: socket.socket, splitter: TcpFrameSplitter, tid: int, register: int, deadline: float) -> bytes:
    """Send one register read; its reply's data bytes.

    Raises:
        TimeoutError: If no matching reply arrives by ``deadline``.
        ProtocolError: If the peer's bytes are not the xArm protocol.
        OSError: If the connection fails.
    """
    sock.sendall(encode_tcp_request(tid, register))
    frames = 0
    while frames < MAX_FRAMES:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise TimeoutError
        sock.settimeout(remaining)
        chunk = sock.recv(_CHUNK)
        if not chunk:
            raise ProtocolError("the peer closed the connection without a reply")
        for raw in splitter.feed(chunk):
            frames += 1
            frame = parse_tcp_reply(raw)
            if frame.register == FEEDBACK_REGISTER:
                continue
            if frame.protocol != PROTOCOL_ID or frame.transaction_id != tid or frame.register != register:
                raise ProtocolError(f"reply (id {frame.transaction_id}, protocol {frame.protocol}, register "
                                    f"{frame.register}) does not answer request {tid} for register {register}")
            return frame.reply.data
    raise ProtocolError(f"{MAX_FRAMES} frames without a reply to register {register}")
