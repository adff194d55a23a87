"""One candidate refit of the diagnosis, as a picklable task for any Executor.

A task carries everything a worker process (local or on a dask cluster) needs to rebuild
the NLP — the runs' compressed data, the law, the parameter values, which parameters are
free, the arc spans and the warm start — and returns numbers only: CasADi Functions do
not cross process boundaries, so each worker builds its own (the compiled arc code is
cached on disk, so that is quick).

:func:`run_candidate` refits from the task's starts, then reads the numbers the diagnosis
scores the candidate by: estimates and confounding (:mod:`identify.diagnosis.refit_readings`),
the gaps on the runs fitted and held out, and for a candidate no test could name, the check
at its realistic magnitude (:mod:`identify.diagnosis.magnitude_check`). How a refit is
solved: :mod:`identify.diagnosis.refit_solve`; the screen a name asks and the early stop:
:mod:`identify.diagnosis.refit_screen`.
"""

from __future__ import annotations

import contextlib
import math
import time
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from identify.diagnosis.features import Layout, feature_values, gap
from identify.diagnosis.heldout import heldout_residuals
from identify.diagnosis.magnitude_check import MAGNITUDE_DECISIVE as MAGNITUDE_DECISIVE
from identify.diagnosis.magnitude_check import MAGNITUDE_MAX_ITER as MAGNITUDE_MAX_ITER
from identify.diagnosis.magnitude_check import MAGNITUDE_MOVED_Z as MAGNITUDE_MOVED_Z
from identify.diagnosis.magnitude_check import MAGNITUDE_WIDER as MAGNITUDE_WIDER
from identify.diagnosis.magnitude_check import at_magnitude
from identify.diagnosis.prior_scale import evidence_scale
from identify.diagnosis.records import CandidateResult
from identify.diagnosis.refit_readings import confounding, parameter_estimates, regime_of_left_out
from identify.diagnosis.refit_screen import (
    BASIN_GIVE_UP_AFTER,
    BASIN_GIVE_UP_FEAS,
    SCREEN_P,
    could_be_named,
    give_up_rule,
)
from identify.diagnosis.refit_screen import GIVE_UP_AFTER as GIVE_UP_AFTER
from identify.diagnosis.refit_screen import GIVE_UP_MARGIN as GIVE_UP_MARGIN
from identify.diagnosis.refit_solve import CANDIDATE_STAT_TOL as CANDIDATE_STAT_TOL
from identify.diagnosis.refit_solve import CONVERGED_SLACK as CONVERGED_SLACK
from identify.diagnosis.refit_solve import EXTRA_ROUNDS as EXTRA_ROUNDS
from identify.diagnosis.refit_solve import EXTRA_ROUNDS_NAMEABLE as EXTRA_ROUNDS_NAMEABLE
from identify.diagnosis.refit_solve import ROUND_GAIN as ROUND_GAIN
from identify.diagnosis.refit_solve import candidate_problem, solve_on
from identify.fitting.convergence import GAVE_UP as GAVE_UP
from identify.fitting.convergence import STALLED as STALLED
from identify.model.effects import get_effect

__all__ = ["CandidateResult", "CandidateTask", "run_candidate", "candidate_problem", "regime_of_left_out"]

FALLBACK_STARTS = 1
"""How many of the starts a refit passed over (a higher χ² at the start than the one it
solved from) it solves as well when it ends worse than the current model (run_candidate)."""


