"""Typed validation of configuration sections (TOML tables) into frozen dataclasses.

:func:`parse_section` checks a mapping against a backend's config dataclass and reports
the first problem as a one-line :class:`~cellcal.devices.errors.ConfigError` naming the
file, the dotted key and what was expected (ADR 0004). Besides each field's own range
(metadata ``gt``, ``ge``, ``lt``, ``le``, ``min_items``, ``max_items``, ``max_len``), every
value has the limits of :data:`DEFAULT_LIMITS`: integers in TOML's 64-bit range, strings
without control characters, bounded lengths.
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import math
import operator
import reprlib
import types
import typing
from collections.abc import Mapping
from typing import Any, Literal, TypeVar, get_args, get_origin, get_type_hints

from .errors import ConfigError

T = TypeVar("T")

_TYPE_NAMES = {bool: "a boolean", int: "an integer", float: "a number", str: "a string"}

#: Limits of every value unless its field's metadata sets its own (a path fits in 4096
#: characters; no table of a cell needs 10,000 items).
DEFAULT_LIMITS: Mapping[str, int] = {"max_len": 4096, "max_items": 10_000}
#: TOML's integer range (tomllib itself accepts any size).
INT_MIN, INT_MAX = -(2**63), 2**63 - 1

_short = reprlib.Repr()
_short.maxstring = _short.maxother = 60
_short.maxlong = 24
_short.maxlist = _short.maxtuple = _short.maxdict = 6
_short.maxlevel = 3


def show(value: Any) -> str:
    """A short ``repr`` of a value for a message: long strings, numbers, lists and deep nesting elided."""
    return _short.repr(value)


def _control_chars(text: str) -> bool:
    """Whether ``text`` holds a C0/C1 control character or DEL (which a config string never needs)."""
    return any(ord(ch) < 0x20 or 0x7F <= ord(ch) < 0xA0 for ch in text)


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
    return ConfigError(f"expected {_describe(tp)}, got {type(value).__name__} {show(value)}", source=source, key=key)


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
    if tp is int and not INT_MIN <= value <= INT_MAX:
        raise ConfigError(f"expected an integer in TOML's 64-bit range, got {show(value)}", source=source, key=key)
    if tp is str and _control_chars(value):
        raise ConfigError(f"expected a string without control characters, got {show(value)}", source=source, key=key)
    return value


def _convert_sequence(value: Any, tp: Any, key: str, source: str | None) -> Any:
    """``list[X]``, ``tuple[X, ...]`` or a fixed ``tuple[X, Y, ...]`` from a TOML array, item by item."""
    origin = get_origin(tp)
    if not isinstance(value, (list, tuple)):
        raise _fail(value, tp, key, source)
    if len(value) > DEFAULT_LIMITS["max_items"]:  # before converting every item of a huge list
        raise ConfigError(f"needs at most {DEFAULT_LIMITS['max_items']} items, got {len(value)}",
                          source=source, key=key)
    args = get_args(tp)
    if origin is tuple and not (len(args) == 2 and args[1] is Ellipsis):  # fixed length, one type per item
        if len(value) != len(args):
            raise ConfigError(f"expected {_describe(tp)}, got {len(value)} items", source=source, key=key)
        items = [_convert(v, a, f"{key}[{i}]", source) for i, (v, a) in enumerate(zip(value, args, strict=True))]
    else:
        items = [_convert(v, args[0], f"{key}[{i}]", source) for i, v in enumerate(value)]
    return tuple(items) if origin is tuple else items


def _check_range(value: Any, meta: Mapping[str, Any], key: str, source: str | None) -> None:
    """The field's limits (its metadata over :data:`DEFAULT_LIMITS`) on a converted value."""
    if value is None:
        return
    meta = {**DEFAULT_LIMITS, **meta}
    values = value if isinstance(value, (list, tuple)) else [value]
    for v in values:
        if isinstance(v, str) and len(v) > meta["max_len"]:
            raise ConfigError(f"must be at most {meta['max_len']} characters, got {len(v)}", source=source, key=key)
        if not isinstance(v, (int, float)) or isinstance(v, bool):
            continue
        for op, (symbol, holds) in _LIMITS.items():
            if op in meta and not holds(v, meta[op]):
                raise ConfigError(f"must be {symbol} {meta[op]}, got {show(value)}", source=source, key=key)
    if isinstance(value, (list, tuple)):
        if "min_items" in meta and len(value) < meta["min_items"]:
            raise ConfigError(f"needs at least {meta['min_items']} items, got {len(value)}", source=source, key=key)
        if len(value) > meta["max_items"]:
            raise ConfigError(f"needs at most {meta['max_items']} items, got {len(value)}", source=source, key=key)


#: Range limits of the field metadata: (symbol in messages, the test a value must pass).
_LIMITS = {"gt": (">", operator.gt), "ge": (">=", operator.ge), "lt": ("<", operator.lt), "le": ("<=", operator.le)}


def check_value(value: Any, tp: Any, metadata: Mapping[str, Any], key: str, source: str | None = None) -> Any:
    """One value against its type and its field's limits, as in a config file; the converted value.

    For a dataclass checking its own fields at construction (``__post_init__``), so that a
    direct construction and a config file are held to the same schema.

    Args:
        value: The value.
        tp: Its resolved type (``typing.get_type_hints``), e.g. ``float`` or ``tuple[int, int]``.
        metadata: The field's metadata (``gt``, ``ge``, ``lt``, ``le``, ...).
        key: Dotted key for messages.
        source: File name (or other origin) for messages.

    Raises:
        ConfigError: Naming ``key`` and what was expected.
    """
    converted = _convert(value, tp, key, source)
    _check_range(converted, metadata, key, source)
    return converted


def _unknown_key(key: object, known: list[str]) -> str:
    """``unknown key; did you mean 'x'? (expected one of: ...)``, or without the guess when none is near."""
    choices = ", ".join(known) or "(none)"
    near = difflib.get_close_matches(key.lower(), known, n=1) if isinstance(key, str) and len(key) <= 60 else []
    if near:
        return f"unknown key; did you mean {near[0]!r}? (expected one of: {choices})"
    return f"unknown key; expected one of: {choices}"


def parse_section(cls: type[T], section: Mapping[str, Any] | None, *, where: str = "",
                  source: str | None = None, ignore: tuple[str, ...] = ()) -> T:
    """Validate a mapping against a config dataclass and build an instance.

    Supported field types: ``bool``, ``int``, ``float``, ``str``, ``Literal[...]``,
    ``tuple[float, ...]`` / ``tuple[float, float, float]`` (and int/str tuples),
    ``list[...]`` of those, ``dict[str, Any]``, nested config dataclasses, and ``X | None``.
    Range limits come from field metadata (``gt``, ``ge``, ``lt``, ``le``, ``min_items``,
    ``max_items``, ``max_len``), over :data:`DEFAULT_LIMITS`; integers must fit TOML's
    64-bit range and strings hold no control characters.

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
            name = key if isinstance(key, str) and key.isprintable() and len(key) <= 60 else show(key)
            raise ConfigError(_unknown_key(key, sorted(known)), source=source, key=_join(where, name))
    kwargs: dict[str, Any] = {}
    for name, f in known.items():
        full = _join(where, name)
        if name not in section:
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise ConfigError(f"missing required value ({_describe(hints[name])})", source=source, key=full)
            continue
        kwargs[name] = check_value(section[name], hints[name], f.metadata, full, source)
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
