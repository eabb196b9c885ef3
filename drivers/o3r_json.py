"""Values read from the O3R JSON configuration, checked against the documented tree (protocols.md A1).

Shared by ifm's two backends, ``o3r`` (its own XML-RPC client) and ``o3r-ifm3d`` (ifm3dpy): the
tree is the VPU's whichever client reads it.

Every check names the JSON pointer of the value and shows it shortened, so a device that
sends ``1e308`` as a port, a list as a state or a 300-digit number fails with one line.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from cellcal.devices.errors import ConfigError, ProtocolError

#: Port states of ``/ports/portN/state``.
STATES = ("RUN", "IDLE", "CONF")
#: Largest image side a head reports, px (the biggest O3R imager is 1280 x 800).
MAX_SIDE = 8192
#: Longest plausible short text in the tree (a type, a firmware version), characters.
MAX_TEXT = 64
#: Most ports named in a message (a VPU has port0..port6).
MAX_PORTS = 16


@dataclass(frozen=True)
class PortInfo:
    """One VPU port as the configuration reports it.

    Attributes:
        name: Port name, e.g. ``"port2"``.
        pcic_port: Its PCIC TCP port, 1..65535.
        type: ``"2D"`` or ``"3D"`` (``/info/features/type``; other short texts pass and are refused later).
        state: ``RUN``, ``IDLE`` or ``CONF``.
        width, height: Resolution from ``/info/features/resolution``, px (0 if absent).
    """

    name: str
    pcic_port: int
    type: str
    state: str
    width: int = 0
    height: int = 0


def pointer(*keys: str) -> str:
    """A JSON pointer from keys (``~`` and ``/`` escaped as RFC 6901 says)."""
    return "".join("/" + k.replace("~", "~0").replace("/", "~1") for k in keys)


def show(value: Any) -> str:
    """A short, single-line rendering of a device value for an error message."""
    if isinstance(value, (dict, list)):
        return "an object" if isinstance(value, dict) else "an array"
    if isinstance(value, int) and not isinstance(value, bool) and abs(value) >= 10**15:
        return f"an integer of {value.bit_length()} bits"
    # texts: control characters escaped and cut, so the message stays one readable line
    if isinstance(value, str):
        return "'" + clip(value, 46) + "'"
    if isinstance(value, (bytes, bytearray)):
        return "b'" + clip(bytes(value).decode("latin-1"), 46) + "'"
    return "null" if value is None else repr(value)[:48]


def clip(text: str, limit: int = 200) -> str:
    """Device text for a message: control characters escaped, at most ``limit`` characters."""
    escaped = text.encode("unicode_escape").decode("ascii")
    return escaped if len(escaped) <= limit else escaped[:limit - 3] + "..."


def _fail(where: str, ptr: str, expected: str, value: Any) -> ProtocolError:
    return ProtocolError(f"{where}: {ptr} must be {expected}, got {show(value)}")


def child(node: Any, key: str, ptr: str, where: str) -> Any:
    """``node[key]`` where ``node`` must be a JSON object holding ``key``.

    Raises:
        ProtocolError: ``node`` is not an object, or lacks ``key``.
    """
    if not isinstance(node, dict):
        raise _fail(where, ptr, "an object", node)
    if key not in node:
        raise ProtocolError(f"{where}: {pointer_join(ptr, key)} is missing")
    return node[key]


def pointer_join(ptr: str, key: str) -> str:
    return ptr + pointer(key)


def int_in(value: Any, lo: int, hi: int, ptr: str, where: str) -> int:
    """An integer (not a bool, not a float) in ``lo..hi``."""
    if not isinstance(value, int) or isinstance(value, bool) or not lo <= value <= hi:
        raise _fail(where, ptr, f"an integer in {lo}..{hi}", value)
    return value


def text(value: Any, ptr: str, where: str, choices: tuple[str, ...] = ()) -> str:
    """A short printable string, one of ``choices`` if given."""
    if choices:
        if not isinstance(value, str) or value not in choices:
            raise _fail(where, ptr, "one of " + ", ".join(choices), value)
        return value
    if not isinstance(value, str) or not 0 < len(value) <= MAX_TEXT or not value.isprintable():
        raise _fail(where, ptr, f"a printable string of 1..{MAX_TEXT} characters", value)
    return value


def ports_of_type(ports: Any, kind: str) -> list[str]:
    """Names of the ports whose ``/info/features/type`` is ``kind``, read leniently (for messages), sorted.

    Args:
        ports: The ``/ports`` object of the tree (anything else: no ports).
        kind: ``"3D"``, ``"2D"``, ``"IMU"``.
    """
    if not isinstance(ports, dict):
        return []
    out = []
    for name, node in list(ports.items())[:MAX_PORTS]:
        info = node.get("info") if isinstance(node, dict) else None
        features = info.get("features") if isinstance(info, dict) else None
        if isinstance(features, dict) and features.get("type") == kind:
            out.append(clip(str(name), 16))
    return sorted(out)


def _heads_note(ports: Any, kind: str) -> str:
    names = ports_of_type(ports, kind)
    return f"its {kind} heads: {', '.join(names)}" if names else f"it has no {kind} head"


def port_info(doc: Any, port: str, *, host: str, where: str, kind: str | None = None) -> PortInfo:
    """Read a port's PCIC port, type, state and resolution from a ``get(['/ports'])`` answer.

    Args:
        doc: The decoded JSON answer.
        port: Port name, e.g. ``"port2"``.
        host: VPU address (for the unknown-port message).
        where: Names the call in messages, e.g. ``"O3R 192.168.0.69:80 get(['/ports'])"``.
        kind: If given, the type the port must have (``"3D"``).

    Raises:
        ConfigError: If the VPU has no such port, or (with ``kind``) the port is of another type; the
            message names the VPU's ports and its heads of ``kind``.
        ProtocolError: If a value is missing, of the wrong type or out of range (naming its pointer).
    """
    ports = child(doc, "ports", "", where)
    if not isinstance(ports, dict):
        raise _fail(where, "/ports", "an object", ports)
    if port not in ports:
        names = ", ".join(sorted(clip(str(k), 16) for k in list(ports)[:MAX_PORTS]))
        raise ConfigError(f"O3R at {host} has no port {clip(port, 16)!r} (ports: {names or 'none'}); "
                          f"{_heads_note(ports, kind or '3D')}", key="camera.port")
    base = pointer("ports", port)
    node = ports[port]
    data = child(node, "data", base, where)
    pcic = int_in(child(data, "pcicTCPPort", base + "/data", where), 1, 65535, base + "/data/pcicTCPPort", where)
    info = child(node, "info", base, where)
    features = child(info, "features", base + "/info", where)
    fptr = base + "/info/features"
    found = text(child(features, "type", fptr, where), fptr + "/type", where)
    if kind is not None and found != kind:
        article = "an" if found[:1] in "AEIOU" else "a"
        raise ConfigError(f"O3R at {host}: {port} is {article} {clip(found, 16)} port, not a {kind} head; "
                          f"{_heads_note(ports, kind)}", key="camera.port")
    state = text(child(node, "state", base, where), base + "/state", where, STATES)
    width = height = 0
    if isinstance(features, dict) and "resolution" in features:
        res = features["resolution"]
        width = int_in(child(res, "width", fptr + "/resolution", where), 1, MAX_SIDE, fptr + "/resolution/width",
                       where)
        height = int_in(child(res, "height", fptr + "/resolution", where), 1, MAX_SIDE,
                        fptr + "/resolution/height", where)
    return PortInfo(name=port, pcic_port=pcic, type=found, state=state, width=width, height=height)


def firmware(doc: Any, where: str) -> str:
    """``/device/swVersion/firmware`` of a ``get(['/device/swVersion'])`` answer.

    Raises:
        ProtocolError: If it is missing or not a short printable string.
    """
    device = child(doc, "device", "", where)
    sw = child(device, "swVersion", "/device", where)
    return text(child(sw, "firmware", "/device/swVersion", where), "/device/swVersion/firmware", where)