@dataclass
class CandidateTask:
    """A refit of the current model with ``extra`` parameters freed (or another law)."""

    effect: str | None  # None: the current model itself (its held-out gap)
    runs: list
    law: str
    values: dict  # every parameter's value: fitted ones from the current model
    free: tuple  # the current model's free parameters
    extra: tuple = ()  # the candidate's parameters, freed in addition
    replace_free: tuple = ()  # parameters no longer free (a law candidate drops the old law's)
    bounds: dict = field(default_factory=dict)
    priors: dict = field(default_factory=dict)  # zero-mean Gaussian priors' sd (FitOptions.priors)
    starts: list = field(default_factory=list)  # start values of the extra parameters (best kept)
    w_tail: Any = None  # the current solution after the parameters (positions, phases)
    ev_M: Any = None
    options: Any = None  # the baseline's FitOptions
    folds: list = field(default_factory=list)
    staged: bool = False  # a law candidate starts from the staged start of identify.fitting.start
    max_iter: int = 30
    threads: int = 1
    nulls: dict = field(default_factory=dict)  # the candidate's null values (the current model)
    null_chi2: float | None = None  # the current model's χ² and free dimensions (SCREEN_P)
    null_n_eff: int | None = None
    screen_p: float = SCREEN_P
    magnitude: tuple | None = None  # (parameter, realistic value) to check (magnitude_check)
    regime_runs: list = field(default_factory=list)  # runs left out for their regime (regime_check)


def run_candidate(task: CandidateTask) -> CandidateResult:
    """Refit, then the numbers the diagnosis scores the candidate by."""
    t0 = time.perf_counter()
    free = tuple(n for n in task.free if n not in task.replace_free) + tuple(
        n for n in task.extra if n not in task.free)
    try:
        prob = candidate_problem(task, free)
        prob.give_up = give_up_rule(task, prob)
        best = _refit(task, prob, _scored_starts(prob, _starts(task, prob, free)))
        scale = None
        if task.effect is not None and get_effect(task.effect, task.runs).priors():
            prob, best, scale = _roughness_rounds(task, prob, free, best)
        ev = prob.central_differences().evaluate(best["w"], jac=True)
        out = _refit_record(task, prob, free, best, ev, t0).but(prior_scale=scale)
        if (task.magnitude and np.isfinite(out.chi2)
                and not could_be_named(task, out.chi2, out.n_eff, prob.n_observations())):
            out = out.but(**_magnitude_check(task, prob, out, ev, t0))
        return out
    except Exception as err:  # one failed candidate never sinks the diagnosis
        return CandidateResult(effect=task.effect, ok=False, status=f"failed: {type(err).__name__}: {err}",
                               error=str(err), wall_s=time.perf_counter() - t0)


ROUGHNESS_ROUNDS = 3
"""Refits a candidate's prior scale (a rough track's roughness, a random walk's intensity)
is chosen over at most: each finds the scale the evidence gives on the last refit's
linearisation (:func:`identify.diagnosis.prior_scale.evidence_scale`) and refits there
from its end; it stops once the scale moves by less than :data:`ROUGHNESS_RTOL`."""
ROUGHNESS_RTOL = 0.1


def _roughness_rounds(task: CandidateTask, prob, free: tuple, best: dict):
    """The refit with its priors' scale chosen by the data (MacKay's evidence rule, to its
    fixed point on the refit's linearisation), and the refit solved again from its end at
    that scale, until the scale settles. Returns the problem and end of the last refit, and
    the scale its priors have."""
    eff = get_effect(task.effect, task.runs)
    own = [n for n in prob.prior_sd() if n in eff.parameters]
    rho = used = _prior_scale_of(prob, eff, own)
    for _ in range(ROUGHNESS_ROUNDS):
        w = best["w"]
        ev = prob.central_differences().evaluate(w, jac=True)
        new = evidence_scale(prob, w, ev, eff, own, rho)
        if abs(math.log(new / rho)) < math.log(1 + ROUGHNESS_RTOL):
            break
        rho = new
        nxt = candidate_problem(replace(task, priors={**task.priors, **eff.priors(rho)}), free)
        nxt.give_up = give_up_rule(task, nxt)
        if nxt.E:
            nxt.ev_M = np.array(prob.ev_M)
            nxt.size_arcs(w)
        f0 = 0.5 * float(np.sum(nxt.residuals(w) ** 2))
        sol = solve_on(nxt, w, f0)
        if not np.isfinite(sol["f"]):
            break
        prob, best, used = nxt, sol, rho
    return prob, best, used


