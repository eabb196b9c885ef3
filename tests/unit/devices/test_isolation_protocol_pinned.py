"""Pinned behaviour of the native-isolation protocol (issue #32): which values travel by value (the exact plain
types, to exactly ``MAX_PLAIN_DEPTH`` levels), the errors rebuilt in the parent, the wire words and bounds, and
the worker's last guard: a reply that pickle refuses goes out as an error reply, not as the worker's end.
"""

from __future__ import annotations

import collections
import pickle
import signal

import pytest

from cellcal.devices.isolation import protocol as p


# ---------------------------------------------------------------- protocol: what travels by value
def _nested_lists(levels: int) -> object:
    """``levels`` lists one inside the other around the scalar 1 (``levels=2``: ``[[1]]``)."""
    value: object = 1
    for _ in range(levels):
        value = [value]
    return value


def _nested_dicts(levels: int) -> object:
    """``levels`` str-keyed dicts one inside the other around the scalar 1."""
    value: object = 1
    for _ in range(levels):
        value = {"k": value}
    return value


@pytest.mark.parametrize("value", [None, True, 0, -7, 2.5, float("nan"), "", "text", b"", b"\x00\xff"])
def test_every_scalar_type_is_plain(value: object) -> None:
    assert p.is_plain(value) is True


@pytest.mark.parametrize("value", [object(), {1, 2}, frozenset(), bytearray(b"x"), 1j, range(3), print])
def test_other_types_stay_in_the_worker(value: object) -> None:
    assert p.is_plain(value) is False


def test_containers_are_plain_to_exactly_max_plain_depth_levels() -> None:
    assert p.MAX_PLAIN_DEPTH == 4
    for nest in (_nested_lists, _nested_dicts):
        assert p.is_plain(nest(p.MAX_PLAIN_DEPTH)) is True            # [[[[1]]]]: four levels travel
        assert p.is_plain(nest(p.MAX_PLAIN_DEPTH + 1)) is False       # [[[[[1]]]]]: the fifth stays
    assert p.is_plain([[[[]]]]) is True
    assert p.is_plain([[[[[]]]]]) is False                            # an empty container at depth 4 too
    assert p.is_plain((1, [2.0, {"a": ("b", b"c")}], None)) is True     # mixed kinds count levels alike
    assert p.is_plain((1, [2.0, {"a": ("b", [b"c"])}], None)) is False


def test_the_depth_argument_counts_the_levels_already_descended() -> None:
    assert p.is_plain([1], depth=p.MAX_PLAIN_DEPTH - 1) is True
    assert p.is_plain([1], depth=p.MAX_PLAIN_DEPTH) is False
    assert p.is_plain({"k": 1}, depth=p.MAX_PLAIN_DEPTH) is False
    assert p.is_plain("scalar", depth=p.MAX_PLAIN_DEPTH + 10) is True  # scalars at any depth
    assert p.is_plain([[1]], depth=p.MAX_PLAIN_DEPTH - 2) is True
    assert p.is_plain([[1]], depth=p.MAX_PLAIN_DEPTH - 1) is False


def test_one_non_plain_member_keeps_the_whole_container_in_the_worker() -> None:
    assert p.is_plain([1, 2, object()]) is False
    assert p.is_plain((object(),)) is False
    assert p.is_plain([1, 2, 3]) is True and p.is_plain(()) is True and p.is_plain([]) is True
    assert p.is_plain({"a": 1, "b": object()}) is False
    assert p.is_plain({"a": 1, "b": [2, 3]}) is True and p.is_plain({}) is True


def test_dicts_travel_only_with_string_keys() -> None:
    assert p.is_plain({1: "x"}) is False
    assert p.is_plain({"a": 1, 2: "b"}) is False
    assert p.is_plain({("a",): 1}) is False
    assert p.is_plain({"a": 1.5, "b": None}) is True


def test_subclasses_of_plain_types_stay_in_the_worker() -> None:
    """Unpickled in the parent, a subclass would import its module there: perhaps the native library itself."""
    assert p.is_plain(collections.Counter("abracadabra")) is False      # a dict subclass (str keys)
    assert p.is_plain(collections.OrderedDict(a=[1, 2])) is False
    assert p.is_plain(signal.SIGINT) is False                          # an IntEnum
    assert p.is_plain(collections.namedtuple("Point", "x y")(1, 2)) is False
    assert p.is_plain([1, signal.SIGINT]) is False and p.is_plain({"a": (1, True)}) is True


# ---------------------------------------------------------------- protocol: errors rebuilt in the parent
@pytest.mark.parametrize("name", sorted(p.KNOWN_ERRORS))
def test_a_known_error_comes_back_as_itself_with_its_message(name: str) -> None:
    error = p.rebuild_error(name, "the library said no")
    assert type(error) is p.KNOWN_ERRORS[name] and type(error).__name__ == name
    assert error.args == ("the library said no",)


def test_the_known_errors_are_exactly_the_builtin_ones_a_library_raises() -> None:
    assert sorted(p.KNOWN_ERRORS) == ["AttributeError", "ConnectionError", "ImportError", "IndexError", "KeyError",
                                      "ModuleNotFoundError", "OSError", "RuntimeError", "TimeoutError", "TypeError",
                                      "ValueError"]


@pytest.mark.parametrize("name", ["JSONDecodeError", "RuntimeException", "ZeroDivisionError", "Exception", ""])
def test_any_other_error_is_a_runtime_error_naming_its_type(name: str) -> None:
    error = p.rebuild_error(name, "boom: at line 3")
    assert type(error) is RuntimeError
    assert error.args == (f"{name}: boom: at line 3",)


def test_message_kinds_and_operations_are_distinct_wire_words() -> None:
    # the parent and the worker (another interpreter, possibly another cellcal) agree on these words
    assert (p.IMPORT, p.CALL, p.DROP, p.CLOSE) == ("import", "call", "drop", "close")
    assert (p.VALUE, p.REF, p.ERROR) == ("value", "ref", "error")
    assert p.MAX_MESSAGE_BYTES == 1_048_576 and p.MAX_ERROR_CHARS == 2000


# ---------------------------------------------------------------- worker: a reply that does not pickle
def test_a_reply_that_does_not_pickle_goes_out_as_an_error_not_as_the_workers_end() -> None:
    """The worker's last guard: a reply pickle refuses becomes an error reply with the same sequence number."""
    from multiprocessing.connection import Pipe
    from types import SimpleNamespace

    from cellcal.devices.isolation.worker import Worker

    ours, theirs = Pipe()
    try:
        Worker._send(SimpleNamespace(conn=theirs), (7, p.VALUE, lambda: 0))  # type: ignore[arg-type]
        seq, kind, (name, message) = pickle.loads(ours.recv_bytes(p.MAX_MESSAGE_BYTES))
        assert (seq, kind) == (7, p.ERROR) and name in ("PicklingError", "AttributeError")  # by Python version
        assert message.startswith("the reply could not be pickled: ") and len(message) <= p.MAX_ERROR_CHARS
        assert str(p.rebuild_error(name, message)).startswith(("the reply could not be pickled", "PicklingError: the"))
    finally:
        ours.close()
        theirs.close()
