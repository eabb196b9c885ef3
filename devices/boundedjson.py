"""JSON from files and peers, parsed with a bound on its nesting depth (ADR 0039)."""

from __future__ import annotations

import json
import re
from typing import Any

__all__ = ["MAX_DEPTH", "JSONTooDeepError", "json_depth", "loads"]

#: Deepest nesting of arrays / objects accepted; cellcal's own documents stay below 12.
MAX_DEPTH = 64
#: A JSON string (its escapes included): brackets inside strings do not nest.
_STRING = re.compile(rb'"(?:[^"\\]|\\.)*"', re.DOTALL)


class JSONTooDeepError(ValueError):
    """A JSON text nested deeper than the bound (a ``ValueError``, as ``json.JSONDecodeError`` is)."""


def json_depth(text: str | bytes) -> int:
    """The deepest nesting of ``[`` / ``{`` in ``text``, strings skipped (0 for a scalar)."""
    import numpy as np  # here: the CLI's parser imports this module and must stay free of numerics

    raw = text.encode("utf-8", "surrogatepass") if isinstance(text, str) else text
    bare = np.frombuffer(_STRING.sub(b'""', raw), dtype=np.uint8)  # strings emptied: their brackets do not count
    # +1 at every opening bracket, -1 at every closing one; the running sum is the depth
    steps = (np.isin(bare, (ord("["), ord("{"))).astype(np.int32)
             - np.isin(bare, (ord("]"), ord("}"))).astype(np.int32))
    return int(np.cumsum(steps).max(initial=0))


def loads(text: str | bytes, *, max_depth: int = MAX_DEPTH, **kwargs: Any) -> Any:
    """``json.loads`` of ``text`` after checking its nesting depth.

    Raises:
        JSONTooDeepError: If ``text`` nests deeper than ``max_depth`` (before any parsing: no
            ``RecursionError`` from the parser).
        json.JSONDecodeError: If it is not JSON.
    """
    depth = json_depth(text)
    if depth > max_depth:
        raise JSONTooDeepError(f"nested {depth} levels deep, more than the {max_depth} accepted")
    return json.loads(text, **kwargs)
