"""Typed validation of configuration sections (TOML tables) into frozen dataclasses.

:func:`parse_section` checks a mapping against a backend's config dataclass and reports
the first problem as a one-line :class:`~cellcal.devices.errors.ConfigError` naming the
file, the dotted key and what was expected (ADR 0004).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import types
import typing
from collections.abc import Mapping
from typing import Any, Literal, TypeVar, get_args, get_origin, get_type_hints

from .errors import ConfigError

T = TypeVar("T")

_TYPE_NAMES = {bool: "a boolean", int: "an integer", float: "a number", str: "a string"}


_cached_type_hints = functools.lru_cache(maxsize=256)(get_type_hints)


def _hints(cls: Any) -> dict[str, Any]:
    """``get_type_hints`` of a config dataclass (cached: it re-evaluates every annotation)."""
    return _cached_type_hints(cls)


def _join(where: str, key: str) -> str:
    return f"{where}.{key}" if where else key


def _plural(tp: Any) -> str:
    """``float`` -> "numbers"; ``Literal["a", "b"]`` -> "items, each one of 'a', 'b'"."""
    text = _describe(tp)
    for article in ("a ", "an "):
        if text.startswith(article) and " or " not in text:
            return text.removeprefix(article) + "s"
    return f"items, each {text}"


def _describe(tp: Any) -> str:
    origin = get_origin(tp)
    if tp in _TYPE_NAMES:
        return _TYPE_NAMES[tp]
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in get_args(tp))
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_describe(a) for a in get_args(tp) if a is not type(None))
    if origin is tuple:
        args = get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return f"a list of {_plural(args[0])}"
        return f"a list of {len(args)} {_plural(args[0])}"
    if origin is list:
        return f"a list of {_plural(get_args(tp)[0])}"
    if origin is dict or tp is dict:
        return "a table"
    if dataclasses.is_dataclass(tp):
        return "a table"
    return getattr(tp, "__name__", str(tp))


def _fail(value: Any, tp: Any, key: str, source: str | None) -> ConfigError:
    """The error for ``value`` not being of type ``tp``: what was expected and what came."""
    return ConfigError(f"expected {_describe(tp)}, got {type(value).__name__} {value!r}", source=source, key=key)


def _convert(value: Any, tp: Any, key: str, source: str | None) -> Any:
    """Check ``value`` against type ``tp`` and return it converted (e.g. int -> float).

    Raises:
        ConfigError: Naming ``key`` (``[i]`` appended for list items) and what was expected.
    """
    origin = get_origin(tp)
    if tp is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        return _convert_union(value, tp, key, source)
    if tp in _TYPE_NAMES:
        return _convert_scalar(value, tp, key, source)
    if origin is Literal:
        if value not in get_args(tp) or isinstance(value, bool):
            raise _fail(value, tp, key, source)
        return value
    if origin is tuple or origin is list:
        return _convert_sequence(value, tp, key, source)
    if origin is dict or tp is dict:
        if not isinstance(value, Mapping):
            raise _fail(value, tp, key, source)
        return dict(value)
    if isinstance(tp, type) and dataclasses.is_dataclass(tp):
        if not isinstance(value, Mapping):
            raise _fail(value, tp, key, source)
        return parse_section(tp, value, where=key, source=source)
    raise ConfigError(f"unsupported schema type {tp!r}", source=source, key=key)  # pragma: no cover


def _convert_union(value: Any, tp: Any, key: str, source: str | None) -> Any:
    """``X | None`` (None, or X with X's own message) or ``X | Y``: the first alternative that accepts it."""
    args = get_args(tp)
    if value is None and type(None) in args:
        return None
    alternatives = [a for a in args if a is not type(None)]
    if len(alternatives) == 1:  # X | None: X's own message names the inner key
        return _convert(value, alternatives[0], key, source)
    for arg in alternatives:
        try:
            return _convert(value, arg, key, source)
        except ConfigError:
            continue
    raise _fail(value, tp, key, source)


def _convert_scalar(value: Any, tp: type, key: str, source: str | None) -> Any:
    """``bool``, ``int``, ``float`` (ints accepted, must be finite) or ``str``; a bool is never a number."""
    if tp is bool:
        ok = isinstance(value, bool)
    elif tp is str:
        ok = isinstance(value, str)
    elif tp is int:
        ok = isinstance(value, int) and not isinstance(value, bool)
    else:  # float
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
    if not ok:
        raise _fail(value, tp, key, source)
    if tp is float:
        if not math.isfinite(value):
            raise ConfigError(f"expected a finite number, got {value!r}", source=source, key=key)
        return float(value)
    return value


def _convert_sequence(value: Any, tp: Any, key: str, source: str | None) -> Any:
    """``list[X]``, ``tuple[X, ...]`` or a fixed ``tuple[X, Y, ...]`` from a TOML array, item by item."""
    origin = get_origin(tp)
    if not isinstance(value, (list, tuple)):
        raise _fail(value, tp, key, source)
    args = get_args(tp)
    if origin is tuple and not (len(args) == 2 and args[1] is Ellipsis):  # fixed length, one type per item
        if len(value) != len(args):
            raise ConfigError(f"expected {_describe(tp)}, got {len(value)} items", source=source, key=key)
        items = [_convert(v, a, f"{key}[{i}]", source) for i, (v, a) in enumerate(zip(value, args, strict=True))]
    else:
        items = [_convert(v, args[0], f"{key}[{i}]", source) for i, v in enumerate(value)]
    return tuple(items) if origin is tuple else items


def _check_range(value: Any, meta: Mapping[str, Any], key: str, source: str | None) -> None:
    if value is None:
        return
    values = value if isinstance(value, (list, tuple)) else [value]
    for v in values:
        if not isinstance(v, (int, float)) or isinstance(v, bool):
            continue
        if "gt" in meta and not v > meta["gt"]:
            raise ConfigError(f"must be > {meta['gt']}, got {value!r}", source=source, key=key)
        if "ge" in meta and not v >= meta["ge"]:
            raise ConfigError(f"must be >= {meta['ge']}, got {value!r}", source=source, key=key)
        if "lt" in meta and not v < meta["lt"]:
            raise ConfigError(f"must be < {meta['lt']}, got {value!r}", source=source, key=key)
        if "le" in meta and not v <= meta["le"]:
            raise ConfigError(f"must be <= {meta['le']}, got {value!r}", source=source, key=key)
    if "min_items" in meta and isinstance(value, (list, tuple)) and len(value) < meta["min_items"]:
        raise ConfigError(f"needs at least {meta['min_items']} items, got {len(value)}", source=source, key=key)


def parse_section(cls: type[T], section: Mapping[str, Any] | None, *, where: str = "",
                  source: str | None = None, ignore: tuple[str, ...] = ()) -> T:
    """Validate a mapping against a config dataclass and build an instance.

    Supported field types: ``bool``, ``int``, ``float``, ``str``, ``Literal[...]``,
    ``tuple[float, ...]`` / ``tuple[float, float, float]`` (and int/str tuples),
    ``list[...]`` of those, ``dict[str, Any]``, nested config dataclasses, and ``X | None``.
    Range limits come from field metadata (``gt``, ``ge``, ``lt``, ``le``, ``min_items``).

    Args:
        cls: The config dataclass.
        section: The mapping (e.g. a parsed TOML table); None means empty.
        where: Dotted path of the section inside the document, for messages.
        source: File name (or other origin) for messages.
        ignore: Keys that belong to the caller (e.g. ``"backend"``) and are skipped.

    Returns:
        The validated config object.

    Raises:
        ConfigError: Naming the source, the key and what was expected.
    """
    if not dataclasses.is_dataclass(cls):
        raise TypeError(f"{cls!r} is not a dataclass")  # programming error, not user input
    if section is None:
        section = {}
    if not isinstance(section, Mapping):
        raise ConfigError(f"expected a table, got {type(section).__name__}", source=source, key=where or None)
    hints = _hints(cls)
    known = {f.name: f for f in dataclasses.fields(cls) if f.init}
    for key in section:
        if key not in known and key not in ignore:
            choices = ", ".join(sorted(known)) or "(none)"
            raise ConfigError(f"unknown key; expected one of: {choices}", source=source, key=_join(where, key))
    kwargs: dict[str, Any] = {}
    for name, f in known.items():
        full = _join(where, name)
        if name not in section:
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise ConfigError(f"missing required value ({_describe(hints[name])})", source=source, key=full)
            continue
        value = _convert(section[name], hints[name], full, source)
        _check_range(value, f.metadata, full, source)
        kwargs[name] = value
    try:
        return cls(**kwargs)
    except ConfigError as exc:  # a check across keys (__post_init__): add what it could not know
        if exc.source and exc.key:
            raise
        inner = exc.key
        if inner and where and not (inner == where or inner.startswith(f"{where}.")):
            inner = _join(where, inner)
        raise ConfigError(exc.reason, source=exc.source or source, key=inner or where or None) from None
    except (ValueError, TypeError) as exc:
        raise ConfigError(str(exc), source=source, key=where or None) from None


def schema_of(cls: type[Any]) -> dict[str, tuple[Any, Any, Mapping[str, Any]]]:
    """Introspect a config dataclass: ``{key: (type, default, metadata)}``.

    The default is ``dataclasses.MISSING`` for required keys.
    """
    hints = _hints(cls)
    out: dict[str, tuple[Any, Any, Mapping[str, Any]]] = {}
    for f in dataclasses.fields(cls):
        if not f.init:
            continue
        if f.default is not dataclasses.MISSING:
            default = f.default
        elif f.default_factory is not dataclasses.MISSING:
            default = f.default_factory()
        else:
            default = dataclasses.MISSING
        out[f.name] = (hints[f.name], default, f.metadata)
    return out
