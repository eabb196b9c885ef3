"""Numbers in messages a person reads: SI values shown in millimetres and degrees, and pairs that differ in print.

The library keeps metres and radians (ADR 0001); a message converts them here, at the last
moment. A value compared with a threshold is printed with as many significant digits as it
takes for the two to read differently: a value just past its threshold never prints equal to it.
"""

from __future__ import annotations

import math

__all__ = ["DISPLAY_UNITS", "distinct", "quantity", "quantity_pair"]

#: SI unit -> (the unit a person reads, factor from SI). ``""``: a plain number (a fraction, a ratio, a count).
DISPLAY_UNITS: dict[str, tuple[str, float]] = {
    "": ("", 1.0),
    "m": ("mm", 1000.0),
    "rad": ("deg", 180.0 / math.pi),
}

#: Significant digits that always tell two different floats apart.
_MAX_DIGITS = 17


def distinct(a: float, b: float, digits: int = 3) -> tuple[str, str]:
    """``a`` and ``b`` with ``digits`` significant digits, or with as many more as it takes to make them differ.

    Two equal numbers (or a NaN, an infinity) print with ``digits``; two different finite
    numbers never print the same.

    Args:
        a: First number.
        b: Second number.
        digits: Fewest significant digits (>= 1).
    """
    sa, sb = f"{a:.{digits}g}", f"{b:.{digits}g}"
    if a == b or not (math.isfinite(a) and math.isfinite(b)):
        return sa, sb
    for p in range(digits, _MAX_DIGITS + 1):
        sa, sb = f"{a:.{p}g}", f"{b:.{p}g}"
        if sa != sb:
            break
    return sa, sb


def _with_unit(text: str, unit: str) -> str:
    return f"{text} {unit}" if unit else text


def quantity(value_si: float, unit: str, digits: int = 3) -> str:
    """One SI value as a person reads it: ``0.0015`` m -> ``"1.5 mm"``, ``0.2618`` rad -> ``"15 deg"``.

    Args:
        value_si: The value in its SI unit.
        unit: ``"m"``, ``"rad"`` or ``""`` (a plain number), see :data:`DISPLAY_UNITS`.
        digits: Significant digits.
    """
    shown, factor = DISPLAY_UNITS[unit]
    return _with_unit(f"{value_si * factor:.{digits}g}", shown)


def quantity_pair(value_si: float, threshold_si: float, unit: str, digits: int = 3) -> tuple[str, str]:
    """A value and its threshold as a person reads them, differing in print whenever they differ.

    Converted to millimetres or degrees (see :func:`quantity`) and printed by :func:`distinct`.
    Should the conversion round two different SI values onto one float, both are printed
    in their SI unit instead, so the difference still shows.

    Args:
        value_si: The measured value, SI unit.
        threshold_si: The threshold it is compared with, SI unit.
        unit: ``"m"``, ``"rad"`` or ``""``.
        digits: Fewest significant digits.
    """
    shown, factor = DISPLAY_UNITS[unit]
    a, b = value_si * factor, threshold_si * factor
    if a == b and value_si != threshold_si:
        a, b, shown = value_si, threshold_si, unit
    sa, sb = distinct(a, b, digits)
    return _with_unit(sa, shown), _with_unit(sb, shown)
