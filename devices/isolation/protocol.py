"""The messages between a :class:`~cellcal.devices.isolation.NativeHost` and its worker process.

A request is ``(seq, op, handle, name, args, kwargs)``; a reply is ``(seq, kind, payload)``
with ``kind`` one of :data:`VALUE`, :data:`REF` (an object that stays in the worker:
``(handle, type name)``) or :data:`ERROR` (``(exception type name, message)``). Both sides
pickle; the parent reads at most :data:`MAX_MESSAGE_BYTES` per reply.
"""

from __future__ import annotations

from typing import Any

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


def rebuild_error(type_name: str, message: str) -> Exception:
    """The parent's exception for a worker's ``(type name, message)``: the same builtin type where known."""
    known = KNOWN_ERRORS.get(type_name)
    if known is None:
        return RuntimeError(f"{type_name}: {message}")
    return known(message)