def _prior_scale_of(prob, eff, own: list) -> float:
    """The scale the priors of ``eff``'s parameters ``own`` have in ``prob``: its default,
    or the one the evidence chose before (a candidate refitted beside a rival carries
    its chosen priors). The priors are proportional to it."""
    unit = eff.priors(1.0)
    ratios = [prob.prior_sd()[n] / unit[n] for n in own if unit.get(n)]
    return float(np.median(ratios)) if ratios else float(eff.roughness)


def _starts(task: CandidateTask, prob, free: tuple) -> list:
    """The refit's start points (w0, staged, basin): warm from the current solution, or
    staged where the candidate starts far from it (``task.starts`` may ask either)."""
    inits = []
    for start in (task.starts or [{}]):
        start = dict(start)
        nudged = bool(start.pop("_staged", False))
        basin = start.pop("_basin", 0)
        staged = nudged or task.staged
        vals = {**task.values, **start}
        th_vals = {n: vals[n] for n in free}
        if staged:
            # far from the current solution (another law, or an effect whose null sits
            # on its bound): from the staged start of a fit, and for a law also from
            # the current values (the same friction numbers under the other curve)
            if not nudged:
                inits.append((prob.initial_w(th_vals), True, basin))
            try:
                from identify.fitting.start import staged_start

                inits.append((prob.initial_w(staged_start(prob, th_vals)[0]), True, basin))
            except Exception:  # the staged start is a convenience
                pass
        else:
            th = prob.theta.to_scaled(th_vals)
            inits.append((np.r_[np.clip(th, prob.theta.lo + 1e-9, prob.theta.hi - 1e-9), task.w_tail], False,
                          basin))
    return inits


def _scored_starts(prob, inits: list) -> list:
    """The starts the model can be evaluated at, as (w0, (staged, basin), ½χ² there)."""
    scored = []
    for w0, staged, basin in inits:
        if prob.E:
            prob.size_arcs(w0)
        f0 = 0.5 * float(np.sum(prob.residuals(w0) ** 2))
        if np.isfinite(f0):
            scored.append((w0, (staged, basin), f0))
    return scored


def _refit(task: CandidateTask, prob, scored: list) -> dict:
    """The refit's best end: solved from the best start of each kind and basin, then, when
    it ends worse than the current model, from the starts it passed over."""
    # solve from the best warm start (they differ only in the candidate's own
    # parameters) and the best far one, of each basin: a start's χ² says which sign
    # or nudge is downhill, not which of several ripples the refit ends in
    todo = []
    for kind in dict.fromkeys(x[1] for x in scored):
        todo.append(min((x for x in scored if x[1] == kind), key=lambda x: x[2]))
    best = None
    const = prob.chi2_constant()
    nameable = _nameable(task, prob, const)
    # several basins: each is dropped after its first iteration once it cannot reach
    # the screen (BASIN_GIVE_UP_AFTER), not after GIVE_UP_AFTER as a single start is
    several = len({kind[1] for _, kind, _ in todo}) > 1
    with contextlib.ExitStack() as basins:
        if several:
            prob.give_up = give_up_rule(task, prob, after=BASIN_GIVE_UP_AFTER)
            basins.enter_context(prob.tuned(give_up_feas=BASIN_GIVE_UP_FEAS))
        for w0, _, f0 in todo:
            best = _better(best, solve_on(prob, w0, f0, nameable))
    prob.give_up = give_up_rule(task, prob)
    if not several:  # (several basins are their own diversity already)
        best = _solve_passed_over(task, prob, scored, todo, best, (nameable, const))
    if best is None:
        raise ValueError("the model cannot be evaluated at any start (an arc or the trigger encoding "
                         "is not finite there)")
    return best


def _nameable(task: CandidateTask, prob, const: float):
    """The test :func:`identify.diagnosis.refit_solve.solve_on` asks for more rounds: is a
    refit at this ½χ² already past the naming screen?"""
    def nameable(half_chi2: float) -> bool:
        return bool(task.effect and task.null_chi2 is not None and task.null_n_eff is not None
                    and could_be_named(task, 2.0 * half_chi2 + const, prob.n_effective(),
                                       prob.n_observations()))

    return nameable


