"""Fuzz targets shared by ``tests/integration/faults/test_fuzz_parsers.py`` (hypothesis, bounded, in CI) and
``benchmarks/fuzz_parsers.py`` (long seeded runs with counts).

A :class:`Target` is a parser, the one error it documents for bad input, valid seed
inputs, and a mutator ``(seed bytes, random.Random) -> bytes``. Feeding it anything
must either succeed or raise the documented error; any other exception is a defect.
:class:`Target` and the byte mutations are in ``fuzz_base``, the ``rtde`` target in ``fuzz_rtde`` and the
``liveview`` target in ``fuzz_liveview``; this module holds the others and :func:`all_targets`.

* ``pcic`` — ifm O3R PCIC stream: :func:`iter_messages`, :func:`walk_chunks`,
  :class:`FrameDecoder` (image chunks and TOF_INFO), async errors and notifications;
  documented error :class:`ProtocolError`.
* ``xarm`` — UFACTORY xArm serial frames both ways: :class:`FrameSplitter`,
  :func:`parse_reply` / :func:`parse_request` (whatever parses must re-encode to the
  same bytes), and the register decoders on the parsed data; :class:`ProtocolError`.
* ``xmlrpc`` — the ifm O3R configuration channel from the HTTP body on: :func:`parse_reply`
  (defusedxml + XML-RPC), :func:`parse_json_object`, and the checks of the documented tree
  (:func:`port_info`, :func:`firmware`); documented errors :class:`ProtocolError`,
  :class:`VendorError` (a well-formed fault) and :class:`ConfigError` (no such port), each
  one line of at most 600 characters. Mutations are byte and XML-token edits of the reply,
  structural edits of the JSON tree inside it, and byte edits of that JSON text.
* ``config`` — the TOML cell configuration: :func:`load_config` on the bytes written
  to a file, then :func:`build_devices` (backend sections and ``[sim]``);
  :class:`ConfigError`. Mutations are byte/line edits of the text and structural edits
  of the parsed document (values of other types, extreme numbers, deleted/added keys).
* ``rtde`` — UR RTDE both ways: the emulated controller's reading of a client's stream
  (:class:`FrameReader`, whole and in pieces, checked against the size fields; the ``V``,
  ``O`` and ``I`` request parsers, the setup reply, :meth:`Recipe.unpack` of data packages
  for recipes of valid names) and the driver's :func:`probe_stream` reading a controller's
  replies from a socket pair whose peer sends the input and closes. Either reading may
  accept; documented errors :class:`ProtocolError` (the only one of the controller side),
  :class:`DeviceConnectionError` and :class:`DeviceTimeoutError`. Mutations are size-field
  edits (0, 1, 2, 3, the true size -/+ 1, 0xFFFF), payload, type and setup-name edits,
  message splicing and repetition, byte edits.
* ``liveview`` — the live-view relay's handshake renames :func:`rename_offer` and
  :func:`rename_reply`: no documented error (any bytes give bytes), each result checked
  against the module's promises (renamed exactly when ``foxglove.websocket.v1`` is offered
  without ``foxglove.sdk.v1``, otherwise unchanged; only protocol header lines change).
  Mutations are line duplication, huge values, tokens, bare LF/CR, case, truncation.
"""

from __future__ import annotations

import contextlib
import copy
import json
import math
import random
import struct
import tempfile
import tomllib
import xmlrpc.client
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from fuzz_base import Target, mutate_bytes, random_bytes
from fuzz_liveview import liveview_target
from fuzz_rtde import rtde_target
from xarm_wire_helpers import decode_move_line, encode_reply, parse_request, request_splitter

