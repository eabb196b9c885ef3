"""argparse ``type=`` checkers: a bad number or path is a one-line usage error (exit 2).

Example: ``p.add_argument("--timeout", type=real(gt=0), default=2.0)``.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from typing import TypeVar

__all__ = ["integer", "path_arg", "real"]

T = TypeVar("T", int, float)


def _limits(gt: float | None, ge: float | None, lt: float | None, le: float | None) -> str:
    parts = [f"{sym} {v:g}" for sym, v in ((">", gt), (">=", ge), ("<", lt), ("<=", le)) if v is not None]
    return (" " + " and ".join(parts)) if parts else ""


def _inside(v: float, gt: float | None, ge: float | None, lt: float | None, le: float | None) -> bool:
    return ((gt is None or v > gt) and (ge is None or v >= ge) and (lt is None or v < lt)
            and (le is None or v <= le))


def _checker(parse: Callable[[str], T], what: str, gt: float | None, ge: float | None, lt: float | None,
             le: float | None) -> Callable[[str], T]:
    expected = f"expected {what}{_limits(gt, ge, lt, le)}"

    def check(text: str) -> T:
        try:
            value = parse(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{expected}, got {text!r}") from None
        if not (math.isfinite(value) and _inside(value, gt, ge, lt, le)):  # type: ignore[arg-type]
            raise argparse.ArgumentTypeError(f"{expected}, got {text!r}")
        return value

    return check


def real(*, gt: float | None = None, ge: float | None = None, lt: float | None = None,
         le: float | None = None) -> Callable[[str], float]:
    """A checker for a finite float within the given limits (unit as the option says)."""
    return _checker(float, "a finite number", gt, ge, lt, le)


def path_arg(text: str) -> str:
    """A file or directory path: not empty (an empty path would silently mean the current directory)."""
    if not text:
        raise argparse.ArgumentTypeError("expected a path, got an empty string")
    return text


def integer(*, gt: int | None = None, ge: int | None = None, lt: int | None = None,
            le: int | None = None) -> Callable[[str], int]:
    """A checker for an integer within the given limits."""
    return _checker(int, "an integer", gt, ge, lt, le)
