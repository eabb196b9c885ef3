"""Fuzz targets shared by ``tests/integration/faults/test_fuzz_parsers.py`` (hypothesis, bounded, in CI) and
``benchmarks/fuzz_parsers.py`` (long seeded runs with counts).

A :class:`Target` is a parser, the one error it documents for bad input, valid seed
inputs, and a mutator ``(seed bytes, random.Random) -> bytes``. Feeding it anything
must either succeed or raise the documented error; any other exception is a defect.

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
import functools
import json
import math
import random
import socket
import struct
import tempfile
import threading
import tomllib
import xmlrpc.client
from collections.abc import Callable
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any
from unittest import mock

import numpy as np
from xarm_wire_helpers import decode_move_line, encode_reply, parse_request, request_splitter

from cellcal.core.calibration.calibrator import build_devices
from cellcal.core.calibration.config import load_config
from cellcal.core.liveview.subprotocol import LEGACY, SDK, rename_offer, rename_reply
from cellcal.devices.errors import (
    ConfigError,
    DeviceConnectionError,
    DeviceTimeoutError,
    ProtocolError,
    VendorError,
)
from cellcal.devices.geometry.camera_model import pixel_grid_rays
from cellcal.devices.types import Frame, Intrinsics
from cellcal.drivers.o3r.config_values import firmware, port_info
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
from cellcal.drivers.ur import rtde_probe
from cellcal.drivers.xarm.protocol import FrameSplitter, encode_request, parse_reply
from cellcal.drivers.xarm.registers import decode_serials, decode_text, unpack_floats
from cellcal.sims.o3r.encoder import FrameEncoder
from cellcal.sims.o3r.wire import message, models_from_intrinsics
from cellcal.sims.ur import rtde_wire

Mutator = Callable[[bytes, random.Random], bytes]


@dataclass
class Target:
    """One parser under fuzz.

    Attributes:
        name: Short name (``pcic``, ``xarm``, ``xmlrpc``, ``config``, ``rtde``, ``liveview``).
        documented: The error the parser documents for malformed input (``()``: none, it must not raise).
        seeds: Valid inputs the mutations start from.
        run: Parses one input; raises ``documented`` (or nothing).
        mutate: Makes a new input from a seed.
        close: Releases what ``run`` needs (temporary files).
    """

    name: str
    documented: type[Exception] | tuple[type[Exception], ...]
    seeds: list[bytes]
    run: Callable[[bytes], None]
    mutate: Mutator
    close: Callable[[], None] = field(default=lambda: None)

    @property
    def documented_names(self) -> str:
        """The documented error(s) by name, e.g. ``ProtocolError`` or ``ProtocolError/VendorError``; ``-`` if none."""
        kinds = self.documented if isinstance(self.documented, tuple) else (self.documented,)
        return "/".join(k.__name__ for k in kinds) or "-"

    def check(self, data: bytes) -> bool:
        """Run one input: True if it parsed, False if rejected with the documented error."""
        try:
            self.run(data)
        except self.documented:
            return False
        return True


# ---------------------------------------------------------------------- byte mutations
#: 32-bit values that break length/size/count fields.
INTERESTING_U32 = (0, 1, 2, 3, 35, 36, 47, 48, 255, 256, 65535, 65536, 0x7FFFFFFF, 0x80000000, 0xFFFFFFFF)


def mutate_bytes(seed: bytes, rng: random.Random, *, max_ops: int = 8) -> bytes:
    """1..max_ops random edits: flip, cut, insert, delete, overwrite a u32/u8, duplicate, truncate."""
    buf = bytearray(seed)
    for _ in range(rng.randint(1, max_ops)):
        op = rng.choice(("flip", "cut", "insert", "delete", "u32", "u8", "dup", "truncate"))
        pos = rng.randrange(len(buf)) if buf else 0
        if op == "flip" and buf:
            buf[pos] ^= rng.randint(1, 255)
        elif op == "cut":
            del buf[pos:pos + rng.randint(1, 64)]
        elif op == "insert":
            buf[pos:pos] = rng.randbytes(rng.randint(1, 16))
        elif op == "delete" and buf:
            del buf[pos]
        elif op == "u32" and pos + 4 <= len(buf):
            struct.pack_into("<I", buf, pos, rng.choice(INTERESTING_U32))
        elif op == "u8" and buf:
            buf[pos] = rng.choice((0, 1, 2, 0x7F, 0x80, 0xFF))
        elif op == "dup" and buf:
            end = min(len(buf), pos + rng.randint(1, 64))
            buf[end:end] = buf[pos:end]
        elif op == "truncate":
            del buf[rng.randint(0, len(buf)):]
    return bytes(buf)


def random_bytes(rng: random.Random, max_size: int = 600) -> bytes:
    return rng.randbytes(rng.randint(0, max_size))


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


# ---------------------------------------------------------------------- UR RTDE
#: The errors :func:`rtde_probe.probe_stream` documents; the controller-side wire parsers document the first only.
RTDE_ERRORS = (ProtocolError, DeviceConnectionError, DeviceTimeoutError)
#: The probe's time for one input, s: its peer always closes after the input, so only a stall would use it up.
RTDE_PROBE_TIMEOUT_S = 0.5
#: Inputs up to this size are written to the probe's peer before it starts (far below a socket pair's buffer);
#: larger ones by a thread while it reads.
_PREFILL_BYTES = 32 * 1024
#: Chunk sizes the controller-side reader is fed in, cycled: every header is split at every offset somewhere.
_PIECES = (1, 2, 3, 5, 8, 13, 21, 34, 55, 89, 144, 233, 377, 610, 987)
RTDE_TYPES = (rtde_wire.REQUEST_PROTOCOL_VERSION, rtde_wire.GET_URCONTROL_VERSION, rtde_wire.TEXT_MESSAGE,
              rtde_wire.DATA_PACKAGE, rtde_wire.CONTROL_PACKAGE_SETUP_OUTPUTS, rtde_wire.CONTROL_PACKAGE_SETUP_INPUTS,
              rtde_wire.CONTROL_PACKAGE_START, rtde_wire.CONTROL_PACKAGE_PAUSE)
#: An output and an input recipe with every RTDE type and a register of each bank.
RTDE_OUTPUTS = ("timestamp", "actual_q", "actual_TCP_pose", "robot_mode", "joint_mode", "actual_digital_input_bits",
                "elbow_position", "runtime_state", "tool_output_mode", "output_bit_register_64",
                "output_int_register_5", "output_double_register_47")
RTDE_INPUTS = ("input_double_register_0", "input_int_register_47", "input_bit_register_127", "speed_slider_mask",
               "standard_digital_output", "external_force_torque")
_RTDE_SAMPLES: dict[str, Any] = {
    "BOOL": True, "UINT8": 7, "UINT32": 4_000_000_000, "UINT64": 2**63 + 5, "INT32": -3, "DOUBLE": 0.25,
    "VECTOR3D": (1.0, -2.0, 3.5), "VECTOR6D": (0.1, -0.2, 0.3, -math.pi, 1e-9, 6.0),
    "VECTOR6INT32": (-1, 2, -3, 4, -(2**31), 2**31 - 1), "VECTOR6UINT32": (0, 1, 2, 3, 4, 2**32 - 1),
}
#: Recipe names for setup requests: valid ones of each kind, registers out of their bank, odd text, and
#: lists long enough that the controller's reply would not fit a message.
RTDE_NAME_TOKENS = (b"timestamp", b"actual_q", b"actual_TCP_pose", b"robot_mode", b"joint_mode", b"speed_slider_mask",
                    b"speed_slider_fraction", b"external_force_torque", b"input_int_register_0",
                    b"input_bit_register_64", b"output_bit_register_127", b"output_double_register_47",
                    b"input_int_register_48", b"input_bit_register_63", b"input_int_register_-1",
                    b"input_int_register_", b"input_int_register_007", b"output_int_register_" + b"1" * 4301,
                    b"input_double_register_" + b"0" * 5000, b"", b" ", b"  timestamp\t", b"\xff", b"\x00",
                    b"NOT_FOUND", b"IN_USE", b"x" * 5000, b"a," * 20000, b"timestamp," * 3000)
#: Output rates: in and out of the controller's range, and not numbers.
RTDE_FREQUENCIES = (125.0, 500.0, 500.0001, 0.0, -0.0, -1.0, 5e-324, 1e308, math.inf, -math.inf, math.nan)


def _rtde_recipe(names: tuple[str, ...], lookup: Callable[[str], str | None]) -> rtde_wire.Recipe:
    return rtde_wire.Recipe(1, names, tuple(lookup(n) or "" for n in names))


def rtde_seeds() -> list[bytes]:
    """Client streams as the controller reads them, and controller replies as the probe reads them.

    The client streams (as ur_rtde sends them): protocol version, controller version, an output
    and an input setup, start, input data packages, pause; and an output setup followed by data
    packages of that recipe. The reply streams: the probe's exchange, bare and with text
    messages, a version reply and data packages of another size in between.
    """
    w = rtde_wire
    outputs, inputs = _rtde_recipe(RTDE_OUTPUTS, w.output_type), _rtde_recipe(RTDE_INPUTS, w.input_type)
    out_body = outputs.pack([_RTDE_SAMPLES[t] for t in outputs.types])
    in_body = inputs.pack([_RTDE_SAMPLES[t] for t in inputs.types])
    output_setup = w.message(w.CONTROL_PACKAGE_SETUP_OUTPUTS,
                             struct.pack(">d", 125.0) + ",".join(RTDE_OUTPUTS).encode() + b",")
    client = (w.message(w.REQUEST_PROTOCOL_VERSION, struct.pack(">H", 2)) + w.message(w.GET_URCONTROL_VERSION)
              + output_setup + w.message(w.CONTROL_PACKAGE_SETUP_INPUTS, ", ".join(RTDE_INPUTS).encode())
              + w.message(w.CONTROL_PACKAGE_START) + w.data_package(1, in_body)
              + w.data_package(1, in_body[::-1]) + w.message(w.CONTROL_PACKAGE_PAUSE))
    stream = output_setup + w.data_package(1, out_body) + w.data_package(1, out_body) + w.message(w.TEXT_MESSAGE)
    timestamp = w.data_package(1, struct.pack(">d", 12.5))
    probe = (w.protocol_reply(True) + w.setup_reply(w.CONTROL_PACKAGE_SETUP_OUTPUTS, 1, ["DOUBLE"])
             + w.start_reply(True) + timestamp)
    chatty = (w.text_message("RTDE: hello") + w.protocol_reply(True) + w.text_message("", level=3)
              + w.setup_reply(w.CONTROL_PACKAGE_SETUP_OUTPUTS, 1, ["DOUBLE"]) + w.text_message("\u00e9" * 200)
              + w.start_reply(True) + w.version_reply(5, 11, 0, 0) + w.data_package(1, out_body) + timestamp)
    return [client, stream, probe, chatty]


def _feed_rtde(pieces: list[bytes]) -> tuple[list[tuple[int, bytes]], ProtocolError | None]:
    reader, messages = rtde_wire.FrameReader(), []
    try:
        for piece in pieces:
            messages += reader.feed(piece)
    except ProtocolError as exc:
        return messages, exc
    return messages, None


def frame_rtde(data: bytes) -> tuple[list[tuple[int, bytes]], bool]:
    """The oracle's framing: the whole messages, and whether a size field below the header comes first."""
    messages: list[tuple[int, bytes]] = []
    pos = 0
    while len(data) - pos >= rtde_wire.HEADER.size:
        size, msg_type = rtde_wire.HEADER.unpack_from(data, pos)
        if size < rtde_wire.HEADER.size:
            return messages, True
        if pos + size > len(data):
            break
        messages.append((msg_type, data[pos + rtde_wire.HEADER.size:pos + size]))
        pos += size
    return messages, False


