"""Bounded JSON: the nesting depth is measured outside strings and checked before parsing (ADR 0039)."""

from __future__ import annotations

import json

import pytest

from cellcal.devices.boundedjson import MAX_DEPTH, JSONTooDeepError, json_depth, loads


@pytest.mark.parametrize(("text", "depth"), [
    ("1", 0), ("[]", 1), ('{"a": [1, {"b": []}]}', 4), ('["[[[{", "\\"[["]', 1), ('"]]]"', 0),
])
def test_depth_counts_brackets_outside_strings(text: str, depth: int) -> None:
    assert json_depth(text) == depth
    assert loads(text) == json.loads(text)


def test_the_bound_is_inclusive_and_the_parser_is_never_reached_beyond_it() -> None:
    at = "[" * MAX_DEPTH + "]" * MAX_DEPTH
    assert json_depth(loads(at).__repr__()) == MAX_DEPTH
    too_deep = f"nested {MAX_DEPTH + 1} levels deep, more than the {MAX_DEPTH} accepted"
    with pytest.raises(JSONTooDeepError, match=too_deep):
        loads("[" + at + "]")
    # 100 000 levels: the plain parser raises RecursionError; the bounded one a ValueError
    with pytest.raises(ValueError, match="nested 100000 levels deep"):
        loads(b"{" * 1 + b'"a":' + b"[" * 99_999 + b"]" * 99_999 + b"}")