from cellcal.core.calibration.calibrator import build_devices
from cellcal.core.calibration.config import load_config
from cellcal.devices.errors import (
    ConfigError,
    ProtocolError,
    VendorError,
)
from cellcal.devices.geometry.camera_model import pixel_grid_rays
from cellcal.devices.types import Frame, Intrinsics
from cellcal.drivers.o3r.decode import FrameDecoder
from cellcal.drivers.o3r.pcic import (
    TICKET_ASYNC_ERROR,
    TICKET_ASYNC_NOTIFICATION,
    TICKET_IMAGE,
    Chunk,
    encode_message,
    iter_messages,
    parse_async_error,
    parse_notification,
    walk_chunks,
)
from cellcal.drivers.o3r.xmlrpc_config import parse_json_object
from cellcal.drivers.o3r.xmlrpc_config import parse_reply as parse_rpc_reply
from cellcal.drivers.o3r_json import firmware, port_info
from cellcal.drivers.xarm.protocol import FrameSplitter, encode_request, parse_reply
from cellcal.drivers.xarm.registers import decode_serials, decode_text, unpack_floats
from cellcal.sims.o3r.encoder import FrameEncoder
from cellcal.sims.o3r.wire import message, models_from_intrinsics


# ---------------------------------------------------------------------- PCIC
def _plane_frame(intr: Intrinsics, z_m: float = 0.8) -> Frame:
    rays = pixel_grid_rays(intr)
    dist = (z_m / rays[..., 2]).astype(np.float32)
    dist[0, 0] = np.nan
    valid = np.isfinite(dist)
    return Frame(distance=dist, xyz=(rays * dist[..., None]).astype(np.float32),
                 amplitude=np.full(dist.shape, 123.0, np.float32), valid=valid, intrinsics=intr,
                 timestamp=1700000000.25, sequence=3, confidence=np.where(valid, 0, 1).astype(np.uint16))


def pcic_seeds() -> list[bytes]:
    """Image messages (header versions 1-3, with and without distortion) plus async messages."""
    plain = Intrinsics(width=16, height=12, fx=20.25, fy=21.5, cx=7.5, cy=5.25)
    dist = Intrinsics(width=16, height=12, fx=20.25, fy=21.5, cx=7.5, cy=5.25, k1=-0.05, k2=0.01, p1=3e-4,
                      p2=-2e-4, k3=0.002)
    seeds = []
    for intr, version in ((plain, 2), (dist, 3), (plain, 1)):
        rays = pixel_grid_rays(intr) if intr.has_distortion else None
        enc = FrameEncoder(models_from_intrinsics(intr, rays), header_version=version)
        seeds.append(message(TICKET_IMAGE, enc.payload(_plane_frame(intr), 7)))
    seeds.append(seeds[0] + encode_message(TICKET_ASYNC_ERROR, b"000000042:x")
                 + encode_message(TICKET_ASYNC_NOTIFICATION, b'000500000:{"a": 1}'))
    return seeds


#: Bytes per pixel of the PIXEL_FORMAT codes an image chunk may carry (ifm's table: 8/16/32/64-bit
#: integers and floats, 3 x float32 for XYZ), written out here for the oracle.
_PIXEL_BYTES = {0: 1, 1: 1, 2: 2, 3: 2, 4: 4, 5: 4, 6: 4, 7: 8, 8: 12}


def check_decoded(payload: bytes, chunks: list[Chunk], frame: Frame, count: int) -> None:
    """The oracle: a decoded frame must agree with the sizes its payload declares.

    Raises:
        AssertionError: A chunk outside the payload or overlapping the next one, a frame whose
            images do not have the declared size, a pixel chunk shorter than its declared
            image, or a validity mask that disagrees with the distances.
    """
    end = 4  # after 'star'
    for c in chunks:
        assert end <= c.offset < c.data_offset <= c.data_offset + c.data_size <= len(payload) - 6, c
        end = c.data_offset + c.data_size
    by_type = {c.chunk_type: c for c in chunks}
    dist_c, info_c = by_type[100], by_type[420]
    h, w = frame.distance.shape
    assert (dist_c.width, dist_c.height) == (info_c.width, info_c.height) == (w, h)
    assert frame.xyz.shape == (h, w, 3) and frame.valid.shape == frame.amplitude.shape == (h, w)
    for ctype in (100, 101, 300):  # every pixel chunk the decoder read holds its whole image
        c = by_type.get(ctype)
        if c is not None and (ctype == 100 or ctype == 101 or frame.confidence is not None):
            assert (c.width, c.height) == (w, h) and c.data_size >= w * h * _PIXEL_BYTES[c.pixel_format], c
    assert frame.confidence is None or frame.confidence.shape == (h, w)
    assert np.array_equal(frame.valid, np.isfinite(frame.distance)) and count == dist_c.frame_count


