"""Depth calibration from the plane and the arm's motion (issue #39, ADR 0056): the joint fit and its result.

:func:`fit_depthcal` fits a camera's systematic depth error (:class:`~cellcal.devices.systematic.SystematicError`)
jointly with the plane in the base frame from :class:`DepthcalView` s; :class:`DepthcalResult` holds the
correction with its covariance, the held-out errors and the :class:`Observability` report, and writes
``depthcal.json``; :func:`load_correction` reads its correction back. ``cellcal depthcal``'s plan
(:func:`depthcal_plan`), run (:func:`run_depthcal`) and summary (:func:`format_summary`,
:func:`held_out_residuals`) are here too; its pictures are :mod:`cellcal.core.report.depthcal`'s (ADR 0057).
"""

from cellcal.core.depthcal.fit import fit_depthcal
from cellcal.core.depthcal.observability import Observability, ParameterSight
from cellcal.core.depthcal.plan import Coverage, PlanView, depthcal_heights, depthcal_plan, plan_coverage
from cellcal.core.depthcal.report import format_summary, held_out_residuals
from cellcal.core.depthcal.result import RESULT_SCHEMA, DepthcalResult, ViewResidual, load_correction
from cellcal.core.depthcal.run import DEPTHCAL_FILENAME, DepthcalCalibrator, raw_camera, run_depthcal
from cellcal.core.depthcal.view import DepthcalView

__all__ = ["DEPTHCAL_FILENAME", "RESULT_SCHEMA", "Coverage", "DepthcalCalibrator", "DepthcalResult", "DepthcalView",
           "Observability", "ParameterSight", "PlanView", "ViewResidual", "depthcal_heights", "depthcal_plan",
           "fit_depthcal", "format_summary", "held_out_residuals", "load_correction", "plan_coverage", "raw_camera",
           "run_depthcal"]
