"""Bounded fuzz (hypothesis) of the four parsers fed by the outside world.

The PCIC stream parser and decoder, the xArm frame parser (both directions), the O3R
XML-RPC/JSON configuration path and the TOML cell-configuration loader must answer any
input with success or their documented error (:class:`ProtocolError`, for the O3R
configuration also :class:`VendorError` and :class:`ConfigError`; :class:`ConfigError` for
the TOML loader), never another exception. The
targets and mutators live in ``tests/support/fuzz_targets.py`` and are shared with the long
seeded run in ``benchmarks/fuzz_parsers.py``; here each gets a few hundred examples
(the whole file runs in seconds).
"""

from __future__ import annotations

import dataclasses
import json
import random
import tomllib
from collections.abc import Iterator
from pathlib import Path

import pytest
from fuzz_targets import (
    CONFIG_DIR,
    ODD_VALUES,
    Target,
    check_decoded,
    config_target,
    dump_toml,
    mutate_document,
    o3r_tree,
    pcic_target,
    xarm_target,
    xmlrpc_reply,
    xmlrpc_target,
)
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from xarm_wire_helpers import encode_reply, parse_request

from cellcal.devices.errors import CellcalError, ConfigError, ProtocolError, VendorError
from cellcal.drivers.o3r.decode import FrameDecoder
from cellcal.drivers.o3r.pcic import iter_messages, walk_chunks
from cellcal.drivers.xarm.protocol import encode_request, parse_reply

BOUNDED = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                                          HealthCheck.function_scoped_fixture])

PCIC = pcic_target()
XARM = xarm_target()
XMLRPC = xmlrpc_target()


@pytest.fixture(scope="module")
def config_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("fuzz-config")


@pytest.fixture(scope="module")
def config(config_dir: Path) -> Iterator[Target]:
    target = config_target(config_dir)
    yield target
    target.close()


@pytest.mark.parametrize("target", [PCIC, XARM], ids=lambda t: t.name)
def test_seeds_parse_and_errors_are_cellcal_errors(target: Target) -> None:
    assert all(target.check(seed) for seed in target.seeds)
    assert issubclass(target.documented, CellcalError)


def test_config_seeds_load(config: Target) -> None:
    assert len(config.seeds) >= 5
    assert all(config.check(seed) for seed in config.seeds)
    assert not config.check(b"[camera]\nbackend = 'sim'\n")  # no [arm]: rejected with ConfigError


@BOUNDED
@given(index=st.integers(0, 10), rnd=st.randoms(use_true_random=False))
def test_fuzz_pcic_mutated_streams_raise_only_protocol_error(index: int, rnd: random.Random) -> None:
    PCIC.check(PCIC.mutate(PCIC.seeds[index % len(PCIC.seeds)], rnd))


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=600))
def test_fuzz_pcic_random_bytes_raise_only_protocol_error(raw: bytes) -> None:
    assert not PCIC.check(b"0000L%09d\r\n0000star" % (len(raw) + 14) + raw + b"stop\r\n")
    PCIC.check(raw)


@BOUNDED
@given(frame=st.builds(encode_reply, st.integers(0, 255), st.binary(max_size=48)),
       request=st.builds(encode_request, st.integers(0, 255), st.binary(max_size=80)),
       rnd=st.randoms(use_true_random=False))
def test_fuzz_xarm_frames_raise_only_protocol_error(frame: bytes, request: bytes, rnd: random.Random) -> None:
    assert parse_reply(frame).data == frame[4:-2]
    assert parse_request(request).params == request[4:-2]
    for seed in (frame, request, rnd.choice(XARM.seeds)):
        XARM.check(XARM.mutate(seed, rnd))  # whatever parses must also re-encode to the same bytes


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=80))
def test_fuzz_xarm_random_bytes_raise_only_protocol_error(raw: bytes) -> None:
    XARM.check(raw)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(index=st.integers(0, 10), rnd=st.randoms(use_true_random=False))
def test_fuzz_config_mutations_raise_only_config_error(config: Target, index: int, rnd: random.Random) -> None:
    config.check(config.mutate(config.seeds[index % len(config.seeds)], rnd))


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(text=st.text(alphabet=st.sampled_from(list("[]{}=\"'.,#\n -+_0123456789abcdeinfsmtuxyz")), max_size=200))
def test_fuzz_config_random_text_raises_only_config_error(config: Target, text: str) -> None:
    config.check(text.encode("utf-8"))


def test_xmlrpc_seeds() -> None:
    assert XMLRPC.check(XMLRPC.seeds[0])  # the whole documented tree parses
    assert not XMLRPC.check(XMLRPC.seeds[-1])  # a well-formed fault: VendorError
    assert all(issubclass(k, CellcalError) for k in XMLRPC.documented)  # type: ignore[union-attr]


