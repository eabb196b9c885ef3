"""Bounded fuzz (hypothesis) of the six parsers fed by the outside world.

The PCIC stream parser and decoder, the xArm frame parser (both directions), the O3R
XML-RPC/JSON configuration path, the TOML cell-configuration loader, the UR RTDE parsers
(the emulated controller's and the driver's probe) and the live-view relay's handshake
renames must answer any input with success or their documented error (:class:`ProtocolError`,
for the O3R configuration also :class:`VendorError` and :class:`ConfigError`; :class:`ConfigError`
for the TOML loader; for the RTDE probe also :class:`DeviceConnectionError` and
:class:`DeviceTimeoutError`; none for the renames), never another exception. The
targets and mutators live in ``tests/support/fuzz_targets.py`` and are shared with the long
seeded run in ``benchmarks/fuzz_parsers.py``; here each gets a few hundred examples
(the whole file runs in seconds).
"""

from __future__ import annotations

import dataclasses
import json
import random
import struct
import time
import tomllib
from collections.abc import Iterator
from pathlib import Path

import pytest
from fuzz_base import Target
from fuzz_liveview import LIVEVIEW_TOKENS, liveview_target
from fuzz_rtde import (
    RTDE_ERRORS,
    RTDE_FREQUENCIES,
    RTDE_NAME_TOKENS,
    RTDE_TYPES,
    probe_rtde_replies,
    rtde_frames,
    rtde_target,
    split_rtde,
)
from fuzz_targets import (
    CONFIG_DIR,
    ODD_VALUES,
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

from cellcal.core.liveview.subprotocol import LEGACY, SDK, rename_offer
from cellcal.devices.errors import (
    CellcalError,
    ConfigError,
    DeviceConnectionError,
    DeviceTimeoutError,
    ProtocolError,
    VendorError,
)
from cellcal.drivers.o3r.decode import FrameDecoder
from cellcal.drivers.o3r.pcic import iter_messages, walk_chunks
from cellcal.drivers.xarm.protocol import encode_request, parse_reply
from cellcal.sims.ur import rtde_wire

BOUNDED = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                                          HealthCheck.function_scoped_fixture])

PCIC = pcic_target()
XARM = xarm_target()
XMLRPC = xmlrpc_target()
RTDE = rtde_target()
LIVEVIEW = liveview_target()


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
    assert RTDE.documented == RTDE_ERRORS == (ProtocolError, DeviceConnectionError, DeviceTimeoutError)
    assert LIVEVIEW.documented == () and LIVEVIEW.documented_names == "-"


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


def test_rtde_seeds_are_read_one_way_or_the_other() -> None:
    """The client streams by the controller's parsers, the reply streams by the probe (which returns their time)."""
    assert all(RTDE.check(seed) for seed in RTDE.seeds)
    assert all(issubclass(k, CellcalError) for k in RTDE.documented)  # type: ignore[union-attr]
    client, stream, probe, chatty = RTDE.seeds
    assert len(rtde_frames(client)) == 8 and len(rtde_frames(stream)) == 4
    assert probe_rtde_replies(probe) == probe_rtde_replies(chatty) == 12.5
    with pytest.raises(ProtocolError, match="refused RTDE protocol version 2"):
        probe_rtde_replies(client)  # its V request (version 00 02) read as a reply: a refusal
    with pytest.raises(DeviceConnectionError, match="closed"):
        probe_rtde_replies(b"")  # the peer closes before answering


@pytest.mark.parametrize("name", [b"output_int_register_" + b"1" * 4301, b"input_double_register_" + b"0" * 5000,
                                  b"input_int_register_03", b"output_bit_register_1270"])
def test_rtde_register_name_of_thousands_of_digits_is_no_field(name: bytes) -> None:
    """Regression (found by the fuzzer): such a name is NOT_FOUND in a setup, not a ValueError from int()."""
    w = rtde_wire
    assert w.input_type(name.decode()) is None and w.output_type(name.decode()) is None
    assert RTDE.check(w.message(w.CONTROL_PACKAGE_SETUP_INPUTS, name))
    assert RTDE.check(w.message(w.CONTROL_PACKAGE_SETUP_OUTPUTS, struct.pack(">d", 125.0) + b"timestamp," + name))


@pytest.mark.parametrize("size", [0, 1, 2])
def test_rtde_size_field_below_the_header_is_a_protocol_error(size: int) -> None:
    """Regression: a u16 size field (1, say) smaller than the 3-byte header, alone or after a valid message."""
    bad = struct.pack(">HB", size, rtde_wire.DATA_PACKAGE) + b"\x01" + bytes(8)
    valid = rtde_wire.protocol_reply(True)
    for stream in (bad, valid + bad):
        with pytest.raises(ProtocolError, match="smaller than"):
            rtde_wire.FrameReader().feed(stream)
        with pytest.raises(ProtocolError, match="smaller than its header"):
            probe_rtde_replies(stream)
        with pytest.raises(ProtocolError):
            RTDE.run(stream)
    reader = rtde_wire.FrameReader()
    assert reader.feed(valid + bad[:1]) == [(rtde_wire.REQUEST_PROTOCOL_VERSION, b"\x01")]
    with pytest.raises(ProtocolError, match=f"message size {size} is smaller"):
        reader.feed(bad[1:])  # the rest of the header in the next read