def rtde_frames(data: bytes) -> list[tuple[int, bytes]]:
    """:class:`FrameReader` on the whole stream and in pieces, each checked against :func:`frame_rtde`.

    Raises:
        ProtocolError: From the reader (a size field smaller than the header).
        AssertionError: Either feed splits the stream otherwise, or raises where it should not
            (or does not where it should).
    """
    expected, bad = frame_rtde(data)
    whole, error = _feed_rtde([data])
    pieces: list[bytes] = []
    pos = 0
    while pos < len(data):
        size = _PIECES[len(pieces) % len(_PIECES)]
        pieces.append(data[pos:pos + size])
        pos += size
    pieced, pieced_error = _feed_rtde(pieces)
    agree = (error is not None) == bad == (pieced_error is not None) and pieced == expected[:len(pieced)]
    if not agree or (not bad and (whole, pieced) != (expected, expected)):
        raise AssertionError(f"FrameReader splits {data[:64].hex()}... otherwise than its size fields say")
    if error is not None:
        raise error
    return whole


def _check_unpack(recipe: rtde_wire.Recipe, body: bytes) -> None:
    values = recipe.unpack(body)
    one_to_one = len(set(recipe.names)) == len(recipe.names) and "BOOL" not in recipe.types  # any byte is a bool
    if one_to_one and recipe.pack(list(values.values())) != body:
        raise AssertionError(f"recipe {recipe.names} unpacks {body.hex()} to values that pack differently")