@BOUNDED
@given(index=st.integers(0, 10), rnd=st.randoms(use_true_random=False))
def test_fuzz_xmlrpc_mutated_replies_raise_only_documented_errors(index: int, rnd: random.Random) -> None:
    XMLRPC.check(XMLRPC.mutate(XMLRPC.seeds[index % len(XMLRPC.seeds)], rnd))


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=600))
def test_fuzz_xmlrpc_random_bytes_raise_only_documented_errors(raw: bytes) -> None:
    assert not XMLRPC.check(raw)


_json = st.recursive(st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=20),
                     lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner,
                                                                                 max_size=4), max_leaves=12)


@settings(max_examples=200, deadline=None)
@given(where=st.sampled_from([("ports", "port2", "data", "pcicTCPPort"), ("ports", "port2", "state"),
                              ("ports", "port2", "info", "features", "type"), ("ports", "port2", "info"),
                              ("ports", "port2", "info", "features", "resolution", "width"), ("ports", "port2"),
                              ("ports",), ("device", "swVersion", "firmware"), ("ports", "port0", "data")]),
       value=_json)
def test_fuzz_xmlrpc_any_json_value_anywhere_in_the_tree(where: tuple[str, ...], value: object) -> None:
    """Any JSON value at a documented place: parses, or one error naming that place's JSON pointer."""
    doc = o3r_tree()
    node = doc
    for key in where[:-1]:
        node = node[key]
    node[where[-1]] = value
    try:
        XMLRPC.run(xmlrpc_reply(json.dumps(doc, allow_nan=True)))
    except ProtocolError as exc:
        text = str(exc)
        assert "\n" not in text and len(text) < 400
        assert "/" + "/".join(where) in text or "not JSON" in text, text  # NaN/Infinity are refused as such
    except ConfigError as exc:  # the ports table lost a port: that is the configured port missing
        assert where == ("ports",) and "has no port" in str(exc), str(exc)
    except VendorError:
        raise AssertionError("a value in the tree is not a fault") from None


_values = st.sampled_from(ODD_VALUES)


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(table=st.sampled_from(["cell", "camera", "arm", "mount", "reference", "safety", "plan", "sim", "monitor"]),
       key=st.sampled_from(["backend", "seed", "name", "heights_m", "plane_normal", "translation_m",
                            "max_speed_m_s", "time_scale", "width", "poses", "boxes", "mount", "nope"]),
       value=_values)
def test_fuzz_config_one_odd_value_anywhere(config: Target, config_dir: Path, table: str, key: str,
                                           value: object) -> None:
    """A single odd value (wrong type, extreme, nan) in any table: loads, or one ConfigError naming the key."""
    doc = tomllib.loads((CONFIG_DIR / "sim.toml").read_text(encoding="utf-8"))
    doc.setdefault(table, {})[key] = value
    try:
        config.run(dump_toml(doc).encode())
    except ConfigError as exc:
        text = str(exc)
        assert "\n" not in text
        assert text.startswith(str(config_dir / "cell.toml"))
        assert exc.key is not None and exc.key.startswith(table), text


def test_structural_mutation_changes_the_document() -> None:
    rnd = random.Random(3)
    doc = {"cell": {"seed": 7}, "plan": {"heights_m": [0.5, 0.6]}}
    assert sum(mutate_document(doc, rnd) != doc for _ in range(20)) >= 15
    assert doc == {"cell": {"seed": 7}, "plan": {"heights_m": [0.5, 0.6]}}  # the input is left alone


def test_documented_errors() -> None:
    assert PCIC.documented is ProtocolError and XARM.documented is ProtocolError
    assert XMLRPC.documented == (ProtocolError, VendorError, ConfigError)


def test_the_pcic_oracle_refuses_a_frame_that_disagrees_with_its_declared_sizes() -> None:
    """A decoder that dropped a size check would hand out such frames: the oracle must notice."""
    seed = PCIC.seeds[0]
    msg = next(iter_messages(seed))
    chunks = walk_chunks(msg.payload)
    frame = FrameDecoder().decode(msg.payload, chunks).frame
    check_decoded(bytes(msg.payload), chunks, frame, 7)  # the seed is consistent
    h, w = frame.distance.shape
    narrower = dataclasses.replace(frame.intrinsics, width=w - 1)
    cropped = dataclasses.replace(frame, distance=frame.distance[:, :-1], xyz=frame.xyz[:, :-1],
                                  amplitude=frame.amplitude[:, :-1], valid=frame.valid[:, :-1], confidence=None,
                                  intrinsics=narrower)
    short = [dataclasses.replace(c, data_size=w * h * 2 - 2) if c.chunk_type == 100 else c for c in chunks]
    past_end = [dataclasses.replace(c, data_size=len(msg.payload)) if c.chunk_type == 101 else c for c in chunks]
    for spoiled_chunks, spoiled_frame, count in ((chunks, cropped, 7), (short, frame, 7), (past_end, frame, 7),
                                                 (chunks, frame, 8)):
        with pytest.raises(AssertionError):
            check_decoded(bytes(msg.payload), spoiled_chunks, spoiled_frame, count)
