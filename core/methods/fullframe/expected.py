"""The plane the user means (:class:`ExpectedPlane`): its home is ``points.py``, with the rest of what the fit is given.

Kept importable from here for the calibration layer, which builds it from ``[reference]``,
``[mount]`` and the arm pose (ADR 0027, "The plane the user means").
"""

from cellcal.core.methods.fullframe.points import (
    DEFAULT_SEARCH_TOLERANCE_DEG,
    DEFAULT_SEARCH_TOLERANCE_M,
    ExpectedPlane,
)

__all__ = ["DEFAULT_SEARCH_TOLERANCE_DEG", "DEFAULT_SEARCH_TOLERANCE_M", "ExpectedPlane"]
