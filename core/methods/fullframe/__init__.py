"""Full-frame plane fit: every valid pixel, robust, weighted, with honest intervals and quality gates.

Method and rationale: docs/adr/0007-full-frame-fit.md.
"""

from cellcal.core.methods.fullframe.fit import fit_full_frame, fit_plane_points
from cellcal.core.methods.fullframe.gates import GATE_NAMES, check_gates
from cellcal.core.methods.fullframe.result import Estimate, FullFrameResult
from cellcal.core.methods.fullframe.settings import MIN_POINTS, FullFrameSettings

__all__ = [
    "GATE_NAMES",
    "MIN_POINTS",
    "Estimate",
    "FullFrameResult",
    "FullFrameSettings",
    "check_gates",
    "fit_full_frame",
    "fit_plane_points",
]
