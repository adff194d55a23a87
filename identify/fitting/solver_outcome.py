"""What the solver's end says of the values: how near an unconverged solve stopped to the
solution its Gauss–Newton model predicts (and the flag and report line that say so), and
how many of a multistart's starts found the best solution.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["NEAR_SOLUTION_SE", "NEAR_SOLUTION_FEAS_UM", "SAME_SOLUTION_HALF_CHI2", "best_found", "solution_gap",
           "gap_text", "unconverged_flag"]

NEAR_SOLUTION_SE = 0.5
"""A solve that stopped unconverged, at a point its Gauss–Newton model puts within this
many standard errors of that model's solution (½χ² within ½·this², continuity to
:data:`NEAR_SOLUTION_FEAS_UM`), has its values flagged with that distance rather than as
untrustworthy: an interval shifted by half its standard error at most is still one.
Measured (the 8-run model-made diagnosis benchmark's baseline, 420da57 on): it ends
``Line_Search_Failed`` at ½χ² 0.0207 from its Gauss–Newton solution (0.2 standard
errors), where the solver's own stall test asks 0.01."""
NEAR_SOLUTION_FEAS_UM = 1e-3  # 1 nm of continuity: 1/90 of the camera noise

SAME_SOLUTION_HALF_CHI2 = 0.05
"""Starts whose ½χ² ends within this of the best count as having found it: the parameters
then within ~0.3 standard errors (√(2·0.05)), a difference the solver's own tolerances do
not resolve (its stall test asks 0.01; a fit that stopped 0.02 short is measured, above).
A relative tolerance (1e-6 of ½χ² before) put that line at 0.005 on an 8-run fit."""


def best_found(costs) -> int:
    """How many of the starts' final ½χ² (``costs``) are the best's, within
    :data:`SAME_SOLUTION_HALF_CHI2`."""
    finite = [float(f) for f in costs if np.isfinite(f)]
    if not finite:
        return 0
    best = min(finite)
    return sum(1 for f in finite if f - best <= SAME_SOLUTION_HALF_CHI2)


def solution_gap(prob, w) -> dict | None:
    """:meth:`identify.fitting.gauss_newton.GaussNewtonSQP.solution_gap` at an unconverged solve's point, with
    the parameters' distance it implies (``within_se``); None when it cannot be computed."""
    try:
        gap = prob.solution_gap(w)
    except Exception:  # (the report stands without it)
        return None
    h = gap["half_chi2"]
    gap["within_se"] = math.sqrt(2.0 * h) if np.isfinite(h) else float("nan")
    gap["near"] = bool(gap["within_se"] <= NEAR_SOLUTION_SE and gap["continuity_um"] <= NEAR_SOLUTION_FEAS_UM)
    return gap


def gap_text(gap: dict) -> str:
    """The report's line on how far an unconverged solve stopped from its Gauss–Newton solution."""
    if not np.isfinite(gap["half_chi2"]):
        return f"its Gauss–Newton model has no solution here (continuity {gap['continuity_um']:.1g} µm)"
    return (f"½χ² {gap['half_chi2']:.2g} away from the solution its Gauss–Newton step predicts (the parameters within "
            f"~{gap['within_se']:.2g} standard errors of it), continuity {gap['continuity_um']:.1g} µm")


def unconverged_flag(status, gap: dict | None) -> str:
    """The flag of a parameter whose solve did not converge: how near it stopped, when
    that is known and near (:data:`NEAR_SOLUTION_SE`), else a warning not to trust it."""
    # (the numbers behind it are on the report's 'stopped' line)
    if gap is not None and gap["near"]:
        return (f"not converged ({status}): within ~{gap['within_se']:.2g} standard errors of the solution its "
                "Gauss–Newton step predicts")
    far = (f" (~{gap['within_se']:.2g} standard errors from the solution its Gauss–Newton step predicts)"
           if gap is not None and np.isfinite(gap["within_se"]) else "")
    return f"not converged ({status}): the value is where the solver stopped, its interval not to be trusted" + far