def parse_rtde_requests(data: bytes) -> None:
    """What the emulated controller does with a client's stream (minus the socket and its state).

    Frames the stream (:func:`rtde_frames`), parses each request, builds the reply to a setup,
    makes a recipe of a setup whose names all exist, and unpacks the data packages of those
    recipes (input recipes first, as the controller; output recipes as a client would).

    Raises:
        ProtocolError: A malformed message, or a reply too large for one message.
    """
    w = rtde_wire
    recipes: dict[int, dict[int, rtde_wire.Recipe]] = {w.CONTROL_PACKAGE_SETUP_INPUTS: {},
                                                       w.CONTROL_PACKAGE_SETUP_OUTPUTS: {}}
    for msg_type, payload in rtde_frames(data):
        if msg_type == w.REQUEST_PROTOCOL_VERSION:
            w.parse_protocol_request(payload)
        elif msg_type in recipes:
            if msg_type == w.CONTROL_PACKAGE_SETUP_OUTPUTS:
                freq, names = w.parse_output_setup(payload)
                types = [w.output_type(n) or w.NOT_FOUND for n in names]
            else:
                freq, names = 0.0, w.parse_input_setup(payload)
                types = [w.input_type(n) or w.NOT_FOUND for n in names]
            table = recipes[msg_type]
            recipe_id = len(table) + 1
            w.setup_reply(msg_type, recipe_id, types)
            if w.NOT_FOUND not in types:
                table[recipe_id] = w.Recipe(recipe_id, names, tuple(types), freq)
        elif msg_type == w.DATA_PACKAGE and payload:
            recipe = (recipes[w.CONTROL_PACKAGE_SETUP_INPUTS].get(payload[0])
                      or recipes[w.CONTROL_PACKAGE_SETUP_OUTPUTS].get(payload[0]))
            if recipe is not None:
                _check_unpack(recipe, payload[1:])


