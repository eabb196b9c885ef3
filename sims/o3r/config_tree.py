"""The emulated O3R's JSON configuration tree and its ``get`` / ``set`` semantics.

``get(pointers)`` returns the sub-tree holding just the requested JSON pointers
(``get([])`` the whole tree); ``set(json)`` merges a partial tree after checking every
key against the tree and a schema-like table (:data:`RULES`): ``readOnly`` values
refuse writes, CONF-only values (the mode) can be written only while their port is in
CONF, ``state`` is RUN/IDLE/CONF and numbers stay in their range. Port numbering is a
VPU's: ``portN`` serves PCIC on 50010 + N (port6 the IMU), application instances from
51010 (ifm documentation, ``ports_overview.md``); the caller passes the bound numbers.
"""

from __future__ import annotations

import copy
import fnmatch
import json
import threading
from collections.abc import Callable, Mapping, MutableSet, Sequence
from collections.abc import Set as AbstractSet
from dataclasses import dataclass
from typing import Any

from .options import two_d_partners

FIRMWARE = "1.4.30"
STATES = ("RUN", "IDLE", "CONF")
#: Prefix of every fault text: the codes are this emulator's own, not ifm's.
FAULT_LABEL = "cellcal O3R emulator"
#: Fault codes (the emulator's own): unknown pointer / key, invalid value, malformed JSON, read-only,
#: CONF-only setting written outside CONF.
UNKNOWN, INVALID, MALFORMED, READ_ONLY, CONF_ONLY = 901000, 901001, 901002, 901003, 901004


@dataclass(frozen=True)
class Rule:
    """How the schema treats the values at a pointer pattern (``*`` matches one key)."""

    pattern: str
    read_only: bool = False
    conf_only: bool = False
    minimum: float | None = None
    maximum: float | None = None


#: The schema-like table, first match wins; pointers matching nothing are writable.
RULES: tuple[Rule, ...] = (
    Rule("/device/info/name"), Rule("/device/info/description"),
    Rule("/device/info/*", read_only=True), Rule("/device/swVersion/*", read_only=True),
    Rule("/device/diagnostic/*", read_only=True), Rule("/device/state/*", read_only=True),
    Rule("/ports/*/info/*", read_only=True), Rule("/ports/*/data/*", read_only=True),
    Rule("/applications/instances/*/data/*", read_only=True),
    Rule("/ports/*/mode", conf_only=True),
    Rule("/ports/*/acquisition/framerate", minimum=0.1, maximum=30.0),
    Rule("/ports/*/processing/extrinsicHeadToUser/rot*", minimum=-6.3, maximum=6.3),
    Rule("/ports/*/processing/extrinsicHeadToUser/trans*", minimum=-100.0, maximum=100.0),
)
#: Modes a 3D head of the emulator accepts (the names of O3R222 modes).
MODES_3D = ("standard_range2m", "standard_range4m", "extended_range4m", "cyclic_4m_2m_4m_2m")


class ConfigTreeError(Exception):
    """A rejected get/set; ``code`` is the XML-RPC fault code (the emulator's own, see :data:`FAULT_LABEL`)."""

    def __init__(self, code: int, message: str) -> None:
        super().__init__(f"{FAULT_LABEL} (own code {code}): {message}")
        self.code = code


def rule_for(pointer: str, rules: Sequence[Rule] = RULES) -> Rule | None:
    """The first rule whose pattern matches ``pointer`` (``*`` spans one key)."""
    depth = pointer.count("/")
    for rule in rules:
        if rule.pattern.count("/") == depth and fnmatch.fnmatchcase(pointer, rule.pattern):
            return rule
    return None


def _head(kind: str, pcic_port: int, state: str, serial: str, name: str, **features: Any) -> dict[str, Any]:
    """One port node: its PCIC port, info (type and features), state and, for a camera head, its extrinsic."""
    zero = {"transX": 0.0, "transY": 0.0, "transZ": 0.0, "rotX": 0.0, "rotY": 0.0, "rotZ": 0.0}
    node: dict[str, Any] = {"data": {"pcicTCPPort": int(pcic_port)},
                            "info": {"features": {"type": kind, **features}, "name": name, "serialNumber": serial},
                            "state": state}
    if kind in ("2D", "3D"):
        node["processing"] = {"extrinsicHeadToUser": dict(zero)}
    return node


