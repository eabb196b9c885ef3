"""The study's design: methods, the paper's setting, the targets, the conditions and settings.

Plain Python (no numpy): ``cellcal study``'s options are built from these names without
loading the trials' numerics (ADR 0021).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from cellcal.devices.errors import CalibrationError

__all__ = [
    "ARTEFACT_LEVELS",
    "ARTEFACT_TABLES",
    "BASE_ARTEFACTS",
    "FULL_FRAME",
    "GRID_METHODS",
    "METHODS",
    "PAPER_HEIGHTS_M",
    "PAPER_INCLINATION_DEG",
    "PAPER_PERIMETERS_PX",
    "TARGET_CLUTTER",
    "TARGET_COVERAGE",
    "TARGET_COVERAGE_CLUTTER",
    "TARGET_ERROR_CLUTTER_DEG",
    "TARGET_ERROR_DEG",
    "Condition",
    "StudySettings",
    "quick_settings",
]

#: The methods in the study's order: the paper's three on the grid, then the full frame.
GRID_METHODS: tuple[str, ...] = ("law_of_cosines", "plane_fit_nominal", "plane_fit")
FULL_FRAME = "full_frame"
METHODS: tuple[str, ...] = (*GRID_METHODS, FULL_FRAME)

#: The paper's experiment: three heights along the optical axis, 80 deg inclination.
PAPER_HEIGHTS_M: tuple[float, ...] = (0.46, 0.59, 0.61)
PAPER_INCLINATION_DEG = 80.0
PAPER_PERIMETERS_PX: tuple[int, ...] = (20, 30, 40, 50)
#: The issues' targets for the full-frame method at the paper's settings (mean |tilt error|:
#: 0.05 deg in the first study, 0.01 deg once the sim has the ToF artefacts, issue 15).
TARGET_ERROR_DEG = 0.01
TARGET_ERROR_CLUTTER_DEG = 0.1
TARGET_CLUTTER = 0.3
TARGET_COVERAGE = (0.93, 0.97)
#: Clutter range over which the interval coverage must hold (issue 15).
TARGET_COVERAGE_CLUTTER = (0.0, 0.4)

#: The ToF artefact levels of the study: the ``[sim.artefacts]`` table of each (ADR 0014).
ARTEFACT_TABLES: dict[str, dict[str, bool]] = {
    "off": {"mixed_pixels": False, "multipath": False, "amplitude_noise": False, "temperature_drift": False},
    "all-but-multipath": {"multipath": False},
    "all": {},
}
ARTEFACT_LEVELS: tuple[str, ...] = tuple(ARTEFACT_TABLES)
#: The level of the inclination and noise sweeps and of the headline figures.
BASE_ARTEFACTS = "all-but-multipath"


# ---------------------------------------------------------------------- settings
@dataclass(frozen=True)
class Condition:
    """One cell of the study's design.

    Attributes:
        height_m: Camera-to-plane distance along the optical axis, metres.
        inclination_deg: Angle between optical axis and plane, degrees (90 = looking straight down).
        noise_scale: Multiplier of the simulated camera's distance noise (1 = default).
        clutter: Requested fraction of the image's plane pixels hidden by boxes, 0..1.
        artefacts: ToF artefact level, a key of :data:`ARTEFACT_TABLES`.
    """

    height_m: float
    inclination_deg: float
    noise_scale: float
    clutter: float
    artefacts: str = BASE_ARTEFACTS

    def key(self) -> str:
        """Stable text key without the artefact level: seeds a condition's trials, so that the
        levels of one condition see the same poses, boxes and noise draws (paired trials)."""
        return f"{self.height_m:.4f}|{self.inclination_deg:.3f}|{self.noise_scale:.3f}|{self.clutter:.3f}"

    def ident(self) -> str:
        """Key with the artefact level (tells conditions apart)."""
        return f"{self.key()}|{self.artefacts}"


@dataclass(frozen=True)
class StudySettings:
    """What the study runs.

    The design is one factor at a time around the paper's setting, each at every
    height: clutter levels at every artefact level (paper inclination, default noise),
    inclinations (no clutter, default noise) and noise scales (no clutter, paper
    inclination), these two at ``base_artefacts``.

    Attributes:
        trials: Trials per condition.
        seed: Root seed.
        heights_m: Heights along the optical axis, metres.
        inclinations_deg: Inclinations of the optical axis to the plane, degrees.
        noise_scales: Noise multipliers of the simulated camera.
        clutter_fractions: Requested fractions of the plane pixels hidden by boxes.
        artefact_levels: ToF artefact levels of the clutter sweep (keys of :data:`ARTEFACT_TABLES`).
        base_artefacts: Artefact level of the other sweeps and of the headline figures.
        perimeters_px: Perimeters of the paper's methods, pixels.
        window_px: Sampling window of the paper's methods, pixels (odd).
        max_boxes: At most this many boxes per cluttered trial (at least 1).
        box_height_m: Range of box heights, metres.
        target_m: Plane point the optical axis hits, base frame, metres.
        camera: Extra keys for the ``sim`` camera section (e.g. ``{"distortion": False}``).
        full_frame: Keyword arguments for ``FullFrameSettings`` (empty: its defaults).
        headline_factor: The headline conditions (paper inclination, default noise,
            no clutter and 30 % clutter) run this many times ``trials``, to pin the
            interval coverage down.
    """

    trials: int = 50
    seed: int = 0
    heights_m: tuple[float, ...] = PAPER_HEIGHTS_M
    inclinations_deg: tuple[float, ...] = (60.0, 70.0, PAPER_INCLINATION_DEG, 85.0)
    noise_scales: tuple[float, ...] = (0.5, 1.0, 2.0, 4.0)
    clutter_fractions: tuple[float, ...] = (0.0, 0.1, 0.2, 0.3, 0.4)
    artefact_levels: tuple[str, ...] = ARTEFACT_LEVELS
    base_artefacts: str = BASE_ARTEFACTS
    perimeters_px: tuple[int, ...] = PAPER_PERIMETERS_PX
    window_px: int = 3
    max_boxes: int = 3
    box_height_m: tuple[float, float] = (0.03, 0.08)
    target_m: tuple[float, float, float] = (0.3, 0.0, 0.0)
    camera: Mapping[str, Any] = field(default_factory=dict)
    full_frame: Mapping[str, Any] = field(default_factory=dict)
    headline_factor: int = 4

    def __post_init__(self) -> None:
        if self.trials < 1:
            raise CalibrationError(f"trials must be >= 1, got {self.trials}")
        if self.seed < 0:
            raise CalibrationError(f"seed must be >= 0, got {self.seed}")
        if any(not 0.0 <= c < 0.9 for c in self.clutter_fractions):
            raise CalibrationError(f"clutter fractions must be in [0, 0.9), got {self.clutter_fractions}")
        if self.max_boxes < 1:
            raise CalibrationError(f"max_boxes must be >= 1, got {self.max_boxes}")
        if self.headline_factor < 1:
            raise CalibrationError(f"headline_factor must be >= 1, got {self.headline_factor}")
        unknown = [a for a in (*self.artefact_levels, self.base_artefacts) if a not in ARTEFACT_TABLES]
        if unknown or not self.artefact_levels:
            raise CalibrationError(f"artefact levels must be some of {', '.join(ARTEFACT_LEVELS)}, "
                                   f"got {', '.join(unknown) or 'none'}")

    def trials_for(self, condition: Condition) -> int:
        """Trials of one condition (``trials``, times ``headline_factor`` for a headline condition)."""
        headline = (condition.inclination_deg == PAPER_INCLINATION_DEG and condition.noise_scale == 1.0
                    and condition.clutter in (0.0, TARGET_CLUTTER) and condition.artefacts == self.base_artefacts)
        return self.trials * (self.headline_factor if headline else 1)

    def conditions(self) -> list[Condition]:
        """The design's conditions, without duplicates, in a stable order."""
        base_noise = 1.0 if 1.0 in self.noise_scales or not self.noise_scales else self.noise_scales[0]
        incl = PAPER_INCLINATION_DEG if PAPER_INCLINATION_DEG in self.inclinations_deg else self.inclinations_deg[0]
        base = self.base_artefacts
        out: dict[str, Condition] = {}
        for h in self.heights_m:
            cells = [Condition(h, incl, base_noise, c, a) for a in self.artefact_levels
                     for c in self.clutter_fractions or (0.0,)]
            cells += [Condition(h, i, base_noise, 0.0, base) for i in self.inclinations_deg]
            cells += [Condition(h, incl, n, 0.0, base) for n in self.noise_scales]
            for c in cells:
                out.setdefault(c.ident(), c)
        return list(out.values())


def quick_settings(trials: int = 8, seed: int = 0, artefact_levels: tuple[str, ...] = (BASE_ARTEFACTS,)
                   ) -> StudySettings:
    """A small design for CI: the paper's heights and inclination, no clutter and 30 %, the base artefacts."""
    return StudySettings(trials=trials, seed=seed, inclinations_deg=(PAPER_INCLINATION_DEG,),
                         noise_scales=(1.0,), clutter_fractions=(0.0, TARGET_CLUTTER), headline_factor=1,
                         artefact_levels=artefact_levels)
