"""Long seeded fuzz run of the PCIC, xArm, O3R XML-RPC/JSON, TOML-config, UR RTDE and live-view handshake parsers.

The same targets and mutators as ``tests/integration/faults/test_fuzz_parsers.py`` (``tests/support/fuzz_targets.py``):
every input must parse or raise the parser's documented error (``ProtocolError``;
``ProtocolError``/``VendorError``/``ConfigError`` for the O3R configuration; ``ConfigError``;
``ProtocolError``/``DeviceConnectionError``/``DeviceTimeoutError`` for RTDE, whose probe reads
from a socket pair; none for the live-view subprotocol renames, which must take any bytes).
Prints, per parser, how many inputs it got, how many parsed, how many were rejected with
the documented error, how many raised anything else (the first such input is saved to
``--out`` with its traceback) and how many emitted a Python warning (e.g. a numpy
overflow; also saved, first one only). Exit status 1 if any input raised an undocumented
exception.

    python benchmarks/fuzz_parsers.py --seconds 60 [--seed 1] [--out fuzz-failures]
    python benchmarks/fuzz_parsers.py --count 100000 --targets pcic xarm xmlrpc
    python benchmarks/fuzz_parsers.py --count 100000 --targets rtde liveview
"""

from __future__ import annotations

import argparse
import random
import sys
import time
import traceback
import warnings
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests" / "support"))

from fuzz_base import Target
from fuzz_liveview import liveview_target
from fuzz_rtde import rtde_target
from fuzz_targets import config_target, pcic_target, xarm_target, xmlrpc_target

FACTORIES = {"pcic": pcic_target, "xarm": xarm_target, "xmlrpc": xmlrpc_target, "config": config_target,
             "rtde": rtde_target, "liveview": liveview_target}


@dataclass
class Tally:
    """Counts for one target."""

    inputs: int = 0
    parsed: int = 0
    rejected: int = 0
    other: int = 0
    warned: int = 0
    seconds: float = 0.0


def _save(out: Path, name: str, kind: str, data: bytes, text: str) -> Path:
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"{name}-{kind}.bin"
    path.write_bytes(data)
    path.with_suffix(".txt").write_text(text, encoding="utf-8")
    return path


def fuzz(target: Target, rng: random.Random, *, seconds: float | None, count: int | None, out: Path) -> Tally:
    """Run one target until the time or the count is used up."""
    tally = Tally()
    start = time.perf_counter()
    deadline = start + seconds if seconds is not None else float("inf")
    while (count is None or tally.inputs < count) and time.perf_counter() < deadline:
        data = target.mutate(rng.choice(target.seeds), rng)
        tally.inputs += 1
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                ok = target.check(data)
            except Exception:  # counting exactly these is the point
                tally.other += 1
                if tally.other == 1:
                    path = _save(out, target.name, "failure", data, traceback.format_exc())
                    print(f"  {target.name}: undocumented exception, input saved to {path}", file=sys.stderr)
                continue
        tally.parsed += ok
        tally.rejected += not ok
        if caught:
            tally.warned += 1
            if tally.warned == 1:
                text = "\n".join(f"{w.category.__name__}: {w.message} ({w.filename}:{w.lineno})" for w in caught)
                path = _save(out, target.name, "warning", data, text)
                print(f"  {target.name}: warning ({text.splitlines()[0]}), input saved to {path}", file=sys.stderr)
    tally.seconds = time.perf_counter() - start
    return tally


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    budget = parser.add_mutually_exclusive_group()
    budget.add_argument("--seconds", type=float, default=60.0, help="total wall time, split evenly (default 60)")
    budget.add_argument("--count", type=int, help="inputs per parser (instead of --seconds)")
    parser.add_argument("--seed", type=int, default=1, help="random seed (default 1)")
    parser.add_argument("--targets", nargs="+", choices=sorted(FACTORIES), default=list(FACTORIES))
    parser.add_argument("--out", type=Path, default=Path("fuzz-failures"), help="where failing inputs go")
    args = parser.parse_args(argv)
    per_target = None if args.count is not None else args.seconds / len(args.targets)
    print(f"fuzz: seed {args.seed}, " + (f"{args.count} inputs per parser" if args.count is not None
                                        else f"{per_target:.1f} s per parser"))
    print(f"{'parser':<8} {'documented error':<54} {'inputs':>9} {'parsed':>8} {'rejected':>9} {'other':>6} "
          f"{'warned':>7} {'inputs/s':>9}")
    failed = False
    for i, name in enumerate(args.targets):
        target = FACTORIES[name]()
        try:
            t = fuzz(target, random.Random(args.seed * 1000 + i), seconds=per_target, count=args.count,
                     out=args.out)
        finally:
            target.close()
        failed |= t.other > 0
        print(f"{name:<8} {target.documented_names:<54} {t.inputs:>9} {t.parsed:>8} {t.rejected:>9} "
              f"{t.other:>6} {t.warned:>7} {t.inputs / t.seconds:>9.0f}")
    print("FAIL: undocumented exceptions (inputs saved)" if failed else "OK: 0 undocumented exceptions")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