def parse_pcic(data: bytes) -> None:
    """Everything the driver does with a received stream (minus the socket), and the oracle on each frame."""
    for msg in iter_messages(data, max_payload=1 << 20):
        if msg.ticket == TICKET_IMAGE:
            chunks = walk_chunks(msg.payload)
            decoded = FrameDecoder().decode(msg.payload, chunks)
            check_decoded(bytes(msg.payload), chunks, decoded.frame, decoded.frame_count)
        elif msg.ticket == TICKET_ASYNC_ERROR:
            parse_async_error(msg.content)
        elif msg.ticket == TICKET_ASYNC_NOTIFICATION:
            parse_notification(msg.content)


def size_lie(seed: bytes, rng: random.Random) -> bytes:
    """The seed's first image with a size its pixel data does not have, told consistently.

    Every image chunk and the TOF_INFO header claim the same larger (or differently shaped)
    image, so no cross-check between them can notice: only the chunk-size check can.
    """
    n = len(next(iter_messages(seed, max_payload=1 << 20)).payload)
    payload = bytearray(seed[16:16 + n])  # the first message's payload follows its 16-byte header
    chunks = walk_chunks(payload)
    w, h = chunks[0].width, chunks[0].height
    new_w, new_h = rng.choice([(w + 1, h), (w, h + 1), (2 * w, 2 * h), (w * h, 2), (w + rng.randrange(1, 64), h)])
    for c in chunks:
        struct.pack_into("<2I", payload, c.offset + 16, new_w, new_h)  # IMAGE_WIDTH, IMAGE_HEIGHT
    return seed[:16] + bytes(payload) + seed[16 + n:]


def mutate_pcic(seed: bytes, rng: random.Random) -> bytes:
    """Byte edits of a valid stream, a consistent size lie, or random bytes (bare, or in a valid image envelope)."""
    kind = rng.random()
    if kind < 0.7:
        return mutate_bytes(seed, rng)
    if kind < 0.8:
        return size_lie(seed, rng)
    raw = random_bytes(rng)
    if kind < 0.9:
        return b"0000L%09d\r\n0000star" % (len(raw) + 14) + raw + b"stop\r\n"
    return raw


def pcic_target() -> Target:
    return Target("pcic", ProtocolError, pcic_seeds(), parse_pcic, mutate_pcic)


# ---------------------------------------------------------------------- xArm
def xarm_seeds() -> list[bytes]:
    """Replies and requests of typical sizes (empty, pose of 6 floats, 48 data bytes)."""
    return [encode_reply(0, b""), encode_reply(0x10, struct.pack("<6f", 300, 0, 400, 3.14, 0, 0)),
            encode_reply(0x40, bytes(range(48))), encode_request(1), encode_request(31, bytes(range(36))),
            encode_request(12, b"\x01")]


