"""Strict autospec for pybind11 vendor classes (ur_rtde, depthai).

``unittest.mock.create_autospec`` checks attribute *names* on pybind11 classes but
not call arguments: pybind11 methods expose no ``inspect.signature``. Their
docstrings do carry the real signatures (``moveL(self: ..., pose: list[float],
speed: float = 0.25, ...) -> bool``), so :func:`strict_autospec` parses them and
builds the mock from a stub whose methods have those signatures: a call the real
library does not have, or one whose arguments bind to none of its overloads
(too many, a wrong keyword, a missing required one), raises ``TypeError``.
An overloaded method gets a ``side_effect`` that binds the call against every
overload; configure such methods through ``return_value`` (a test that replaces
their ``side_effect`` drops that check).
"""

from __future__ import annotations

import inspect
import re
from typing import Any
from unittest import mock

_HEADER = re.compile(r"^(?:\d+\.\s+)?(?P<name>\w+)\((?P<params>.*)\)\s*->")


def _split_params(text: str) -> list[str]:
    out, depth, cur = [], 0, ""
    for ch in text:
        if ch in "[(<{":
            depth += 1
        elif ch in "])>}":
            depth -= 1
        if ch == "," and depth == 0:
            out.append(cur.strip())
            cur = ""
        else:
            cur += ch
    if cur.strip():
        out.append(cur.strip())
    return out


def pybind_signatures(func: Any) -> list[inspect.Signature]:
    """All overload signatures of a pybind11 function, parsed from its docstring."""
    name = getattr(func, "__name__", "")
    sigs = []
    for line in (getattr(func, "__doc__", None) or "").splitlines():
        m = _HEADER.match(line.strip())
        if not m or m.group("name") != name:
            continue
        params = []
        for raw in _split_params(m.group("params")):
            if raw.startswith("**"):
                params.append(inspect.Parameter(raw[2:].split(":")[0], inspect.Parameter.VAR_KEYWORD))
                continue
            if raw.startswith("*"):
                params.append(inspect.Parameter(raw[1:].split(":")[0], inspect.Parameter.VAR_POSITIONAL))
                continue
            pname = raw.split(":")[0].split("=")[0].strip()
            default = None if "=" in raw else inspect.Parameter.empty
            params.append(inspect.Parameter(pname, inspect.Parameter.POSITIONAL_OR_KEYWORD, default=default))
        sigs.append(inspect.Signature(params))
    return sigs


def _stub_method(real: Any, name: str) -> Any:
    sigs = pybind_signatures(real)

    def stub(*args: Any, **kwargs: Any) -> Any:  # pragma: no cover - never called (autospec)
        raise AssertionError

    stub.__name__ = name
    if len(sigs) == 1:
        stub.__signature__ = sigs[0]  # type: ignore[attr-defined]
    stub._overloads = sigs  # type: ignore[attr-defined]
    return stub


def strict_autospec(cls: type, **attrs: Any) -> Any:
    """An instance mock of ``cls`` whose methods enforce the real signatures.

    Args:
        cls: The real vendor class (pybind11).
        attrs: Extra attributes to set on the mock (e.g. node outputs).
    """
    namespace: dict[str, Any] = {}
    for name in dir(cls):
        if name.startswith("_"):
            continue
        real = getattr(cls, name)
        if callable(real) and type(real).__name__ in ("instancemethod", "builtin_function_or_method",
                                                       "method_descriptor", "function"):
            namespace[name] = _stub_method(real, name)
        else:
            namespace[name] = real
    stub_cls = type(cls.__name__, (), namespace)
    m = mock.create_autospec(stub_cls, instance=True)
    for name, stub in namespace.items():
        overloads = getattr(stub, "_overloads", None)
        if overloads and len(overloads) > 1:
            getattr(m, name).side_effect = _overload_guard(name, overloads)
    for k, v in attrs.items():
        setattr(m, k, v)
    return m



def _overload_guard(name: str, sigs: list[inspect.Signature]) -> Any:
    def guard(*args: Any, **kwargs: Any) -> Any:
        for sig in sigs:
            try:
                sig.bind(None, *args, **kwargs)  # None stands for self
            except TypeError:
                continue
            return mock.DEFAULT
        raise TypeError(f"{name}(*{args!r}, **{kwargs!r}) matches no overload of the real method")
    return guard
