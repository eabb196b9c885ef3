"""The ChArUco board a configuration describes (``[handeye] charuco_*``), checked against the simulated one.

The detector looks for the board of ``[handeye]``; a simulated camera shows the board of
``[sim.charuco]`` (its own table, read here as plain document values: core never imports
the simulator). A board printed one way and looked for another is found in no view, so a
mismatch is refused before anything moves, naming both keys (ADR 0034).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from cellcal.core.calibration.config import CellConfig
from cellcal.core.handeye.charuco import BoardSpec
from cellcal.devices.errors import ConfigError

#: ``[sim.charuco]`` keys and the ``[handeye]`` key of the same board property.
SIM_BOARD_KEYS = {"squares": "charuco_squares", "square_m": "charuco_square_m",
                  "marker_ratio": "charuco_marker_ratio", "dictionary": "charuco_dictionary"}


def board_spec(config: CellConfig) -> BoardSpec:
    """The board of ``[handeye] charuco_*`` (checked against ``[sim.charuco]`` when there is one).

    Raises:
        ConfigError: If ``[sim.charuco]`` describes another board.
    """
    he = config.handeye
    spec = BoardSpec(tuple(he.charuco_squares), he.charuco_square_m, he.charuco_marker_ratio,  # type: ignore[arg-type]
                     he.charuco_dictionary)
    check_sim_board(config, spec)
    return spec


def sim_board(config: CellConfig) -> Mapping[str, Any] | None:
    """The ``[sim.charuco]`` table of the document, or None."""
    sim = config.document.get("sim")
    board = sim.get("charuco") if isinstance(sim, Mapping) else None
    return board if isinstance(board, Mapping) else None


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, float) or isinstance(b, float):
        return isinstance(a, (int, float)) and isinstance(b, (int, float)) and math.isclose(a, b, rel_tol=1e-9)
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return list(a) == list(b)
    return bool(a == b)


def check_sim_board(config: CellConfig, spec: BoardSpec) -> None:
    """Refuse a ``[sim.charuco]`` board that differs from ``spec`` (its defaults are :class:`BoardSpec`'s).

    Raises:
        ConfigError: Naming the first differing pair of keys and both values.
    """
    board = sim_board(config)
    if board is None:
        return
    default = BoardSpec()
    for key, he_key in SIM_BOARD_KEYS.items():
        shown, sought = board.get(key, getattr(default, key)), getattr(spec, key)
        if not _same(shown, sought):
            raise ConfigError(f"[sim.charuco] {key} = {_text(shown)} but [handeye] {he_key} = {_text(sought)}: the "
                              "simulated camera would show a board the detector does not look for; make them equal",
                              source=config.source, key=f"handeye.{he_key}")


def _text(value: Any) -> str:
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(str(v) for v in value) + "]"
    return f'"{value}"' if isinstance(value, str) else f"{value:g}" if isinstance(value, float) else str(value)


def missing_board_hint(config: CellConfig) -> str:
    """What to check when the board was found in too few views (one clause)."""
    spec = board_spec(config)
    what = (f"{spec.squares[0]}x{spec.squares[1]} squares of {1000 * spec.square_m:g} mm, "
            f"markers {spec.marker_ratio:g} of a square, DICT_{spec.dictionary}")
    if config.camera_section.get("backend") == "sim" and sim_board(config) is None:
        return (f"the simulated camera shows a board only with a [sim.charuco] table (the detector looks for {what}; "
                "see configs/sim_handeye.toml)")
    return (f"the detector looks for {what} ([handeye] charuco_*): is that board, printed at 100 % "
            "(`cellcal board`), flat where the plan looks?")


__all__ = ["SIM_BOARD_KEYS", "board_spec", "check_sim_board", "missing_board_hint", "sim_board"]
