"""The emulated O3R's JSON configuration tree and its ``get`` / ``set`` semantics.

``get(pointers)`` returns the sub-tree holding just the requested JSON pointers
(``get([])`` the whole tree); ``set(json)`` merges a partial tree after checking
that every key exists, that leaf types match, that ``state`` is RUN/IDLE/CONF and
that the extrinsics are numbers.
"""

from __future__ import annotations

import copy
import json
import threading
from collections.abc import Callable, MutableSet, Sequence
from typing import Any

FIRMWARE = "1.4.30"
STATES = ("RUN", "IDLE", "CONF")


class ConfigTreeError(Exception):
    """A rejected get/set; ``code`` is the XML-RPC fault code the XML-RPC layer answers with.

    The codes are the emulator's own: 101000 unknown pointer / key, 101001 invalid
    value, 101002 malformed JSON.
    """

    def __init__(self, code: int, message: str) -> None:
        super().__init__(message)
        self.code = code


def default_tree(*, port: str, pcic_port: int, width: int, height: int, state: str, frame_rate_hz: float
                 ) -> dict[str, Any]:
    """A realistic O3R tree: one 3D head on ``port``, a 2D head on ``port0``."""
    zero = {"transX": 0.0, "transY": 0.0, "transZ": 0.0, "rotX": 0.0, "rotY": 0.0, "rotZ": 0.0}
    return {
        "applications": {"instances": {}},
        "device": {
            "clock": {"currentTime": 0},
            "diagnostic": {"data": {"pcicPort": 50009}, "temperatures": []},
            "info": {"name": "cellcal-emulator", "description": "emulated O3R VPU", "partNumber": "M04239",
                     "productCode": "OVP800", "serialNumber": "000000000000", "vendor": "ifm electronic gmbh",
                     "features": {}},
            "network": {"interfaces": {"eth0": {"ipv4": {"address": "127.0.0.1", "mask": 8}}}},
            "state": {"errorMessage": "", "errorCode": 0},
            "swVersion": {"firmware": FIRMWARE, "kernel": "emulated", "l4t": "emulated"},
        },
        "ports": {
            "port0": {
                "acquisition": {"framerate": 10.0},
                "data": {"pcicTCPPort": 50010},
                "info": {"features": {"type": "2D", "resolution": {"width": 1280, "height": 800}},
                         "name": "O3R222 2D", "serialNumber": "000000000001"},
                "mode": "standard_autoexposure2D",
                "processing": {"extrinsicHeadToUser": dict(zero)},
                "state": "RUN",
            },
            port: {
                "acquisition": {"framerate": float(frame_rate_hz)},
                "data": {"pcicTCPPort": int(pcic_port)},
                "info": {"features": {"type": "3D", "resolution": {"width": width, "height": height},
                                      "fov": {"horizontal": 60, "vertical": 45}},
                         "name": "O3R222 3D", "serialNumber": "000000000002"},
                "mode": "standard_range4m",
                "processing": {"extrinsicHeadToUser": dict(zero)},
                "state": state,
            },
        },
    }


def _split(pointer: str) -> list[str]:
    if pointer in ("", "/"):
        return []
    if not pointer.startswith("/"):
        raise ConfigTreeError(101000, f"JSON pointer must start with '/': {pointer!r}")
    return [p.replace("~1", "/").replace("~0", "~") for p in pointer[1:].split("/")]


class ConfigTree:
    """Thread-safe tree with change callbacks.

    Args:
        tree: Initial content.
        on_change: Called (outside the lock) with the set of changed pointers after a set.
    """

    def __init__(self, tree: dict[str, Any], on_change: Callable[[set[str]], None] | None = None) -> None:
        self._tree = tree
        self._lock = threading.Lock()
        self._on_change = on_change

    def resolve(self, pointer: str) -> Any:
        """Value at a pointer (a deep copy)."""
        with self._lock:
            node: Any = self._tree
            for key in _split(pointer):
                if not isinstance(node, dict) or key not in node:
                    raise ConfigTreeError(101000, f"JSON pointer not found: {pointer}")
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
                raise ConfigTreeError(101000, f"JSON pointer must be a string, got {ptr!r}")
            keys = _split(ptr)
            value = self.resolve(ptr)
            if not keys:
                return json.dumps(value)
            node = out
            for k in keys[:-1]:
                node = node.setdefault(k, {})
            node[keys[-1]] = value
        return json.dumps(out)

    def set(self, text: str) -> None:
        """Merge a partial JSON tree after validating all of it."""
        try:
            patch = json.loads(text)
        except (TypeError, ValueError) as exc:
            raise ConfigTreeError(101002, f"malformed JSON: {exc}") from None
        if not isinstance(patch, dict):
            raise ConfigTreeError(101002, "set expects a JSON object")
        changed: set[str] = set()
        with self._lock:
            staged = copy.deepcopy(self._tree)
            self._merge(staged, patch, "", changed)
            self._tree = staged
        if self._on_change and changed:
            self._on_change(changed)

    def _merge(self, node: dict[str, Any], patch: dict[str, Any], path: str, changed: MutableSet[str]) -> None:
        for key, value in patch.items():
            here = f"{path}/{key}"
            if key not in node:
                raise ConfigTreeError(101000, f"unknown key: {here}")
            old = node[key]
            if isinstance(old, dict):
                if not isinstance(value, dict):
                    raise ConfigTreeError(101001, f"{here} must be an object")
                self._merge(old, value, here, changed)
                continue
            if key == "state" and value not in STATES:
                raise ConfigTreeError(101001, f"{here} must be one of {', '.join(STATES)}, got {value!r}")
            if isinstance(old, bool) or isinstance(value, bool):
                ok = isinstance(old, bool) and isinstance(value, bool)
            elif isinstance(old, (int, float)):
                ok = isinstance(value, (int, float))
                value = float(value) if isinstance(old, float) else value
            else:
                ok = type(value) is type(old)
            if not ok:
                raise ConfigTreeError(101001, f"{here} must be {type(old).__name__}, got {value!r}")
            if "/info/" in here or "/data/" in here or here.startswith("/device/swVersion"):
                raise ConfigTreeError(101001, f"{here} is read-only")
            node[key] = value
            changed.add(here)
