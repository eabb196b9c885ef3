"""The O3R configuration channel: JSON over XML-RPC, each call bounded in time and size, parsed by defusedxml.

``get([json pointers]) -> JSON text`` and ``set(JSON text)`` at
``http://<host>:<port>/api/rpc/v1/com.ifm.efector/`` (protocols.md A1). Why not
``xmlrpc.client.ServerProxy``: see ADR 0015.
"""

from __future__ import annotations

import json
import xmlrpc.client
from typing import Any
from xml.parsers.expat import ExpatError

from defusedxml.xmlrpc import DefusedExpatParser

from cellcal.devices.errors import (
    ConfigError,
    DeviceConnectionError,
    DeviceTimeoutError,
    ProtocolError,
    VendorError,
)
from cellcal.drivers import o3r_json as config_values
from cellcal.drivers.o3r_json import PortInfo

from .rpc_http import post

RPC_PATH = "/api/rpc/v1/com.ifm.efector/"
#: Default cap on one XML-RPC reply, bytes (a whole VPU tree is tens of kB).
DEFAULT_MAX_REPLY = 4 * 1024 * 1024
#: Deepest nesting of XML-RPC arrays/structs accepted (O3R replies are one string).
MAX_DEPTH = 32
#: Default deadline of one ``set`` (state changes and CONF-only settings are slow on a VPU; ifm3d allows 15 s).
DEFAULT_SET_TIMEOUT_S = 15.0
#: Longest fault text kept in an error message, characters.
_MAX_FAULT_TEXT = 200
#: What a malformed reply can raise inside the XML, XML-RPC and JSON parsers.
_PARSE_ERRORS = (ExpatError, ValueError, TypeError, LookupError, ArithmeticError, RecursionError,
                 xmlrpc.client.Error)

__all__ = ["DEFAULT_MAX_REPLY", "RPC_PATH", "O3RConfigClient", "PortInfo", "parse_reply"]


class _ShallowUnmarshaller(xmlrpc.client.Unmarshaller):
    """The stdlib unmarshaller, refusing arrays and structs nested deeper than :data:`MAX_DEPTH`."""

    def start(self, tag: str, attrs: Any) -> None:
        if tag in ("array", "struct") and len(self._marks) >= MAX_DEPTH:
            raise xmlrpc.client.ResponseError(f"arrays/structs nested deeper than {MAX_DEPTH}")
        super().start(tag, attrs)


def _show_param(param: Any) -> str:
    """A request parameter for messages: pointer lists in full (shortened), other values as :func:`show`."""
    if isinstance(param, list) and all(isinstance(p, str) for p in param):
        text = "[" + ", ".join(repr(p) for p in param) + "]"
        return text if len(text) <= 80 else text[:77] + "..."
    return config_values.show(param)


def _reason(exc: BaseException) -> str:
    """An exception's own words, escaped and cut for a one-line message."""
    text = exc.args[0] if exc.args and isinstance(exc.args[0], str) else str(exc)
    return config_values.clip(text, 120)


def _no_constant(name: str) -> Any:
    raise ValueError(f"{name} is not JSON")


def parse_reply(body: bytes, what: str) -> Any:
    """The single value of an XML-RPC ``methodResponse``, parsed without entities or DTDs.

    Args:
        body: The HTTP response body.
        what: Names the call, e.g. ``"O3R 10.0.0.1:80 get(['/ports'])"``.

    Raises:
        VendorError: A well-formed fault (integer faultCode, string faultString).
        ProtocolError: Anything else that is not one well-formed value.
    """
    unmarshaller = _ShallowUnmarshaller()
    try:
        parser = DefusedExpatParser(unmarshaller, forbid_dtd=True)
        parser.feed(body)
        parser.close()
        values = unmarshaller.close()
    except xmlrpc.client.Fault as fault:
        code, text = fault.faultCode, fault.faultString
        if not isinstance(code, int) or isinstance(code, bool) or not isinstance(text, str):
            raise ProtocolError(f"{what}: fault reply with faultCode {config_values.show(code)} and "
                                f"faultString {config_values.show(text)} (expected an integer and a string)"
                                ) from None
        shown = text.encode("unicode_escape").decode("ascii")[:_MAX_FAULT_TEXT]
        raise VendorError("o3r", code, f"{what}: {shown}") from None
    except _PARSE_ERRORS as exc:
        raise ProtocolError(f"{what}: malformed XML-RPC reply ({type(exc).__name__}: {_reason(exc)})") from None
    if len(values) != 1:
        raise ProtocolError(f"{what}: XML-RPC reply holds {len(values)} values, expected 1")
    return values[0]


def parse_json_object(text: Any, what: str) -> dict[str, Any]:
    """A JSON object from a reply string (depth, size and constants checked).

    Raises:
        ProtocolError: Not a string, not JSON (incl. NaN/Infinity, nesting too deep), or not an object.
    """
    if not isinstance(text, str):
        raise ProtocolError(f"{what}: answered {config_values.show(text)}, expected a JSON string")
    try:
        doc = json.loads(text, parse_constant=_no_constant)
    except RecursionError:
        raise ProtocolError(f"{what}: the JSON answer is nested too deeply") from None
    except ValueError as exc:
        raise ProtocolError(f"{what}: the answer is not JSON ({_reason(exc)})") from None
    if not isinstance(doc, dict):
        raise ProtocolError(f"{what}: the JSON answer is {config_values.show(doc)}, expected an object")
    return doc