def _send(peer: socket.socket, data: bytes, close: bool) -> None:
    with contextlib.suppress(OSError):  # the probe may stop reading (and close) before the end
        peer.sendall(data)
        if close:
            peer.shutdown(socket.SHUT_WR)


def probe_rtde_replies(data: bytes, *, timeout: float = RTDE_PROBE_TIMEOUT_S, close: bool = True) -> float:
    """:func:`probe_stream` against a peer that sends ``data``, then closes (or, ``close=False``, stays silent).

    The peer is one end of a socket pair handed to the probe in place of its TCP connection.

    Returns:
        The timestamp of the first data package.

    Raises:
        ProtocolError, DeviceConnectionError, DeviceTimeoutError: As :func:`probe_stream` documents.
    """
    ours, peer = socket.socketpair()
    writer = None
    try:
        if len(data) <= _PREFILL_BYTES:
            _send(peer, data, close)
        else:
            writer = threading.Thread(target=_send, args=(peer, data, close), daemon=True)
            writer.start()
        with mock.patch.object(rtde_probe, "open_port", lambda *_: ours):
            return rtde_probe.probe_stream("fuzz", timeout)
    finally:
        ours.close()
        if writer is not None:
            writer.join()
        peer.close()


def parse_rtde(data: bytes) -> None:
    """Both directions: the controller reading a client's stream, the probe reading a controller's replies.

    Raises:
        ProtocolError, DeviceConnectionError, DeviceTimeoutError: The probe's error, if neither
            reading accepts the stream.
        AssertionError: The controller-side parsers raised an error only the probe documents.
    """
    try:
        parse_rtde_requests(data)
    except ProtocolError:
        probe_rtde_replies(data)  # the documented error if it is no reply stream either
        return
    except (DeviceConnectionError, DeviceTimeoutError) as exc:
        raise AssertionError(f"the controller-side RTDE parsers raised {exc!r}") from exc
    with contextlib.suppress(*RTDE_ERRORS):
        probe_rtde_replies(data)


