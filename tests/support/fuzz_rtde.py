"""The UR RTDE fuzz target, both ways (``fuzz_targets`` describes it)."""

from __future__ import annotations

import contextlib
import functools
import math
import random
import socket
import struct
import threading
from collections.abc import Callable
from typing import Any
from unittest import mock

from fuzz_base import Target, mutate_bytes, random_bytes

from cellcal.devices.errors import (
    DeviceConnectionError,
    DeviceTimeoutError,
    ProtocolError,
)
from cellcal.drivers.ur import rtde_probe
from cellcal.sims.ur import rtde_wire

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