class O3RConfigClient:
    """Blocking XML-RPC client for the O3R JSON configuration.

    Args:
        host: VPU address.
        port: XML-RPC TCP port (80 on a real VPU).
        timeout_s: Deadline of one whole call (connect + request + full reply), seconds.
        max_reply_bytes: Cap on one reply body, bytes.
        set_timeout_s: Deadline of one ``set`` call, seconds (its own, longer: a VPU
            applies a state change or a CONF-only setting before it answers).
    """

    def __init__(self, host: str, port: int = 80, timeout_s: float = 2.0,
                 max_reply_bytes: int = DEFAULT_MAX_REPLY, set_timeout_s: float = DEFAULT_SET_TIMEOUT_S) -> None:
        self.host = host
        self.port = port
        self.timeout_s = timeout_s
        self.max_reply_bytes = max_reply_bytes
        self.set_timeout_s = set_timeout_s

    def _where(self, method: str, params: tuple[Any, ...]) -> str:
        shown = ", ".join(_show_param(p) for p in params)
        return f"O3R XML-RPC {self.host}:{self.port} {method}({shown})"

    def call(self, method: str, *params: Any, timeout: float | None = None) -> Any:
        """Call one XML-RPC method within ``min(timeout_s, timeout)`` seconds (``set_timeout_s`` for ``set``).

        Raises:
            DeviceTimeoutError: The whole call did not finish in time.
            DeviceConnectionError: Connection refused / reset / unreachable, or an HTTP error status.
            VendorError: The device answered with an XML-RPC fault.
            ProtocolError: The answer is not one well-formed XML-RPC value, or exceeds the size cap.
        """
        own = self.set_timeout_s if method == "set" else self.timeout_s
        limit = own if timeout is None else min(own, timeout)
        where = self._where(method, params)
        if limit <= 0:
            raise DeviceTimeoutError(f"{where}: no time left for the call")
        request = xmlrpc.client.dumps(params, method, encoding="utf-8", allow_none=True).encode("utf-8")
        status, reason, body = post(self.host, self.port, RPC_PATH, request, timeout_s=limit,
                                    max_bytes=self.max_reply_bytes, where=where)
        if status != 200:
            raise DeviceConnectionError(f"{where}: HTTP {status} {config_values.show(reason)}")
        return parse_reply(body, where)

    def get(self, pointers: list[str], *, timeout: float | None = None) -> dict[str, Any]:
        """The configuration sub-tree holding ``pointers`` (everything when empty)."""
        text = self.call("get", list(pointers), timeout=timeout)
        return parse_json_object(text, self._where("get", (list(pointers),)))

    def set(self, patch: dict[str, Any], *, timeout: float | None = None) -> None:
        """Merge a partial configuration, within ``set_timeout_s`` (or ``timeout`` if shorter)."""
        self.call("set", json.dumps(patch), timeout=timeout)

    def port_info(self, port: str, *, timeout: float | None = None, kind: str | None = None) -> PortInfo:
        """Read and check a port's PCIC port, type, state and resolution.

        Args:
            port: Port name, e.g. ``"port2"``.
            timeout: Deadline of the call, s (at most ``timeout_s``).
            kind: If given, the type the port must have (``"3D"``).

        Raises:
            ConfigError: If the VPU has no such port, or it is not of ``kind`` (naming the VPU's ports and heads).
            ProtocolError: If a value is missing, of the wrong type or out of range (naming its JSON pointer).
        """
        doc = self.get(["/ports"], timeout=timeout)
        return config_values.port_info(doc, port, host=self.host, where=self._where("get", (["/ports"],)), kind=kind)

    def ports(self, *, timeout: float | None = None) -> tuple[list[PortInfo], list[str]]:
        """Every port of the VPU (sorted by name), and one line per port that could not be read.

        Raises:
            ProtocolError: If the answer holds no ``/ports`` object.
        """
        doc = self.get(["/ports"], timeout=timeout)
        where = self._where("get", (["/ports"],))
        ports = config_values.child(doc, "ports", "", where)
        if not isinstance(ports, dict):
            raise ProtocolError(f"{where}: /ports must be an object, got {config_values.show(ports)}")
        found: list[PortInfo] = []
        unread: list[str] = []
        for name in sorted(str(k) for k in list(ports)[:config_values.MAX_PORTS]):
            try:
                found.append(config_values.port_info(doc, name, host=self.host, where=where))
            except (ProtocolError, ConfigError) as exc:
                unread.append(f"{config_values.clip(name, 16)}: {str(exc).removeprefix(where + ': ')}")
        return found, unread

    def set_state(self, port: str, state: str, *, timeout: float | None = None) -> None:
        """Set ``/ports/<port>/state`` (RUN / IDLE / CONF)."""
        self.set({"ports": {port: {"state": state}}}, timeout=timeout)

    def firmware(self, *, timeout: float | None = None) -> str:
        """Firmware version string ('' if the device does not say, or says something malformed)."""
        try:
            doc = self.get(["/device/swVersion"], timeout=timeout)
            return config_values.firmware(doc, self._where("get", (["/device/swVersion"],)))
        except (VendorError, ProtocolError):
            return ""
