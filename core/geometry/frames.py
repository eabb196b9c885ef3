"""Closed frame chains: ``Z T6 E = B G`` solved for any one unknown.

``T_a_b`` maps frame-*b* coordinates into frame *a*; ``T_a_c = T_a_b @ T_b_c``
(ADR 0002).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import reduce

from cellcal.devices.errors import CalibrationError
from cellcal.devices.pose import Pose

__all__ = ["FrameChain"]


@dataclass(frozen=True)
class _Term:
    name: str
    inverse: bool

    @classmethod
    def parse(cls, token: str) -> _Term:
        tok = token.strip()
        inverse = False
        for suffix in ("^-1", "^{-1}", "⁻¹"):
            if tok.endswith(suffix):
                tok, inverse = tok[: -len(suffix)].strip(), True
                break
        if not tok or not (tok.replace("_", "a").isalnum()):
            raise CalibrationError(f"bad transform name {token!r} in frame chain")
        return cls(tok, inverse)

    def value(self, known: Mapping[str, Pose]) -> Pose:
        p = known[self.name]
        return p.inv() if self.inverse else p

    def __str__(self) -> str:
        return f"{self.name}^-1" if self.inverse else self.name


def _product(poses: Sequence[Pose]) -> Pose:
    return reduce(lambda a, b: a @ b, poses, Pose.identity())


class FrameChain:
    """A closed loop of named transforms, ``lhs[0] @ lhs[1] ... == rhs[0] @ ...``.

    A name may carry ``^-1`` to use its inverse (e.g. ``"P = I C"`` or
    ``"C = I^-1 P"``). Each name may occur once in the chain.

    Example:
        >>> chain = FrameChain.parse("Z T6 E = B G")
        >>> name, t6 = chain.solve({"Z": z, "E": e, "B": b, "G": g})  # doctest: +SKIP
        >>> b = chain.solve_for("B", Z=z, T6=t6, E=e, G=g)  # doctest: +SKIP

    Args:
        lhs: Names on the left-hand side, in multiplication order.
        rhs: Names on the right-hand side (may be empty: identity).

    Raises:
        CalibrationError: On a malformed or repeated name, or an empty chain.
    """

    def __init__(self, lhs: Sequence[str], rhs: Sequence[str] = ()):
        if isinstance(lhs, str) or isinstance(rhs, str):
            raise CalibrationError("FrameChain sides must be lists of names (use FrameChain.parse)")
        self.lhs = tuple(_Term.parse(t) for t in lhs)
        self.rhs = tuple(_Term.parse(t) for t in rhs)
        if not self.lhs and not self.rhs:
            raise CalibrationError("frame chain is empty")
        names = [t.name for t in self.lhs + self.rhs]
        dupes = sorted({n for n in names if names.count(n) > 1})
        if dupes:
            raise CalibrationError(f"frame chain uses {', '.join(dupes)} more than once")

    @classmethod
    def parse(cls, text: str) -> FrameChain:
        """Parse ``"Z T6 E = B G"`` (names separated by spaces or ``*``/``@``/``·``)."""
        if text.count("=") != 1:
            raise CalibrationError(f"frame chain must contain exactly one '=': {text!r}")
        left, right = text.split("=")

        def tokens(side: str) -> list[str]:
            for sep in ("*", "@", "·"):
                side = side.replace(sep, " ")
            return side.split()

        return cls(tokens(left), tokens(right))

    @property
    def names(self) -> tuple[str, ...]:
        """All transform names, left side first."""
        return tuple(t.name for t in self.lhs + self.rhs)

    def __str__(self) -> str:
        def side(ts: Sequence[_Term]) -> str:
            return " ".join(str(t) for t in ts) or "I"

        return f"{side(self.lhs)} = {side(self.rhs)}"

    def __repr__(self) -> str:
        return f"FrameChain.parse({str(self)!r})"

    def _check_known(self, known: Mapping[str, Pose]) -> None:
        extra = sorted(set(known) - set(self.names))
        if extra:
            raise CalibrationError(f"{', '.join(extra)} not in frame chain '{self}'")
        for k, v in known.items():
            if not isinstance(v, Pose):
                raise CalibrationError(f"transform {k} must be a Pose, got {type(v).__name__}")

    def solve(self, known: Mapping[str, Pose]) -> tuple[str, Pose]:
        """Solve for the one name not in ``known``.

        Returns:
            ``(name, pose)`` of the unknown transform.

        Raises:
            CalibrationError: If zero or more than one name is unknown, or ``known``
                holds a name that is not in the chain.
        """
        self._check_known(known)
        unknown = [n for n in self.names if n not in known]
        if len(unknown) != 1:
            what = "no unknown" if not unknown else f"{len(unknown)} unknowns ({', '.join(unknown)})"
            raise CalibrationError(f"frame chain '{self}' has {what}; exactly one is needed")
        name = unknown[0]
        # Move the unknown's side so it reads  A @ X @ B = C
        if name in (t.name for t in self.lhs):
            side, other = self.lhs, self.rhs
        else:
            side, other = self.rhs, self.lhs
        i = next(k for k, t in enumerate(side) if t.name == name)
        before = _product([t.value(known) for t in side[:i]])
        after = _product([t.value(known) for t in side[i + 1:]])
        target = _product([t.value(known) for t in other])
        x = before.inv() @ target @ after.inv()
        return name, (x.inv() if side[i].inverse else x)

    def solve_for(self, name: str, known: Mapping[str, Pose] | None = None, **more: Pose) -> Pose:
        """Solve for ``name`` given every other transform (as a mapping and/or keywords).

        Raises:
            CalibrationError: If ``name`` is not in the chain or a transform is missing.
        """
        if name not in self.names:
            raise CalibrationError(f"{name} is not in frame chain '{self}'")
        given = {**(known or {}), **more}
        if name in given:
            raise CalibrationError(f"{name} is the unknown but was also given")
        missing = [n for n in self.names if n != name and n not in given]
        if missing:
            raise CalibrationError(f"cannot solve '{self}' for {name}: {', '.join(missing)} missing")
        return self.solve(given)[1]

    def residual(self, known: Mapping[str, Pose]) -> Pose:
        """``(lhs)^-1 @ (rhs)`` with every transform known: identity when the loop closes."""
        self._check_known(known)
        missing = [n for n in self.names if n not in known]
        if missing:
            raise CalibrationError(f"residual of '{self}' needs {', '.join(missing)}")
        left = _product([t.value(known) for t in self.lhs])
        right = _product([t.value(known) for t in self.rhs])
        return left.inv() @ right
