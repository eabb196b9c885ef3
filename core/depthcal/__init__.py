"""Depth calibration from the plane and the arm's motion (issue #39, ADR 0056): the joint fit and its result.

:func:`fit_depthcal` fits a camera's systematic depth error (:class:`~cellcal.devices.systematic.SystematicError`)
jointly with the plane in the base frame from :class:`DepthcalView` s; :class:`DepthcalResult` holds the
correction with its covariance, the held-out errors and the :class:`Observability` report, and writes
``depthcal.json``; :func:`load_correction` reads its correction back.
"""

from cellcal.core.depthcal.fit import fit_depthcal
from cellcal.core.depthcal.observability import Observability, ParameterSight
from cellcal.core.depthcal.result import RESULT_SCHEMA, DepthcalResult, ViewResidual, load_correction
from cellcal.core.depthcal.view import DepthcalView

__all__ = ["RESULT_SCHEMA", "DepthcalResult", "DepthcalView", "Observability", "ParameterSight", "ViewResidual",
           "fit_depthcal", "load_correction"]