def split_rtde(stream: bytes) -> list[bytes]:
    """A stream's messages as bytes, by their size fields (one below the header taken as the header); the tail."""
    out: list[bytes] = []
    pos = 0
    while pos + 3 <= len(stream):
        size = max(3, struct.unpack_from(">H", stream, pos)[0])
        out.append(stream[pos:pos + size])
        pos += size
    if pos < len(stream):
        out.append(stream[pos:])
    return out


@functools.cache
def _rtde_seed_messages() -> tuple[bytes, ...]:
    return tuple(m for seed in rtde_seeds() for m in split_rtde(seed))


def _mutate_setup(msg: bytes, rng: random.Random) -> bytes:
    """A setup request with 1-3 names replaced, added, deleted or repeated, and (outputs) another rate."""
    msg_type = rng.choice((rtde_wire.CONTROL_PACKAGE_SETUP_OUTPUTS, rtde_wire.CONTROL_PACKAGE_SETUP_INPUTS))
    payload = msg[3:] if len(msg) >= 3 and msg[2] == msg_type else b""
    head = b""
    if msg_type == rtde_wire.CONTROL_PACKAGE_SETUP_OUTPUTS:
        head, payload = (payload[:8], payload[8:]) if len(payload) >= 8 else (struct.pack(">d", 125.0), payload)
        if rng.random() < 0.3:
            head = struct.pack(">d", rng.choice(RTDE_FREQUENCIES))
    names = payload.split(b",")
    for _ in range(rng.randint(1, 3)):
        i = rng.randrange(len(names))
        op = rng.choice(("replace", "insert", "delete", "repeat"))
        if op == "replace":
            names[i] = rng.choice(RTDE_NAME_TOKENS)
        elif op == "insert":
            names.insert(i, rng.choice(RTDE_NAME_TOKENS))
        elif op == "delete" and len(names) > 1:
            del names[i]
        elif op == "repeat":
            names[i:i] = [names[i]] * rng.randint(1, 500)
    body = head + b",".join(names)
    return rtde_wire.message(msg_type, body[:rtde_wire.MAX_MESSAGE_BYTES - rtde_wire.HEADER.size])