def test_rtde_a_silent_peer_is_a_timeout() -> None:
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeoutError, match="sent no data"):
        probe_rtde_replies(RTDE.seeds[2][:-3], timeout=0.05, close=False)
    assert time.monotonic() - t0 < 1.0


def test_rtde_mutations_edit_size_fields_and_messages() -> None:
    rnd = random.Random(5)
    seed = RTDE.seeds[0]
    mutated = [RTDE.mutate(seed, rnd) for _ in range(200)]
    assert sum(m != seed for m in mutated) >= 190
    sizes = {struct.unpack_from(">H", m)[0] for mut in mutated for m in split_rtde(mut) if len(m) >= 3}
    assert {0, 1, 2, 3, 0xFFFF} <= sizes


@BOUNDED
@given(index=st.integers(0, 10), rnd=st.randoms(use_true_random=False))
def test_fuzz_rtde_mutated_streams_raise_only_documented_errors(index: int, rnd: random.Random) -> None:
    RTDE.check(RTDE.mutate(RTDE.seeds[index % len(RTDE.seeds)], rnd))


@settings(max_examples=200, deadline=None)
@given(raw=st.binary(max_size=300), msg_type=st.sampled_from(RTDE_TYPES))
def test_fuzz_rtde_random_bytes_raise_only_documented_errors(raw: bytes, msg_type: int) -> None:
    RTDE.check(raw)
    RTDE.check(rtde_wire.message(msg_type, raw))


@settings(max_examples=200, deadline=None)
@given(names=st.lists(st.sampled_from([t for t in RTDE_NAME_TOKENS if len(t) < 100]), min_size=1, max_size=8),
       freq=st.sampled_from(RTDE_FREQUENCIES) | st.floats(), body=st.binary(max_size=120), inputs=st.booleans())
def test_fuzz_rtde_any_setup_then_data(names: list[bytes], freq: float, body: bytes, inputs: bool) -> None:
    """A setup of any names (and rate), then a data package: a recipe of valid names unpacks a body of its size."""
    w = rtde_wire
    text = b",".join(names)
    setup = (w.message(w.CONTROL_PACKAGE_SETUP_INPUTS, text) if inputs
             else w.message(w.CONTROL_PACKAGE_SETUP_OUTPUTS, struct.pack(">d", freq) + text))
    lookup = w.input_type if inputs else w.output_type
    parts = [n.decode("latin-1").strip() for n in names]
    valid = all(lookup(n) for n in parts)
    if valid:
        recipe = w.Recipe(1, tuple(parts), tuple(lookup(n) or "" for n in parts))
        body = (body * (recipe.size // max(1, len(body)) + 1))[:recipe.size] if body else bytes(recipe.size)
    assert RTDE.check(setup + w.data_package(1, body)) or not valid


def test_liveview_seeds() -> None:
    """Requests offering only the legacy name are renamed, the others (and the replies) forwarded unchanged."""
    assert all(LIVEVIEW.check(seed) for seed in LIVEVIEW.seeds)
    renamed = [rename_offer(seed)[1] for seed in LIVEVIEW.seeds]
    assert renamed == [True, False, False, False, True, True, True, False, False]
    for seed, was in zip(LIVEVIEW.seeds, renamed, strict=True):
        assert (LEGACY in rename_offer(seed)[0]) == (LEGACY in seed and not was)
        assert was <= (SDK in rename_offer(seed)[0])


@BOUNDED
@given(index=st.integers(0, 10), rnd=st.randoms(use_true_random=False))
def test_fuzz_liveview_mutated_handshakes_keep_the_promises(index: int, rnd: random.Random) -> None:
    assert LIVEVIEW.check(LIVEVIEW.mutate(LIVEVIEW.seeds[index % len(LIVEVIEW.seeds)], rnd))


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=600))
def test_fuzz_liveview_random_bytes_keep_the_promises(raw: bytes) -> None:
    assert LIVEVIEW.check(raw)


@settings(max_examples=200, deadline=None)
@given(lines=st.lists(st.lists(st.sampled_from((*LIVEVIEW_TOKENS, b"x.v2", b"Host: h", b"")), max_size=6)
                      .map(b"".join), max_size=8))
def test_fuzz_liveview_handshakes_of_tokens_keep_the_promises(lines: list[bytes]) -> None:
    """Header lines made of protocol names, header names, separators and odd bytes."""
    assert LIVEVIEW.check(b"GET / HTTP/1.1\r\n" + b"\r\n".join(lines) + b"\r\n\r\n")
