"""The live-view relay's handshake fuzz target (``fuzz_targets`` describes it)."""

from __future__ import annotations

import random

from fuzz_base import Target, mutate_bytes, random_bytes

from cellcal.core.liveview.subprotocol import LEGACY, SDK, rename_offer, rename_reply

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