def default_tree(*, heads: Mapping[str, tuple[int, int]], pcic_ports: Mapping[str, int], state: str,
                 frame_rate_hz: float, mode: str = "standard_range4m") -> dict[str, Any]:
    """A VPU tree: a 3D head on each port of ``heads`` (port -> 3D resolution, width and height in px; the
    first is the one application ``app0`` uses), the 2D head of each (:func:`~.options.two_d_partners`),
    the IMU on port6 and ``app0``; ``pcic_ports`` maps each of those names to its bound PCIC port.

    Every 3D head starts in ``state`` at ``frame_rate_hz`` in ``mode``; head k's 2D and 3D
    imagers have serial numbers ``100 k + 1`` and ``100 k + 2`` (the IMU ``3``).
    """
    names = list(heads)
    partners = two_d_partners(names)
    ports: dict[str, dict[str, Any]] = {}
    for k, name in enumerate(names):
        width, height = heads[name]
        ports[name] = _head("3D", pcic_ports[name], state, f"{100 * k + 2:012d}", "O3R222 3D",
                            resolution={"width": width, "height": height}, fov={"horizontal": 60, "vertical": 45})
        ports[name].update(mode=mode, acquisition={"framerate": float(frame_rate_hz)})
    for k, name in enumerate(partners):
        ports[name] = _head("2D", pcic_ports[name], "RUN", f"{100 * k + 1:012d}", "O3R222 2D",
                            resolution={"width": 1280, "height": 800})
        ports[name].update(mode="standard_autoexposure2D", acquisition={"framerate": 10.0})
    ports["port6"] = _head("IMU", pcic_ports["port6"], "RUN", "000000000003", "VPU IMU")
    app = {"app0": {"class": "ods", "name": "", "ports": names[:1], "state": "CONF",
                    "data": {"pcicTCPPort": int(pcic_ports["app0"])}}}
    return {
        "applications": {"instances": app},
        "device": {
            "clock": {"currentTime": 0, "sntp": {"active": False}},
            "diagnostic": {"data": {"pcicPort": 50009}, "temperatures": []},
            "info": {"name": "cellcal-emulator", "description": "emulated O3R VPU", "partNumber": "M04239",
                     "productCode": "OVP800", "serialNumber": "000000000000", "vendor": "ifm electronic gmbh",
                     "features": {}},
            "network": {"interfaces": {"eth0": {"ipv4": {"address": "127.0.0.1", "mask": 8}}}},
            "state": {"errorMessage": "", "errorCode": 0},
            "swVersion": {"firmware": FIRMWARE, "kernel": "emulated", "l4t": "emulated"},
        },
        "ports": dict(sorted(ports.items())),
    }


def schema_of(node: Any, pointer: str = "", rules: Sequence[Rule] = RULES) -> dict[str, Any]:
    """A JSON-schema-like description of a tree, with ``readOnly`` as the rules say."""
    if isinstance(node, dict):
        return {"type": "object", "additionalProperties": False,
                "properties": {k: schema_of(v, f"{pointer}/{k}", rules) for k, v in node.items()}}
    kind = {bool: "boolean", int: "integer", float: "number", str: "string", list: "array"}.get(type(node), "null")
    out: dict[str, Any] = {"type": kind}
    rule = rule_for(pointer, rules)
    if rule is not None:
        out["readOnly"] = rule.read_only
        if rule.conf_only:
            out["description"] = "settable only while the port is in CONF"
        if rule.minimum is not None:
            out.update(minimum=rule.minimum, maximum=rule.maximum)
    if pointer.endswith("/state") and pointer.startswith("/ports/"):
        out["enum"] = list(STATES)
    return out


def _split(pointer: str) -> list[str]:
    if pointer in ("", "/"):
        return []
    if not pointer.startswith("/"):
        raise ConfigTreeError(UNKNOWN, f"JSON pointer must start with '/': {pointer!r}")
    return [p.replace("~1", "/").replace("~0", "~") for p in pointer[1:].split("/")]