def _decode_data(data: bytes) -> None:
    for decode in (lambda d: unpack_floats(d, len(d) // 4 + (len(d) % 4 > 0)), decode_move_line, decode_text,
                   decode_serials):
        with contextlib.suppress(ProtocolError):
            decode(data)


def parse_xarm(data: bytes) -> None:
    """Both directions: split the stream, parse each frame, decode the data; round-trip what parsed."""
    for parse, encode, splitter in ((parse_reply, lambda r: encode_reply(r.state, r.data), FrameSplitter.for_replies()),
                                    (parse_request, lambda r: encode_request(r.register, r.params),
                                     request_splitter())):
        for piece in (data, *splitter.feed(data)):
            try:
                parsed = parse(piece)
            except ProtocolError:
                continue
            if encode(parsed) != piece:
                raise AssertionError(f"{parse.__name__} accepted {piece.hex()} but it re-encodes differently")
            _decode_data(parsed.data if hasattr(parsed, "data") else parsed.params)
    try:  # the whole input as one frame: the documented error if it is none
        parse_reply(data)
    except ProtocolError:
        parse_request(data)


def mutate_xarm(seed: bytes, rng: random.Random) -> bytes:
    """Byte edits of 1-3 concatenated frames, or random bytes."""
    if rng.random() < 0.15:
        return random_bytes(rng, 80)
    frames = seed + b"".join(rng.choice(xarm_seeds()) for _ in range(rng.randint(0, 2)))
    return mutate_bytes(frames, rng, max_ops=4)


def xarm_target() -> Target:
    return Target("xarm", ProtocolError, xarm_seeds(), parse_xarm, mutate_xarm)


# ---------------------------------------------------------------------- O3R XML-RPC configuration channel
def o3r_tree() -> dict[str, Any]:
    """A documented O3R tree: a 2D head on port0, a 3D head on port2, the firmware version."""
    head = {"data": {"pcicTCPPort": 50012}, "state": "RUN", "mode": "standard_range4m",
            "info": {"features": {"type": "3D", "resolution": {"width": 224, "height": 172}}, "name": "O3R222"}}
    return {"ports": {"port0": {"data": {"pcicTCPPort": 50010}, "state": "CONF",
                                "info": {"features": {"type": "2D"}}},
                      "port2": head},
            "device": {"swVersion": {"firmware": "1.4.30", "kernel": "5.10"}}}


def xmlrpc_reply(value: Any) -> bytes:
    return xmlrpc.client.dumps((value,), methodresponse=True, allow_none=True).encode("utf-8")


def xmlrpc_seeds() -> list[bytes]:
    """Replies to get (whole tree, one port), set (empty string) and a fault."""
    tree = o3r_tree()
    return [xmlrpc_reply(json.dumps(tree)), xmlrpc_reply(json.dumps({"ports": {"port2": tree["ports"]["port2"]}})),
            xmlrpc_reply(""), xmlrpc.client.dumps(xmlrpc.client.Fault(101000, "unknown key: /x"),
                                                  methodresponse=True).encode()]


#: XML and XML-RPC fragments that break structure, types, entities and encodings.
XML_TOKENS = (b"<!DOCTYPE r [<!ENTITY a 'aaaa'>]>", b"&a;", b"&amp;", b"&#0;", b"&#x110000;", b"<![CDATA[", b"]]>",
              b"<value>", b"</value>", b"<array><data>", b"</data></array>", b"<struct>", b"</struct>",
              b"<member><name>faultCode</name>", b"</member>", b"<int>", b"</int>", b"<int>1e308</int>",
              b"<double>nan</double>", b"<boolean>2</boolean>", b"<nil/>", b"<base64>!</base64>",
              b"<dateTime.iso8601>x</dateTime.iso8601>", b"<fault>", b"</fault>", b"<params>", b"</params>",
              b"<?xml version='1.0' encoding='utf-16'?>", b"\x00", b"\xff", b"<i8>" + b"9" * 5000 + b"</i8>")
#: JSON fragments: deep nesting, constants, huge numbers, odd strings.
JSON_TOKENS = (b"[" * 5000, b"]" * 5000, b"NaN", b"-Infinity", b"1e999", b"1" + b"0" * 5000, b'"\\ud800"', b"null",
               b"true", b"{}", b"[]", b'"\\u0000"', b",", b":", b"{", b"}")


def _mutate_tree_reply(seed: bytes, rng: random.Random) -> bytes | None:
    """The reply with the JSON tree inside edited structurally or as bytes; None if the seed carries none."""
    try:
        text = parse_rpc_reply(seed, "seed")
        doc = json.loads(text) if isinstance(text, str) and text else None
    except (ProtocolError, VendorError, ValueError):
        return None
    if not isinstance(doc, dict):
        return None
    if rng.random() < 0.6:
        return xmlrpc_reply(json.dumps(mutate_document(doc, rng)))
    raw = bytearray(mutate_bytes(json.dumps(doc).encode(), rng, max_ops=3))
    for _ in range(rng.randint(0, 2)):
        pos = rng.randint(0, len(raw))
        raw[pos:pos] = rng.choice(JSON_TOKENS)
    return xmlrpc_reply(raw.decode("utf-8", "replace"))


def mutate_xmlrpc(seed: bytes, rng: random.Random) -> bytes:
    """Structural/byte edits of the JSON inside, XML-token insertions, or byte edits of the XML."""
    kind = rng.random()
    if kind < 0.45:
        mutated = _mutate_tree_reply(seed, rng)
        if mutated is not None:
            return mutated
    if kind < 0.75:
        buf = bytearray(seed)
        for _ in range(rng.randint(1, 3)):
            pos = rng.randint(0, len(buf))
            buf[pos:pos] = rng.choice(XML_TOKENS)
        return bytes(buf)
    if kind < 0.95:
        return mutate_bytes(seed, rng)
    return random_bytes(rng)


def parse_xmlrpc(data: bytes) -> None:
    """Everything the driver does with a reply body: XML-RPC, JSON, then the checks of both ports and firmware.

    Raises:
        The last documented error; AssertionError if an error message is not one short line.
    """
    where = "O3R XML-RPC fuzz:80 get(['/ports'])"
    last: Exception | None = None
    try:
        doc = parse_json_object(parse_rpc_reply(data, where), where)
        for check in (lambda: port_info(doc, "port2", host="fuzz", where=where),
                      lambda: port_info(doc, "port0", host="fuzz", where=where), lambda: firmware(doc, where)):
            try:
                check()
            except (ProtocolError, ConfigError) as exc:
                last = exc
    except (ProtocolError, VendorError) as exc:
        last = exc
    if last is not None:
        message = str(last)
        if "\n" in message or len(message) > 600:
            raise AssertionError(f"error message is not one short line: {message[:200]!r}...")
        raise last


def xmlrpc_target() -> Target:
    return Target("xmlrpc", (ProtocolError, VendorError, ConfigError), xmlrpc_seeds(), parse_xmlrpc, mutate_xmlrpc)


# ---------------------------------------------------------------------- TOML config
CONFIG_DIR = Path(str(resources.files("cellcal.configs")))


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)  # a JSON string is a valid TOML basic string
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{json.dumps(k)} = {_toml_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(f"cannot write {v!r} as TOML")


def dump_toml(doc: dict[str, Any]) -> str:
    """A TOML document for ``doc`` (top-level values first, then one ``[table]`` each)."""
    lines = [f"{json.dumps(k)} = {_toml_value(v)}" for k, v in doc.items() if not isinstance(v, dict)]
    for name, table in doc.items():
        if isinstance(table, dict):
            lines.append(f"[{json.dumps(name)}]")
            lines += [f"{json.dumps(k)} = {_toml_value(v)}" for k, v in table.items()]
    return "\n".join(lines) + "\n"


def config_seeds() -> list[bytes]:
    """Every packaged configuration."""
    return [p.read_bytes() for p in sorted(CONFIG_DIR.glob("*.toml"))]


#: Values a hand-edited file might hold where something else belongs.
ODD_VALUES: tuple[Any, ...] = (
    0, 1, -1, 3, 7, 4097, 10**9, -(10**9), 2**63 - 1, -(2**63), 0.0, -0.0, 0.5, -0.5, 1e-300, 1e300, math.inf,
    -math.inf, math.nan, True, False, "", "x", "sim", "o3r", "xarm", "ur", "oak", "software", "port2", "1.2.3",
    "\u00e9\u6f22", [], [0], [0.0, 0.0], [0.0, 0.0, 0.0], [1.0, 2.0, 3.0, 4.0], ["a"], [[1.0]], {}, {"a": 1},
    [{"xyz_m": [0.3, 0.0, 0.5]}], [{}],
)
TOML_TOKENS = (b"[", b"]", b"[[", b"]]", b"=", b"\"", b"'", b"\"\"\"", b"\n", b"#", b"{", b"}", b",", b".",
               b"nan", b"inf", b"-", b"+", b"1e999", b"0x", b"0o7", b"true", b"1979-05-27T07:32:00Z", b"\\u00",
               b"\x00", b"\xff", b" = [", b"[sim]\n", b"[[plan.poses]]\n")


def _paths(node: Any, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    out = [prefix] if prefix else []
    if isinstance(node, dict):
        for k, v in node.items():
            out += _paths(v, (*prefix, k))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            out += _paths(v, (*prefix, i))
    return out


def mutate_document(doc: dict[str, Any], rng: random.Random) -> dict[str, Any]:
    """1-4 structural edits: replace a value, delete it, add a key, wrap it in a list."""
    doc = copy.deepcopy(doc)
    for _ in range(rng.randint(1, 4)):
        paths = _paths(doc)
        if not paths:
            doc = {"x": rng.choice(ODD_VALUES)}
            continue
        path = rng.choice(paths)
        parent = doc
        for p in path[:-1]:
            parent = parent[p]
        last = path[-1]
        op = rng.choice(("replace", "replace", "delete", "add", "wrap"))
        if op == "replace":
            parent[last] = copy.deepcopy(rng.choice(ODD_VALUES))
        elif op == "delete":
            del parent[last]
        elif op == "add" and isinstance(parent, dict):
            parent[rng.choice(("extra", "backend", "seed", "mount", "x" * 40))] = copy.deepcopy(rng.choice(ODD_VALUES))
        elif op == "wrap":
            parent[last] = [parent[last]]
    return doc


def mutate_config(seed: bytes, rng: random.Random) -> bytes:
    """Structural edits of the parsed document, line edits, or byte/token edits of the text."""
    kind = rng.random()
    if kind < 0.45:
        return dump_toml(mutate_document(tomllib.loads(seed.decode("utf-8")), rng)).encode("utf-8")
    if kind < 0.7:
        lines = seed.split(b"\n")
        for _ in range(rng.randint(1, 3)):
            i = rng.randrange(len(lines))
            op = rng.choice(("delete", "dup", "swap", "token"))
            if op == "delete" and len(lines) > 1:
                del lines[i]
            elif op == "dup":
                lines.insert(i, lines[i])
            elif op == "swap":
                j = rng.randrange(len(lines))
                lines[i], lines[j] = lines[j], lines[i]
            else:
                pos = rng.randint(0, len(lines[i]))
                lines[i] = lines[i][:pos] + rng.choice(TOML_TOKENS) + lines[i][pos:]
        return b"\n".join(lines)
    buf = bytearray(mutate_bytes(seed, rng, max_ops=3))
    for _ in range(rng.randint(0, 3)):
        pos = rng.randint(0, len(buf))
        buf[pos:pos] = rng.choice(TOML_TOKENS)
    return bytes(buf)


def config_target(directory: Path | None = None) -> Target:
    """The loader reads a real file: inputs are written to ``directory`` (default: a temporary one)."""
    tmp = None
    if directory is None:
        shm = Path("/dev/shm")  # a file system in memory: rewriting the file is 4x faster than on disk
        tmp = tempfile.TemporaryDirectory(prefix="cellcal-fuzz-", dir=shm if shm.is_dir() else None)
        directory = Path(tmp.name)
    path = directory / "cell.toml"

    def run(data: bytes) -> None:
        path.write_bytes(data)
        build_devices(load_config(path))  # unconnected: nothing opens

    return Target("config", ConfigError, config_seeds(), run, mutate_config,
                  close=tmp.cleanup if tmp is not None else (lambda: None))


def all_targets() -> list[Target]:
    return [pcic_target(), xarm_target(), xmlrpc_target(), config_target(), rtde_target(), liveview_target()]
