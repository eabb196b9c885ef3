"""What every fuzz target shares: :class:`Target` and the byte mutations (``fuzz_targets`` names the targets)."""

from __future__ import annotations

import random
import struct
from collections.abc import Callable
from dataclasses import dataclass, field

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


