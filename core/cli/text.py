"""What the ``cellcal`` command prints that came from outside: one line, escaped, of bounded length.

Paths, keys and values in error messages come from the command line and from files;
a control character in them must not reach the terminal (it could move the cursor,
recolour or hide text) and a huge value must not flood it.
"""

from __future__ import annotations

__all__ = ["MAX_LINE", "escape", "one_line"]

#: Characters of one printed message line (the rest is elided in the middle).
MAX_LINE = 400

#: Invisible characters that reorder or hide text (bidirectional overrides, zero widths, BOM).
_INVISIBLE = frozenset("\u200b\u200c\u200d\u200e\u200f\u202a\u202b\u202c\u202d\u202e\u2066\u2067\u2068\u2069"
                       "\ufeff")


def _escaped(ch: str) -> str:
    code = ord(ch)
    if code < 0x20 or 0x7F <= code < 0xA0 or ch in _INVISIBLE:
        return f"\\x{code:02x}" if code < 0x100 else f"\\u{code:04x}"
    if 0xDC80 <= code <= 0xDCFF:  # a byte that was not UTF-8 (surrogateescape): show the byte
        return f"\\x{code - 0xDC00:02x}"
    if 0xD800 <= code <= 0xDFFF:  # any other lone surrogate cannot be encoded at all
        return f"\\u{code:04x}"
    return ch


def escape(text: str) -> str:
    """``text`` with control, invisible and undecodable characters written as ``\\xNN`` / ``\\uNNNN``."""
    return "".join(_escaped(ch) for ch in text)


def one_line(text: str, limit: int = MAX_LINE) -> str:
    """``text`` escaped (:func:`escape`, newlines included) and cut to ``limit`` characters in the middle."""
    tail_n = limit // 4
    head_n = limit - tail_n - 5  # room for " ... "
    if len(text) <= limit:
        line = escape(text)
        return line if len(line) <= limit else f"{line[:head_n]} ... {line[-tail_n:]}"
    # only the two ends are escaped: a huge text costs no more than a short one
    return f"{escape(text[:head_n])[:head_n]} ... {escape(text[-tail_n:])[-tail_n:]}"
