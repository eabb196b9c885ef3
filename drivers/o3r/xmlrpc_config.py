"""The O3R configuration channel: JSON over XML-RPC (stdlib ``xmlrpc.client`` with timeouts).

``get([json pointers]) -> JSON text`` and ``set(JSON text)`` at
``http://<host>:<port>/api/rpc/v1/com.ifm.efector/`` (protocols.md A1).
"""

from __future__ import annotations

import http.client
import json
import xmlrpc.client
from dataclasses import dataclass
from typing import Any

from cellcal.devices.errors import (
    ConfigError,
    DeviceConnectionError,
    DeviceTimeoutError,
    ProtocolError,
    VendorError,
)

RPC_PATH = "/api/rpc/v1/com.ifm.efector/"


class _TimeoutTransport(xmlrpc.client.Transport):
    """An XML-RPC transport whose HTTP connection has a socket timeout."""

    def __init__(self, timeout_s: float) -> None:
        super().__init__()
        self.timeout_s = timeout_s

    def make_connection(self, host: Any) -> http.client.HTTPConnection:
        conn = super().make_connection(host)
        conn.timeout = self.timeout_s
        return conn


@dataclass(frozen=True)
class PortInfo:
    """One VPU port as the configuration reports it.

    Attributes:
        name: Port name, e.g. ``"port2"``.
        pcic_port: Its PCIC TCP port.
        type: ``"2D"`` or ``"3D"`` (``/info/features/type``).
        state: ``RUN``, ``IDLE`` or ``CONF``.
        width, height: Resolution from ``/info/features/resolution`` (0 if absent).
    """

    name: str
    pcic_port: int
    type: str
    state: str
    width: int = 0
    height: int = 0


class O3RConfigClient:
    """Blocking XML-RPC client for the O3R JSON configuration.

    Args:
        host: VPU address.
        port: XML-RPC TCP port (80 on a real VPU).
        timeout_s: Socket timeout of every call, seconds.
    """

    def __init__(self, host: str, port: int = 80, timeout_s: float = 2.0) -> None:
        self.host = host
        self.port = port
        self.timeout_s = timeout_s
        self._url = f"http://{host}:{port}{RPC_PATH}"

    def _proxy(self) -> xmlrpc.client.ServerProxy:
        return xmlrpc.client.ServerProxy(self._url, transport=_TimeoutTransport(self.timeout_s), allow_none=True)

    def call(self, method: str, *params: Any) -> Any:
        """Call one XML-RPC method, translating failures into cellcal errors.

        Raises:
            DeviceTimeoutError: No answer within the timeout.
            DeviceConnectionError: Connection refused / reset / host unreachable.
            VendorError: The device answered with an XML-RPC fault.
            ProtocolError: The answer is not valid XML-RPC.
        """
        where = f"O3R XML-RPC {self.host}:{self.port}"
        try:
            with self._proxy() as proxy:
                return getattr(proxy, method)(*params)
        except xmlrpc.client.Fault as exc:
            raise VendorError("o3r", int(exc.faultCode), f"{method}: {exc.faultString}") from None
        except TimeoutError:
            raise DeviceTimeoutError(f"{where}: no answer to '{method}' within {self.timeout_s:g} s") from None
        except xmlrpc.client.ProtocolError as exc:
            raise DeviceConnectionError(f"{where}: HTTP {exc.errcode} {exc.errmsg} for '{method}'") from None
        except (xmlrpc.client.ResponseError, http.client.HTTPException, ValueError) as exc:
            raise ProtocolError(f"{where}: malformed answer to '{method}': {exc}") from None
        except OSError as exc:
            raise DeviceConnectionError(f"{where}: cannot reach the device ({exc.strerror or exc})") from None

    def get(self, pointers: list[str]) -> dict[str, Any]:
        """The configuration sub-tree holding ``pointers`` (everything when empty)."""
        text = self.call("get", list(pointers))
        try:
            doc = json.loads(text)
        except (TypeError, ValueError):
            raise ProtocolError(f"O3R get({pointers}) returned non-JSON text") from None
        if not isinstance(doc, dict):
            raise ProtocolError(f"O3R get({pointers}) returned {type(doc).__name__}, not an object")
        return doc

    def set(self, patch: dict[str, Any]) -> None:
        """Merge a partial configuration."""
        self.call("set", json.dumps(patch))

    def port_info(self, port: str) -> PortInfo:
        """Read a port's PCIC port, type, state and resolution.

        Raises:
            ConfigError: If the VPU has no such port.
            ProtocolError: If the answer lacks the expected fields.
        """
        doc = self.get(["/ports"])
        ports = doc.get("ports", {})
        if not isinstance(ports, dict) or port not in ports:
            names = ", ".join(sorted(ports)) if isinstance(ports, dict) else "none"
            raise ConfigError(f"O3R at {self.host} has no port {port!r} (ports: {names})", key="camera.port")
        p = ports[port]
        try:
            res = p.get("info", {}).get("features", {}).get("resolution", {}) or {}
            return PortInfo(name=port, pcic_port=int(p["data"]["pcicTCPPort"]),
                            type=str(p["info"]["features"]["type"]), state=str(p["state"]),
                            width=int(res.get("width", 0)), height=int(res.get("height", 0)))
        except (KeyError, TypeError, ValueError, AttributeError):
            raise ProtocolError(f"O3R port {port!r}: configuration lacks data/pcicTCPPort, "
                                f"info/features/type or state") from None

    def set_state(self, port: str, state: str) -> None:
        """Set ``/ports/<port>/state`` (RUN / IDLE / CONF)."""
        self.set({"ports": {port: {"state": state}}})

    def firmware(self) -> str:
        """Firmware version string ('' if the device does not say)."""
        try:
            doc = self.get(["/device/swVersion"])
            return str(doc.get("device", {}).get("swVersion", {}).get("firmware", ""))
        except (VendorError, ProtocolError):
            return ""