def _better(best: dict | None, sol: dict) -> dict | None:
    """The lower of two ends (a non-finite one never counts)."""
    return sol if np.isfinite(sol["f"]) and (best is None or sol["f"] < best["f"]) else best


def _solve_passed_over(task: CandidateTask, prob, scored: list, todo: list, best: dict | None, how: tuple):
    """``best``, or a better end from the starts passed over for a lower χ², best first
    (:data:`FALLBACK_STARTS`), while it is worse than the current model. ``how``:
    (nameable, χ² constant)."""
    nameable, const = how
    # a refit from one start that ends worse than the current model has not found the
    # candidate's fit (its null is the current model, or for a law the same friction
    # under another curve). A refit of a law from the staged start can stop far worse
    # than from the current values (the engineering notes measure one on the withheld
    # logarithmic-law set).
    tried = {id(x[0]) for x in todo}
    rest = sorted((x for x in scored if id(x[0]) not in tried), key=lambda x: x[2])
    for w0, _, f0 in rest[:FALLBACK_STARTS]:
        if best is not None and (task.null_chi2 is None
                                 or 2.0 * best["f"] + const <= task.null_chi2):
            break
        best = _better(best, solve_on(prob, w0, f0, nameable))
    return best


def _refit_record(task: CandidateTask, prob, free: tuple, best: dict, ev, t0: float) -> CandidateResult:
    """The numbers of the refit's best end (``ev``: its central-difference evaluation) the
    diagnosis scores it by."""
    w = best["w"]
    r = ev[0]
    chi2, n_eff = prob.penalised_counts(r, w, ev)
    est = parameter_estimates(prob, w, ev)
    eff = get_effect(task.effect).named(task.extra) if task.effect else None
    info = confounding(prob, w, ev, task.extra if task.effect else (),
                       eff.defining if eff is not None and eff.nuisance else None)
    fitted = gap(feature_values(prob, w, r))
    heldout = _heldout_gap(task, prob, w, r, ev, (chi2, n_eff)) if task.folds else dict(gap_um=float("nan"))
    values = dict(task.values)
    values.update(zip(prob.theta.names, (float(v) for v in prob.theta.from_scaled(w[: prob.n_theta]))))
    p0, p1 = prob.residual_groups()["priors"]
    r_data = np.r_[r[:p0], r[p1:]]  # (records compare the data's rows: the priors' depend on the candidate)
    return CandidateResult(
        effect=task.effect, ok=bool(np.isfinite(chi2)), status=best["status"], iterations=best["iterations"],
        rounds=best.get("rounds", []),
        chi2=chi2, n_obs=prob.n_observations(), n_eff=n_eff, free=list(free), law=task.law,
        priors=prob.prior_sd() or None,
        values=values, estimates=est, confounding=info, r=r_data, w=w, ev_M=np.array(prob.ev_M),
        gap=fitted, heldout=heldout, wall_s=time.perf_counter() - t0, error=None, nulls=dict(task.nulls),
        regime=regime_of_left_out(task, values) if task.regime_runs else None,
        time_by_run=_time_by_run(prob, w, r) if task.effect is None else None,
    )


def _time_by_run(prob, w, r) -> dict | None:
    """The runs' own trends of their plateau levels in time, as one χ² (None without a run
    of four plateaus)."""
    from scipy import stats

    from identify.diagnosis.where import run_trends

    t, _ = run_trends(prob, feature_values(prob, w, r)["post_slip_level"])
    if not t.size:
        return None
    q = float(t @ t)
    return dict(chi2=q, df=int(t.size), p=float(stats.chi2.sf(q, t.size)))