class ConfigTree:
    """Thread-safe tree with change callbacks.

    Attributes:
        generation: Counts the sets applied; a reader may keep values it read while it is unchanged.

    Args:
        tree: Initial content.
        on_change: Called (outside the lock) with the set of changed pointers after a set.
        rules: The schema-like table.
    """

    def __init__(self, tree: dict[str, Any], on_change: Callable[[set[str]], None] | None = None,
                 rules: Sequence[Rule] = RULES) -> None:
        self._tree = tree
        self._lock = threading.Lock()
        self._on_change = on_change
        self.rules = tuple(rules)
        self.generation = 0

    def resolve(self, pointer: str) -> Any:
        """Value at a pointer (a deep copy)."""
        with self._lock:
            node: Any = self._tree
            for key in _split(pointer):
                if not isinstance(node, dict) or key not in node:
                    raise ConfigTreeError(UNKNOWN, f"JSON pointer not found: {pointer}")
                node = node[key]
            return copy.deepcopy(node)

    def get(self, pointers: Sequence[str]) -> str:
        """JSON text of the sub-tree holding ``pointers`` (all of it when empty)."""
        if not pointers:
            with self._lock:
                return json.dumps(self._tree)
        out: dict[str, Any] = {}
        for ptr in pointers:
            if not isinstance(ptr, str):
                raise ConfigTreeError(UNKNOWN, f"JSON pointer must be a string, got {ptr!r}")
            keys = _split(ptr)
            value = self.resolve(ptr)
            if not keys:
                return json.dumps(value)
            node = out
            for k in keys[:-1]:
                node = node.setdefault(k, {})
            node[keys[-1]] = value
        return json.dumps(out)

    def schema(self) -> str:
        """JSON text of :func:`schema_of` the current tree."""
        with self._lock:
            return json.dumps(schema_of(self._tree, "", self.rules))

    def set(self, text: str) -> set[str]:
        """Merge a partial JSON tree after validating all of it; returns the changed pointers."""
        try:
            patch = json.loads(text)
        except (TypeError, ValueError) as exc:
            raise ConfigTreeError(MALFORMED, f"malformed JSON: {exc}") from None
        if not isinstance(patch, dict):
            raise ConfigTreeError(MALFORMED, "set expects a JSON object")
        changed: set[str] = set()
        with self._lock:
            staged = copy.deepcopy(self._tree)
            self._merge(staged, patch, "", changed)
            self._check_conf_only(staged, changed)
            self._tree = staged
            self.generation += 1
        if self._on_change and changed:
            self._on_change(changed)
        return changed

    def _check_conf_only(self, staged: dict[str, Any], changed: AbstractSet[str]) -> None:
        """A CONF-only value may change only on a port that is in CONF before and after the set."""
        for ptr in changed:
            rule = rule_for(ptr, self.rules)
            if rule is None or not rule.conf_only:
                continue
            port = ptr.split("/")[2]
            before = self._tree["ports"][port]["state"]
            if before != "CONF" or staged["ports"][port]["state"] != "CONF":
                raise ConfigTreeError(CONF_ONLY, f"{ptr} can be set only while /ports/{port}/state is CONF "
                                                 f"(it is {before})")

    def _merge(self, node: dict[str, Any], patch: dict[str, Any], path: str, changed: MutableSet[str]) -> None:
        for key, value in patch.items():
            here = f"{path}/{key}"
            if key not in node:
                raise ConfigTreeError(UNKNOWN, f"unknown key: {here}")
            old = node[key]
            if isinstance(old, dict):
                if not isinstance(value, dict):
                    raise ConfigTreeError(INVALID, f"{here} must be an object")
                self._merge(old, value, here, changed)
                continue
            node[key] = self._checked(here, old, value)
            if node[key] != old:
                changed.add(here)

    def _checked(self, here: str, old: Any, value: Any) -> Any:
        """``value`` for ``here`` after the type, enum, range and read-only checks."""
        if here.startswith("/ports/") and here.endswith("/state") and value not in STATES:
            raise ConfigTreeError(INVALID, f"{here} must be one of {', '.join(STATES)}, got {value!r}")
        if isinstance(old, bool) or isinstance(value, bool):
            ok = isinstance(old, bool) and isinstance(value, bool)
        elif isinstance(old, (int, float)):
            ok = isinstance(value, (int, float))
            value = float(value) if isinstance(old, float) else value
        else:
            ok = type(value) is type(old)
        if not ok:
            raise ConfigTreeError(INVALID, f"{here} must be {type(old).__name__}, got {value!r}")
        rule = rule_for(here, self.rules)
        if rule is not None and rule.read_only and value != old:
            raise ConfigTreeError(READ_ONLY, f"{here} is read-only")
        if rule is not None and rule.minimum is not None and not rule.minimum <= value <= (rule.maximum or 0):
            raise ConfigTreeError(INVALID, f"{here} must be in {rule.minimum:g}..{rule.maximum:g}, got {value!r}")
        if here.startswith("/ports/") and here.endswith("/mode") and isinstance(value, str) \
                and old in MODES_3D and value not in MODES_3D:
            raise ConfigTreeError(INVALID, f"{here} must be one of {', '.join(MODES_3D)}, got {value!r}")
        return value
