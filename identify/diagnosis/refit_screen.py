"""The screen a candidate refit must pass to be named, and the solver's early stop once it cannot.

The screen (:func:`could_be_named`) is generous: it decides how much work a refit gets
(its held-out folds refitted, more rounds of iterations, an early stop, the check at the
realistic magnitude for one it cannot name), not whether it is named: the diagnosis's
scores decide that.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import stats

from identify.model.effects import get_effect

__all__ = ["could_be_named", "give_up_rule", "SCREEN_P", "GIVE_UP_AFTER", "GIVE_UP_MARGIN", "BASIN_GIVE_UP_AFTER",
           "BASIN_GIVE_UP_FEAS"]

SCREEN_P = 0.01
"""Held-out folds the linear leave-out step does not hold for are refitted exactly only for a
candidate a test could name (:func:`could_be_named`). The diagnosis names a nested
candidate only with p below α over the number of candidates and ΔBIC < 0, a law only with
ΔAIC < −10; the screen asks p <
:attr:`~identify.diagnosis.candidates.CandidateTask.screen_p` (the diagnosis passes its α,
0.01: the Bonferroni divisor left out, as a later round has fewer candidates) and ΔBIC < 0
(which alone needs p ≲ 0.002 for one parameter on 10⁴ frames), ΔAIC < 0 for a law, each
against the current model's χ² as the task carries it. For any other candidate the
held-out gap is reported where the linear steps hold for every fold, and not computed (the
reason given) where they do not: a linear prediction the model contradicts, beside the
current model's refitted folds, is no comparison (on the out-of-library benchmark set it
put the held-out χ² of a refit that had not moved at 3× the current model's). Measured on
model-made data (8 runs, all candidates, four processes on two cores) before any screen:
load_scale, confounded with the friction coefficients (p = 1), took 214 s for a
2-iteration refit and 8 fold refits; the logistic law (not significant) 405 s for 13
iterations and 8 fold refits, of a 1147 s diagnosis. With the screen at p < 0.1 alone (one
worker, one other process on the cores), damping (p = 0.054, 3 iterations) still took 56 s
and spring_nonlinearity (p = 0.026) 45 s of a 335 s diagnosis, neither of them nameable."""

GIVE_UP_AFTER = 3
GIVE_UP_MARGIN = 3.0
"""A refit is stopped (status :data:`identify.fitting.convergence.GAVE_UP`) after
:data:`GIVE_UP_AFTER` iterations once its gain so far plus :data:`GIVE_UP_MARGIN` times
what the Gauss–Newton step still promises falls short of the screen
(:func:`could_be_named`): a heuristic bound (the promise is the local quadratic model's),
after which the refit is taken as not nameable, its Δnll a lower bound and its p-value an
upper bound, and the worker is freed. Nested candidates only (a law's refit starts far
off). The screen is judged against the χ² the task carries, the current model's from the
previous round; the diagnosis scores against the current model re-solved in this round
from that solution, whose χ² is lower when the re-solve gains anything, which makes the
screen looser than the score, not tighter. Measured on model-made data (8 runs, one
worker), before the stop: the refits that end not significant took 20 iterations
(stick_threshold, 44 s), 17 (rejuvenation, 34 s; load_offset, 26 s), 13 (topography, 30 s)
to report p = 0.12-0.95; with it (two workers) they stop after 4-5 iterations, 9-13 s
each."""
BASIN_GIVE_UP_AFTER = 1
"""The same stop after one iteration for each basin of a candidate solved from several
(the topography's leading ripples, :func:`identify.diagnosis.tasks.candidate_starts`): the basins are
alternatives, and the one the data favour gains from its first step. Measured on the
8-run diagnosis benchmark (model-made data, one worker, 2026-11-25): six ripple basins
took 4, 4, 4, 4, 11 and 4 iterations, 34 s, each ending unable to matter after its first
step had gained ½χ² 6-8 and left ~0.4 a step; the one that took 11 wandered 1-2.6 nm
off continuity, just outside GIVE_UP_FEAS, where the stop is not asked. So a basin is
asked within :data:`BASIN_GIVE_UP_FEAS`: 10 nm, a ninth of the camera noise, moves a
slip's prediction by 0.11 σ, its ½χ² by about that times its residual in σ, against a
screen of ~10 units and the 3× margin on what the step still promises."""
BASIN_GIVE_UP_FEAS = 1e-2


def could_be_named(task, chi2: float, n_eff: int, n_obs: int) -> bool:
    """Whether the diagnosis's tests could name this refit (generously: see SCREEN_P);
    the current model itself always counts (its held-out gap decides the verdict)."""
    if task.effect is None or task.null_chi2 is None or task.null_n_eff is None:
        return True
    dnll, dk = 0.5 * (task.null_chi2 - chi2), n_eff - task.null_n_eff
    if not np.isfinite(dnll):
        return False  # the refit is not scored at all
    return bool(2 * dnll > _needed(task, dk, n_obs))


def _needed(task, dk: int, n_obs: int) -> float:
    """The fall of χ² below the current model's that the screen of :func:`could_be_named`
    asks of a candidate with ``dk`` more free dimensions."""
    if not get_effect(task.effect).nested:
        return 2.0 * dk  # ΔAIC < 0
    dk = max(dk, 1)
    return max(float(stats.chi2.isf(task.screen_p, dk)), dk * math.log(max(n_obs, 2)))


def give_up_rule(task, prob, after: int = GIVE_UP_AFTER):
    """The solver's early stop for a candidate refit (after ``after`` iterations,
    :data:`GIVE_UP_AFTER`), or None for the current model and a task that does not know
    the current χ²."""
    if task.effect is None or task.null_chi2 is None or task.null_n_eff is None:
        return None
    if not get_effect(task.effect).nested:
        # a law starts far off (a staged start), where three iterations say little of
        # where it ends; not measured on data with another law, so never stopped
        return None
    need = _needed(task, prob.n_effective() - task.null_n_eff, prob.n_observations())
    const = prob.chi2_constant()

    def stop(it: int, half_chi2: float, promised: float) -> bool:
        if it <= after:
            return False
        best = task.null_chi2 - (2.0 * half_chi2 + const) + 2.0 * GIVE_UP_MARGIN * max(promised, 0.0)
        return best < need

    return stop