def _heldout_gap(task: CandidateTask, prob, w, r: np.ndarray, ev, counts: tuple) -> dict:
    """The held-out gap of the refit over ``task.folds``, or why it is missing (the fit
    stands either way); ``counts``: its χ² and free dimensions
    (:meth:`identify.fitting.problem.Problem.penalised_counts`)."""
    try:
        nameable = could_be_named(task, *counts, prob.n_observations())
        ho = heldout_residuals(prob, w, task.folds, evaluated=ev, refit=nameable)
        if ho.unverified and not nameable:
            # a linear prediction the model contradicts is no number to report
            # beside the current model's refitted folds
            raise _NotComputed(f"{len(ho.unverified)} of {len(task.folds)} fold(s) not confirmed by the "
                               "model and not refitted (no test could name this candidate)")
        return _heldout_numbers(task, prob, w, r, ho)
    except _NotComputed as why:
        return dict(gap_um=float("nan"), error=str(why))
    except Exception as err:  # the fit stands; only its held-out check is missing
        return dict(gap_um=float("nan"), error=f"{type(err).__name__}: {err}")


def _heldout_numbers(task: CandidateTask, prob, w, r: np.ndarray, ho) -> dict:
    """The held-out gap and deviance of the leave-out residuals ``ho``, in all and by fold."""
    feats_ho = feature_values(prob, w, ho.residuals)
    heldout = gap(feats_ho)
    # the held-out deviance: every row in its own noise units, as the fit
    # weighs them (the µm gap weighs features by their size in µm)
    fin = np.isfinite(ho.residuals)
    heldout["chi2"] = float(ho.residuals[fin] @ ho.residuals[fin])
    heldout["n_rows"] = int(fin.sum())
    # per fold, fitted and held out, and the held-out gap without each fold in
    # turn: for a rule one run cannot decide (identify.diagnosis.scores.heldout_by_fold)
    rows = Layout.of(prob).row_run
    if rows.size != r.size:
        raise RuntimeError(f"residual layout mismatch: {rows.size} rows mapped to runs, {r.size} residuals")
    heldout["fitted_chi2_by_fold"] = _chi2_by_fold(r, rows, task.folds)
    heldout["chi2_by_fold"] = _chi2_by_fold(ho.residuals, rows, task.folds)
    heldout["rows_by_fold"] = [int((np.isin(rows, list(f)) & fin).sum()) for f in task.folds]
    n_runs = len(prob.runs)
    without = [gap(feats_ho, runs=[i for i in range(n_runs) if i not in set(f)]) for f in task.folds]
    heldout["gap_um_without_fold"] = [x["gap_um"] for x in without]
    heldout["noise_um_without_fold"] = [x["noise_um"] for x in without]
    heldout["refitted_folds"] = len(ho.refitted)
    heldout["unverified_folds"] = len(ho.unverified)
    return heldout


def _magnitude_check(task: CandidateTask, prob, out: CandidateResult, ev, t0: float) -> dict:
    """The check at the realistic magnitude of the refit ``out`` (its error instead, the
    refit's numbers standing), with where a profile over the parameter would start: the
    fields to add to ``out``."""
    try:
        m = at_magnitude(task, prob, out.w, out.chi2, out.estimates, evaluated=ev)
    except Exception as err:  # the refit's numbers stand; only this check is missing
        m = dict(parameter=task.magnitude[0], value=float(task.magnitude[1]), absorbed=None,
                 error=f"{type(err).__name__}: {err}")
    add = dict(at_magnitude=m, wall_s=time.perf_counter() - t0)
    start = m.pop("_start", None)
    if start is not None:
        add.update(w_at_magnitude=start["w"], ev_M_at_magnitude=start["ev_M"])
    return add


def _chi2_by_fold(r: np.ndarray, row_run: np.ndarray, folds) -> list:
    """χ² of each fold's rows (rows the model could not give left out)."""
    out = []
    for f in folds:
        a = r[np.isin(row_run, list(f))]
        a = a[np.isfinite(a)]
        out.append(float(a @ a))
    return out


class _NotComputed(Exception):
    """A held-out gap deliberately not computed (the reason is the message)."""