def mutate_rtde(seed: bytes, rng: random.Random) -> bytes:
    """1-3 message edits, then sometimes byte edits; or random bytes, bare or framed.

    Message edits: a size field set to 0, 1, 2, 3, the true size -/+ 1, 0xFFFF or anything; a
    payload edited (framed again with its true size); a type changed; the names and rate of a
    setup edited; messages of other seeds spliced in, one repeated, dropped or swapped.
    """
    kind = rng.random()
    if kind < 0.04:
        return random_bytes(rng, 200)
    if kind < 0.08:
        return rtde_wire.message(rng.choice(RTDE_TYPES), random_bytes(rng, 120))
    msgs = split_rtde(seed) or [rng.choice(_rtde_seed_messages())]
    for _ in range(rng.randint(1, 3)):
        i = rng.randrange(len(msgs))
        msg = msgs[i]
        op = rng.choice(("size", "size", "payload", "payload", "type", "setup", "setup", "splice", "repeat", "drop",
                         "swap"))
        if op == "size" and len(msg) >= 3:
            size = rng.choice((0, 1, 2, 3, len(msg) - 1, len(msg) + 1, 0xFFFF, rng.randrange(0x10000)))
            msgs[i] = struct.pack(">H", min(size, 0xFFFF)) + msg[2:]
        elif op == "payload" and len(msg) >= 3:
            payload = mutate_bytes(msg[3:], rng, max_ops=3)[:rtde_wire.MAX_MESSAGE_BYTES - 3]
            msgs[i] = rtde_wire.message(msg[2], payload)
        elif op == "type" and len(msg) >= 3:
            msgs[i] = msg[:2] + bytes([rng.choice((*RTDE_TYPES, 0, 0xFF, rng.randrange(256)))]) + msg[3:]
        elif op == "setup":
            msgs[i] = _mutate_setup(msg, rng)
        elif op == "splice":
            msgs[i:i] = rng.choices(_rtde_seed_messages(), k=rng.randint(1, 4))
        elif op == "repeat":
            msgs[i:i] = [msg] * min(rng.randint(1, 40), 128 * 1024 // max(1, len(msg)))
        elif op == "drop" and len(msgs) > 1:
            del msgs[i]
        elif op == "swap":
            j = rng.randrange(len(msgs))
            msgs[i], msgs[j] = msgs[j], msgs[i]
    stream = b"".join(msgs)
    return mutate_bytes(stream, rng, max_ops=3) if rng.random() < 0.3 else stream


def rtde_target() -> Target:
    return Target("rtde", RTDE_ERRORS, rtde_seeds(), parse_rtde, mutate_rtde)


# ---------------------------------------------------------------------- live-view subprotocol relay
_PROTOCOL_HEADER = b"sec-websocket-protocol:"
_UPGRADE = (b"GET / HTTP/1.1\r\nHost: 127.0.0.1:8765\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
            b"Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n%s\r\n")
#: Fragments that break header lines, names, separators and encodings.
LIVEVIEW_TOKENS = (LEGACY, SDK, b"FOXGLOVE.WEBSOCKET.V1", LEGACY + b"\x00", b" " + LEGACY + b" ", b",", b", ,",
                   b"\r\n", b"\n", b"\r", b"\r\n\r\n", b"\n\r", b":", b" ", b"\t", b"\x0b", b"\x0c", b"\x00",
                   b"\xff", b"\x80", b"\xc3\xa9", b"Sec-WebSocket-Protocol:", b"sec-websocket-protocol: ",
                   b"\r\nSEC-WEBSOCKET-PROTOCOL:" + LEGACY, b"\r\nSec-WebSocket-Protocol : " + LEGACY,
                   b"\r\n Sec-WebSocket-Protocol: " + LEGACY)
#: Header values far longer than the relay reads (it stops at 16 KiB; the functions take anything).
LIVEVIEW_HUGE = (b"x" * 70000, b", " * 20000 + LEGACY, (b"," + LEGACY) * 3000, b" " * 20000 + LEGACY,
                 b"\xff" * 30000)


def liveview_seeds() -> list[bytes]:
    """Upgrade requests offering the legacy name, the SDK's, both, neither, with odd case and space; replies."""
    offers = (b"Sec-WebSocket-Protocol: foxglove.websocket.v1\r\n", b"Sec-WebSocket-Protocol: foxglove.sdk.v1\r\n",
              b"Sec-WebSocket-Protocol: foxglove.sdk.v1, foxglove.websocket.v1\r\n", b"",
              b"sec-websocket-protocol:foxglove.websocket.v1 ,  x.v2\r\n",
              b"SEC-WEBSOCKET-PROTOCOL:\t foxglove.websocket.v1\t\r\n",
              b"Sec-WebSocket-Protocol: x.v2\r\nSec-WebSocket-Protocol: foxglove.websocket.v1\r\n")
    replies = (b"HTTP/1.1 101 Switching Protocols\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
               b"Sec-WebSocket-Accept: s3pPLMBiTxaQ9kYGzzhZRbK+xOo=\r\nSec-WebSocket-Protocol: foxglove.sdk.v1\r\n\r\n",
               b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\n\r\n")
    return [_UPGRADE % offer for offer in offers] + list(replies)


def _is_protocol_line(line: bytes) -> bool:
    return line.lower().startswith(_PROTOCOL_HEADER)


def offered_protocols(lines: list[bytes]) -> list[bytes]:
    """The subprotocols header lines offer: the comma-separated values of every ``Sec-WebSocket-Protocol``."""
    return [p.strip() for line in lines if _is_protocol_line(line) for p in line[len(_PROTOCOL_HEADER):].split(b",")]


def parse_liveview(data: bytes) -> None:
    """Both handshake renames on the same bytes, each checked against what the module promises.

    Neither function documents an error: any bytes give bytes. A request is renamed exactly
    when it offers ``foxglove.websocket.v1`` and not ``foxglove.sdk.v1``, and then only its
    ``Sec-WebSocket-Protocol`` lines change, offering the same list with the legacy name
    replaced; otherwise it is returned unchanged. A reply changes only where such a line names
    ``foxglove.sdk.v1`` alone. Both are idempotent.

    Raises:
        AssertionError: Where a result breaks one of those promises.
    """
    lines = data.split(b"\r\n")
    offered = offered_protocols(lines)
    request, renamed = rename_offer(data)
    if not isinstance(request, bytes) or not isinstance(renamed, bool):
        raise AssertionError(f"rename_offer returned {type(request).__name__}, {type(renamed).__name__}")
    if renamed != (LEGACY in offered and SDK not in offered):
        raise AssertionError(f"rename_offer renamed={renamed} for the offers {offered[:8]}")
    new = request.split(b"\r\n")
    if not renamed and request != data:
        raise AssertionError("rename_offer changed a request it did not rename")
    if renamed and (len(new) != len(lines)
                    or any(a != b for a, b in zip(lines, new, strict=False) if not _is_protocol_line(a))
                    or offered_protocols(new) != [SDK if p == LEGACY else p for p in offered]
                    or rename_offer(request) != (request, False)):
        raise AssertionError(f"rename_offer renamed {data[:200]!r}... to {request[:200]!r}...")
    reply = rename_reply(data)
    if not isinstance(reply, bytes):
        raise AssertionError(f"rename_reply returned {type(reply).__name__}")
    expected = [line[:len(_PROTOCOL_HEADER)] + b" " + LEGACY
                if _is_protocol_line(line) and line[len(_PROTOCOL_HEADER):].strip() == SDK else line for line in lines]
    if reply.split(b"\r\n") != expected or rename_reply(reply) != reply:
        raise AssertionError(f"rename_reply renamed {data[:200]!r}... to {reply[:200]!r}...")


def mutate_liveview(seed: bytes, rng: random.Random) -> bytes:
    """1-4 line edits, then sometimes a truncation; or random bytes.

    Line edits: a line (the protocol header more often) duplicated, a huge value appended, a
    token inserted (names, separators, CR/LF alone, non-ASCII bytes), a line joined to the next
    with a bare LF or CR, its case changed, byte edits, lines deleted, swapped or spliced from
    another seed.
    """
    if rng.random() < 0.04:
        return random_bytes(rng, 400)
    lines = seed.split(b"\r\n")
    for _ in range(rng.randint(1, 4)):
        protocol = [i for i, line in enumerate(lines) if _is_protocol_line(line)]
        i = rng.choice(protocol) if protocol and rng.random() < 0.5 else rng.randrange(len(lines))
        op = rng.choice(("dup", "dup", "huge", "token", "token", "token", "join", "case", "bytes", "delete", "swap",
                         "splice"))
        if op == "dup":
            lines[i:i] = [lines[i]] * rng.randint(1, 3)
        elif op == "huge":
            lines[i] += rng.choice(LIVEVIEW_HUGE)
        elif op == "token":
            pos = rng.randint(0, len(lines[i]))
            lines[i] = lines[i][:pos] + rng.choice(LIVEVIEW_TOKENS) + lines[i][pos:]
        elif op == "join" and i + 1 < len(lines):
            lines[i:i + 2] = [lines[i] + rng.choice((b"\n", b"\r", b"\n\r", b"\r\r\n")) + lines[i + 1]]
        elif op == "case":
            lines[i] = rng.choice((bytes.upper, bytes.lower, bytes.swapcase, bytes.title))(lines[i])
        elif op == "bytes":
            lines[i] = mutate_bytes(lines[i], rng, max_ops=2)
        elif op == "delete" and len(lines) > 1:
            del lines[i]
        elif op == "swap":
            j = rng.randrange(len(lines))
            lines[i], lines[j] = lines[j], lines[i]
        elif op == "splice":
            other = rng.choice(liveview_seeds()).split(b"\r\n")
            start = rng.randrange(len(other))
            lines[i:i] = other[start:start + rng.randint(1, 3)]
    data = b"\r\n".join(lines)
    return data[:rng.randint(0, len(data))] if rng.random() < 0.15 else data


def liveview_target() -> Target:
    return Target("liveview", (), liveview_seeds(), parse_liveview, mutate_liveview)


def all_targets() -> list[Target]:
    return [pcic_target(), xarm_target(), xmlrpc_target(), config_target(), rtde_target(), liveview_target()]
