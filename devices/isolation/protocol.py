"""The messages between a :class:`~cellcal.devices.isolation.NativeHost` and its worker process.

A request is ``(seq, op, handle, name, args, kwargs)``; a reply is ``(seq, kind, payload)``
with ``kind`` one of :data:`VALUE`, :data:`REF` (an object that stays in the worker:
``(handle, type name)``) or :data:`ERROR` (``(exception type name, message)``, and for one of
cellcal's own errors its ``args`` and plain attributes too, so that it is rebuilt as itself).
Both sides pickle; the parent reads at most :data:`MAX_MESSAGE_BYTES` per reply.
"""

from __future__ import annotations

from typing import Any

from .. import errors as cellcal_errors

#: Operations: import a module, call an attribute of a held object, forget an object, end the worker.
IMPORT, CALL, DROP, CLOSE = "import", "call", "drop", "close"
#: Reply kinds.
VALUE, REF, ERROR = "value", "ref", "error"
#: Largest pickled message either side accepts, bytes.
MAX_MESSAGE_BYTES = 1 << 20
#: Longest exception message carried back, characters.
MAX_ERROR_CHARS = 2000
#: Deepest nesting of lists / tuples returned by value (deeper results stay in the worker).
MAX_PLAIN_DEPTH = 4
#: Exception types re-raised as themselves in the parent; any other becomes a RuntimeError.
KNOWN_ERRORS: dict[str, type[Exception]] = {
    cls.__name__: cls for cls in (RuntimeError, OSError, ValueError, TypeError, ImportError,
                                  ModuleNotFoundError, AttributeError, KeyError, IndexError,
                                  ConnectionError, TimeoutError)
}
_SCALARS = (type(None), bool, int, float, str, bytes)


def is_plain(value: Any, depth: int = 0) -> bool:
    """Whether ``value`` travels by value: scalars, and lists / tuples / dicts of them (bounded depth).

    Exact types only: a subclass (an ``IntEnum``, a vendor's tuple) would be unpickled in the parent
    by importing its module, which may be the native library the worker is there to keep out.
    """
    if type(value) in _SCALARS:
        return True
    if depth >= MAX_PLAIN_DEPTH:
        return False
    if type(value) in (list, tuple):
        return all(is_plain(v, depth + 1) for v in value)
    if type(value) is dict:
        return all(isinstance(k, str) and is_plain(v, depth + 1) for k, v in value.items())
    return False


def error_payload(exc: BaseException) -> tuple[Any, ...]:
    """What the worker sends for ``exc``: ``(type name, message)``, plus ``(args, attributes)`` for cellcal's own.

    cellcal's errors (a backend run whole in the worker raises them: a timeout, a lost link, a
    vendor code) travel with their arguments and plain attributes, so the parent raises the
    same type with the same message; anything else is rebuilt by :func:`rebuild_error`.
    """
    name, message = type(exc).__name__, str(exc)[:MAX_ERROR_CHARS]
    if type(exc).__module__ != cellcal_errors.__name__:
        return name, message
    args = tuple(_bounded(a) for a in exc.args)
    state = {k: _bounded(v) for k, v in vars(exc).items() if type(v) in _SCALARS}  # key, code, offset, ...
    return name, message, args, state


def _bounded(value: Any) -> Any:
    """A scalar as it is (a string cut to :data:`MAX_ERROR_CHARS`); anything else as its string."""
    if type(value) not in _SCALARS:
        value = str(value)
    return value[:MAX_ERROR_CHARS] if isinstance(value, (str, bytes)) else value


def rebuild_error(type_name: str, message: str, args: tuple[Any, ...] | None = None,
                  state: dict[str, Any] | None = None) -> Exception:
    """The parent's exception for a worker's error: the same builtin or cellcal type where known.

    Args:
        type_name: The exception's class name in the worker.
        message: Its message (at most :data:`MAX_ERROR_CHARS`).
        args: For one of cellcal's errors (:func:`error_payload`), its ``args``.
        state: ... and its plain attributes (``key``, ``code``, ``signal_name``).
    """
    if args is not None:
        cls = getattr(cellcal_errors, type_name, None)
        if isinstance(cls, type) and issubclass(cls, cellcal_errors.CellcalError):
            # built without its __init__ (whose signature differs per class), as pickle would rebuild it
            error: Exception = cls.__new__(cls)
            Exception.__init__(error, *args)
            error.__dict__.update(state or {})
            return error
    known = KNOWN_ERRORS.get(type_name)
    if known is None:
        return RuntimeError(f"{type_name}: {message}")
    return known(message)
