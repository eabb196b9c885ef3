"""Strict-JSON copies of documents (:func:`json_safe`): the one cleaner for results, journals and recordings."""

from __future__ import annotations

import datetime as _dt
import math
from collections.abc import Mapping
from typing import Any

import numpy as np

__all__ = ["json_safe"]


def json_safe(value: Any) -> Any:
    """Strict-JSON copy of ``value``: what ``json.dumps(..., allow_nan=False)`` accepts.

    NaN/inf become None (JSON has no such numbers), numpy arrays and scalars Python
    lists and numbers, tuples and sets lists, mapping keys strings, and TOML
    dates/times ISO 8601 strings. Anything else is a programming error (a document
    that holds, say, a :class:`~cellcal.devices.pose.Pose` instead of its ``to_dict()``
    form) and raises rather than being written as its ``str()``, which no reader could
    turn back into the object.

    Args:
        value: A document: mappings, sequences, sets, numbers (Python or numpy),
            numpy arrays, strings, None, and ``datetime``/``date``/``time`` values.

    Returns:
        A copy built of dicts (string keys), lists, finite floats, ints, bools,
        strings and None.

    Raises:
        TypeError: If the document holds any other kind of object (naming its type
            and its place, e.g. ``$.poses[2].camera_pose``).
    """
    return _safe(value, "$")


def _safe(value: Any, where: str) -> Any:
    if isinstance(value, Mapping):
        return {str(k): _safe(v, f"{where}.{k}") for k, v in value.items()}
    if isinstance(value, (list, tuple, set, frozenset)):
        return [_safe(v, f"{where}[{i}]") for i, v in enumerate(value)]
    if isinstance(value, (np.ndarray, np.generic)):
        return _safe(value.tolist(), where)
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if value is None or isinstance(value, (str, int)):
        return value
    if isinstance(value, (_dt.date, _dt.time)):  # TOML's date, time and date-time values
        return value.isoformat()
    raise TypeError(f"{type(value).__module__}.{type(value).__qualname__} at {where} is not JSON data "
                    "(convert it to a dict, list, number or string first)")
