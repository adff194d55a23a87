"""One candidate refit of the diagnosis, as a picklable task for any Executor.

A task carries everything a worker process (local or on a dask cluster) needs to rebuild
the NLP — the runs' compressed data, the law, the parameter values, which parameters are
free, the arc spans and the warm start — and returns numbers only: CasADi Functions do
not cross process boundaries, so each worker builds its own (the compiled arc code is
cached on disk, so that is quick).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy import stats

from identify.diagnosis.features import Layout, feature_values, gap
from identify.diagnosis.heldout import heldout_residuals
from identify.fitting.convergence import GAVE_UP, GIVE_UP_FEAS, STALLED

__all__ = ["CandidateTask", "run_candidate"]

CANDIDATE_STAT_TOL = 1e-2
EXTRA_ROUNDS = 2
"""A refit that stops at its iteration limit while its last round still gained more than
:data:`ROUND_GAIN` likelihood units is continued from where it stopped, up to this many
more rounds: measured, a rejuvenation refit (dc from the baseline's 20 nm towards the
truth of 1 µm) stopped at dc = 0.18 µm, significant but unconverged and so never named."""
ROUND_GAIN = 1.0
EXTRA_ROUNDS_NAMEABLE = 6
"""A refit that keeps gaining at its iteration limit while already past the screen a
name asks (:func:`_could_be_named`) is continued up to this many more rounds instead of
:data:`EXTRA_ROUNDS`: its name hangs on convergence alone. Measured (rejuvenation
withheld, dc = 0.1 µm against the baseline's 20 nm): after three rounds of 20 iterations
the refit was still gaining (½χ² 323 → 276 → 242), dc = 41 ± 13 nm, p = 1e-68, closing
all of the held-out gap above the noise, and was not named for it; with 60 iterations a
round it converged in the second (½χ² 126), dc = 74 ± 11 nm, and was named. Refits of
candidates no test could name (all of them on data the model made: the speed benchmark)
keep :data:`EXTRA_ROUNDS`."""
SCREEN_P = 0.01
"""Held-out folds the linear leave-out step does not hold for are refitted exactly only
for a candidate a test could name. The diagnosis names a nested candidate only with p
below α over the number of candidates and ΔBIC < 0, a law only with ΔAIC < −10; the
screen asks p < :attr:`CandidateTask.screen_p` (the diagnosis passes its α, 0.01: the
Bonferroni divisor left out, as a later round has fewer candidates) and ΔBIC < 0 (which
alone needs p ≲ 0.002 for one parameter on 10⁴ frames), ΔAIC < 0 for a law, each
against the current model's χ² as the task carries it. For any other candidate the
held-out gap is reported where the linear steps hold for every fold, and not computed
(the reason given) where they do not: a linear prediction the
model contradicts, beside the current model's refitted folds, is no comparison (on the
out-of-library benchmark set it put the held-out χ² of a refit that had not moved at 3×
the current model's). Measured on model-made data (8 runs, all candidates, four
processes on two cores) before any screen: load_scale, confounded with the friction
coefficients (p = 1), took 214 s for a 2-iteration refit and 8 fold refits; the logistic
law (not significant) 405 s for 13 iterations and 8 fold refits, of a 1147 s diagnosis.
With the screen at p < 0.1 alone (one worker, one other process on the cores), damping
(p = 0.054, 3 iterations) still took 56 s and spring_nonlinearity (p = 0.026) 45 s of a
335 s diagnosis, neither of them nameable."""
CONVERGED_SLACK = 0.5 * float(stats.chi2.isf(SCREEN_P, 1))  # 3.3: ½ χ²₁ quantile at SCREEN_P
"""A round that converges is kept over the unconverged round before it (which stopped
off continuity) when its ½χ² is at most this much higher: a difference the screen could
not call. Further above, the earlier point stands, not converged (_solve_on)."""

GIVE_UP_AFTER = 3
GIVE_UP_MARGIN = 3.0
"""A refit is stopped (status :data:`identify.fitting.convergence.GAVE_UP`) after :data:`GIVE_UP_AFTER`
iterations once its gain so far plus :data:`GIVE_UP_MARGIN` times what the Gauss–Newton
step still promises falls short of the screen (:func:`_could_be_named`): a heuristic
bound (the promise is the local quadratic model's), after which the refit is taken as
not nameable, its Δnll a lower bound and its p-value an upper bound, and the worker is
freed. Nested candidates only (a law's refit starts far off). The screen is judged
against the χ² the task carries, the current model's from the previous round; the
diagnosis scores against the current model re-solved in this round from that solution,
whose χ² is lower when the re-solve gains anything, which makes the screen looser than
the score, not tighter. Measured on model-made data (8 runs, one worker), before the
stop: the refits that end not significant took 20 iterations (stick_threshold, 44 s),
17 (rejuvenation, 34 s; load_offset, 26 s), 13 (topography, 30 s) to report
p = 0.12-0.95; with it (two workers) they stop after 4-5 iterations, 9-13 s each."""
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
# STALLED (from :mod:`identify.fitting.problem`) is also the status of a refit whose last round of
# iterations, at the iteration limit, gained less than ROUND_GAIN: its Δnll is known to
# better than a likelihood unit, which is what the scores need, though the step test has
# not passed (finite-difference noise of the arcs can hold it off for ever).


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
    magnitude: tuple | None = None  # (parameter, realistic value): the check of _at_magnitude
    regime_runs: list = field(default_factory=list)  # runs left out for their regime (regime_check)


def candidate_problem(task: CandidateTask, free: tuple):
    from identify.fitting.problem import Problem
    from identify.model.laws import get_law
    from identify.model.symbolic import Model

    bounds = {n: b for n, b in {**dict(task.options.bounds), **task.bounds}.items() if n in free}
    opts = replace(task.options, free=free, bounds=bounds, fixed={}, start={}, law=task.law,
                   threads=task.threads, max_iter=task.max_iter)
    prob = Problem(task.runs, Model(get_law(task.law)), dict(task.values), opts)
    # a candidate is scored by its Δnll: converging to 0.01 of a likelihood unit is plenty
    prob.stat_tol = CANDIDATE_STAT_TOL
    # continuity to 10 pm: finite-difference noise of the arcs keeps ~1e-6 µm
    prob.feas_tol = 1e-5
    # and a refit that stalls is good enough if its Δnll is known to a likelihood unit,
    # as for a round that stops at the iteration limit
    prob.stall_tol = ROUND_GAIN
    # judged so within GIVE_UP_FEAS of continuity (1 nm, 1/90 of the camera noise): the
    # stall test's ½χ² gap is to the linearised problem's *feasible* stationary point,
    # so restoring continuity is in it. Measured (drift at 5e-9 m/s, 0.1× the withheld
    # set's): the refit stopped with |g| = 1.03e-4 µm, just above the fit's 1e-4, and ½χ²
    # 0.025 from that point — "not converged", so a drift rate of 4.971e-9 ± 0.085e-9
    # m/s that closed the whole held-out gap (38.6 -> 19.7 nm, noise 20.1) was not named
    prob.stall_feas = GIVE_UP_FEAS
    if task.ev_M is not None and len(task.ev_M) == prob.E:
        prob.ev_M = np.array(task.ev_M)
    return prob.build()


def _solve_on(prob, w0, f0: float, nameable=None) -> dict:
    """Solve from w0; continue from where it stopped while rounds that hit the iteration
    limit still gain (:data:`EXTRA_ROUNDS`, or :data:`EXTRA_ROUNDS_NAMEABLE` while
    ``nameable(½χ²)`` says the refit is already past the naming screen); a round that
    gained less than :data:`ROUND_GAIN` is reported :data:`STALLED`."""
    sol = prob.solve(w0)
    its, wall, before, rounds = sol["iterations"], sol["wall_s"], f0, 0
    trail = [(sol["status"], float(sol["f"]))]  # (status, ½χ²) of every round, for the record
    while sol["status"] == "Maximum_Iterations_Exceeded":
        if not (before - sol["f"] > ROUND_GAIN):
            sol["status"] = STALLED
            break
        more_rounds = EXTRA_ROUNDS_NAMEABLE if nameable is not None and nameable(float(sol["f"])) else EXTRA_ROUNDS
        if rounds >= more_rounds:
            break
        rounds += 1
        before = sol["f"]
        try:
            if prob.E:
                prob.size_arcs(sol["w"])  # the slips may have grown past the arcs' horizons
            more = prob.solve(sol["w"])
        except Exception:  # the finished round stands
            break
        its, wall = its + more["iterations"], wall + more["wall_s"]
        trail.append((more["status"], float(more["f"])))
        # a round that converges is kept even at a ½χ² a little higher (CONVERGED_SLACK):
        # the point it continued from stopped off continuity, where ½χ² is not yet the
        # model's (measured, the load offset's refit on the two-effect withheld set: ½χ²
        # 4263.99 at |g| 3.8e-5 µm after round 1, 4265.52 converged at 8.8e-7 in one more
        # iteration; the refit was reported "not converged" and not named)
        if not (np.isfinite(more["f"]) and (more["f"] <= sol["f"] or (
                more.get("success") and more["f"] <= sol["f"] + CONVERGED_SLACK))):
            break
        sol = more
    sol["iterations"], sol["wall_s"], sol["rounds"] = its, wall, trail
    return sol


def run_candidate(task: CandidateTask) -> dict:
    """Refit, then the numbers the diagnosis scores the candidate by."""
    t0 = time.perf_counter()
    free = tuple(n for n in task.free if n not in task.replace_free) + tuple(
        n for n in task.extra if n not in task.free)
    try:
        prob = candidate_problem(task, free)
        prob.give_up = _give_up(task, prob)
        inits = []  # (w0, staged, basin)
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
        scored = []
        for w0, staged, basin in inits:
            if prob.E:
                prob.size_arcs(w0)
            f0 = 0.5 * float(np.sum(prob.residuals(w0) ** 2))
            if np.isfinite(f0):
                scored.append((w0, (staged, basin), f0))
        # solve from the best warm start (they differ only in the candidate's own
        # parameters) and the best far one, of each basin: a start's χ² says which sign
        # or nudge is downhill, not which of several ripples the refit ends in
        todo = []
        for kind in dict.fromkeys(x[1] for x in scored):
            todo.append(min((x for x in scored if x[1] == kind), key=lambda x: x[2]))
        best = None
        const = prob.chi2_constant()

        def nameable(half_chi2: float) -> bool:
            return bool(task.effect and task.null_chi2 is not None and task.null_n_eff is not None
                        and _could_be_named(task, 2.0 * half_chi2 + const, prob.n_effective(),
                                            prob.n_observations()))

        # several basins: each is dropped after its first iteration once it cannot reach
        # the screen (BASIN_GIVE_UP_AFTER), not after GIVE_UP_AFTER as a single start is
        several = len({kind[1] for _, kind, _ in todo}) > 1
        if several:
            prob.give_up = _give_up(task, prob, after=BASIN_GIVE_UP_AFTER)
            prob.give_up_feas = BASIN_GIVE_UP_FEAS
        for w0, _, f0 in todo:
            sol = _solve_on(prob, w0, f0, nameable)
            if np.isfinite(sol["f"]) and (best is None or sol["f"] < best["f"]):
                best = sol
        prob.give_up, prob.give_up_feas = _give_up(task, prob), GIVE_UP_FEAS
        # a refit from one start that ends worse than the current model has not found the
        # candidate's fit (its null is the current model, or for a law the same friction
        # under another curve): the starts passed over for a lower χ² are solved too, best
        # first (FALLBACK_STARTS; several basins are their own diversity already). A refit
        # of a law from the staged start can stop far worse than from the current values
        # (the engineering notes measure one on the withheld logarithmic-law set).
        tried = {id(x[0]) for x in todo}
        rest = [] if several else sorted((x for x in scored if id(x[0]) not in tried), key=lambda x: x[2])
        for w0, _, f0 in rest[:FALLBACK_STARTS]:
            if best is not None and (task.null_chi2 is None
                                     or 2.0 * best["f"] + const <= task.null_chi2):
                break
            sol = _solve_on(prob, w0, f0, nameable)
            if np.isfinite(sol["f"]) and (best is None or sol["f"] < best["f"]):
                best = sol
        if best is None:
            raise ValueError("the model cannot be evaluated at any start (an arc or the trigger encoding "
                             "is not finite there)")
        w = best["w"]
        ev = prob.central_differences().evaluate(w, jac=True)
        r = ev[0]
        chi2 = float(r @ r) + prob.chi2_constant()
        est = _estimates(prob, w, ev)
        info = _confounding(prob, w, ev, task.extra if task.effect else ())
        feats = feature_values(prob, w, r)
        fitted = gap(feats)
        heldout = dict(gap_um=float("nan"))
        if task.folds:
            try:
                nameable = _could_be_named(task, chi2, prob.n_effective(), prob.n_observations())
                ho = heldout_residuals(prob, w, task.folds, evaluated=ev, refit=nameable)
                if ho.unverified and not nameable:
                    # a linear prediction the model contradicts is no number to report
                    # beside the current model's refitted folds
                    raise _NotComputed(f"{len(ho.unverified)} of {len(task.folds)} fold(s) not confirmed by the "
                                       "model and not refitted (no test could name this candidate)")
                feats_ho = feature_values(prob, w, ho.residuals)
                heldout = gap(feats_ho)
                # the held-out deviance: every row in its own noise units, as the fit
                # weighs them (the µm gap weighs features by their size in µm)
                fin = np.isfinite(ho.residuals)
                heldout["chi2"] = float(ho.residuals[fin] @ ho.residuals[fin])
                heldout["n_rows"] = int(fin.sum())
                # per fold, fitted and held out, and the held-out gap without each fold in
                # turn: for a rule one run cannot decide (diagnosis._heldout_by_fold)
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
            except _NotComputed as why:
                heldout = dict(gap_um=float("nan"), error=str(why))
            except Exception as err:  # the fit stands; only its held-out check is missing
                heldout = dict(gap_um=float("nan"), error=f"{type(err).__name__}: {err}")
        values = dict(task.values)
        values.update(zip(prob.theta.names, (float(v) for v in prob.theta.from_scaled(w[: prob.n_theta]))))
        out = dict(
            effect=task.effect, ok=bool(np.isfinite(chi2)), status=best["status"], iterations=best["iterations"],
            rounds=best.get("rounds", []),
            chi2=chi2, n_obs=prob.n_observations(), n_eff=prob.n_effective(), free=list(free), law=task.law,
            values=values, estimates=est, confounding=info, r=r, w=w, ev_M=np.array(prob.ev_M),
            gap=fitted, heldout=heldout, wall_s=time.perf_counter() - t0, error=None, nulls=dict(task.nulls),
        )
        if task.regime_runs:
            out["regime"] = regime_of_left_out(task, values)
        if (task.magnitude and np.isfinite(chi2)
                and not _could_be_named(task, chi2, prob.n_effective(), prob.n_observations())):
            try:
                out["at_magnitude"] = _at_magnitude(task, prob, w, chi2, est, evaluated=ev)
            except Exception as err:  # the refit's numbers stand; only this check is missing
                out["at_magnitude"] = dict(parameter=task.magnitude[0], value=float(task.magnitude[1]),
                                           absorbed=None, error=f"{type(err).__name__}: {err}")
            out["wall_s"] = time.perf_counter() - t0
            start = out["at_magnitude"].pop("_start", None)
            if start is not None:
                out["w_at_magnitude"], out["ev_M_at_magnitude"] = start["w"], start["ev_M"]
        return out
    except Exception as err:  # one failed candidate never sinks the diagnosis
        return dict(effect=task.effect, ok=False, status=f"failed: {type(err).__name__}: {err}", error=str(err),
                    wall_s=time.perf_counter() - t0)


def regime_of_left_out(task: CandidateTask, values: dict) -> dict:
    """The runs left out for their regime, simulated at the refit's values
    (:func:`identify.fitting.regime_check.regime_check`), JSON-able; its error instead if the
    check itself fails (the refit's numbers stand)."""
    from identify.fitting.regime_check import regime_check
    from identify.model.laws import get_law
    from identify.model.symbolic import Model

    try:
        return regime_check(Model(get_law(task.law)), values, task.regime_runs).to_json()
    except Exception as err:
        return dict(error=f"{type(err).__name__}: {err}")


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


def _needed(task: CandidateTask, dk: int, n_obs: int) -> float:
    """The fall of χ² below the current model's that the screen of :func:`_could_be_named`
    asks of a candidate with ``dk`` more free dimensions."""
    from scipy import stats

    from identify.model.effects import get_effect

    if not get_effect(task.effect).nested:
        return 2.0 * dk  # ΔAIC < 0
    dk = max(dk, 1)
    return max(float(stats.chi2.isf(task.screen_p, dk)), dk * math.log(max(n_obs, 2)))


def _give_up(task: CandidateTask, prob, after: int = GIVE_UP_AFTER):
    """The solver's early stop for a candidate refit (after ``after`` iterations,
    :data:`GIVE_UP_AFTER`), or None for the current model and a task that does not know
    the current χ²."""
    if task.effect is None or task.null_chi2 is None or task.null_n_eff is None:
        return None
    from identify.model.effects import get_effect

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


MAGNITUDE_MAX_ITER = 10
"""Iterations of the solve at the realistic magnitude. Measured (four bundled runs): a
2 µN load offset, 40 % of the smallest load, left the continuity 0.07–0.3 µm off for 20
iterations (Δnll ≈ 14 400, not a bound there), 27 s; it ends "not settled"."""
MAGNITUDE_DECISIVE = 100.0
"""Away from continuity (further than GIVE_UP_FEAS), where the early stop is not asked,
the check at the magnitude still stops once its χ² excess, less 2 × GIVE_UP_MARGIN × what
the step promises, exceeds this many times the quantile it is judged by: excluded, its
Δnll a lower bound. Measured on the 8-run diagnosis benchmark (model-made data, no
effect, 2026-11-25): held at 2 µN the load offset's solve wandered 0.06-0.14 µm off
continuity at ½χ² 38 000-41 500 (the refit's 175) for its 10 iterations, the spring
nonlinearity's at ~8400 with 3e-3-0.5 µm off, each ~8 s for "not settled"; past three
iterations both were 1000s of quantiles above, with promises of 0.01-3500."""
FALLBACK_STARTS = 1
"""How many of the starts a refit passed over (a higher χ² at the start than the one it
solved from) it solves as well when it ends worse than the current model (run_candidate)."""
MAGNITUDE_MOVED_Z = 1.0
MAGNITUDE_WIDER = math.sqrt(2.0)
"""A parameter is named as the partner of an effect the data cannot exclude at its
realistic magnitude (:func:`_at_magnitude`) when, with the effect held there, its
estimate moves by at least :data:`MAGNITUDE_MOVED_Z` of its standard errors, or its
standard error grows by :data:`MAGNITUDE_WIDER` or more — half its information or more
gone, a variance inflation of 2 — or it becomes undetermined: were the effect there, its
stated value or its stated uncertainty would not hold. Both are measured against what
the current model states: the standard errors with the effect's parameter held where
the refit has it (at its null, the current model's own), not the refit's, whose freed
parameter may already have unpinned them. (Measured, the damping set: A, μmin and μmax
1.68–1.71×, τ 1.02× at 3896163; 8.0–8.7× and 3.5× at 2eb2dc5, where against the refit's
own, c_extra free at 0 ± 5.3e-5, they were 1.40×, just short; motion blur on model-made
data: ≤ 1.01×.)"""


def _at_magnitude(task: CandidateTask, prob, w: np.ndarray, chi2: float, est: dict, evaluated=None) -> dict:
    """Whether the data can tell a candidate at its realistic magnitude from its refit.

    The local tests (the refit's likelihood gain, its R² with the model's parameters at
    the refit) see a neighbourhood of the null. An effect the data do not show there can
    still be absorbed far from it: measured (damping of c_extra = 2e-5 N s/m, 56× the
    air damping, on the withheld-effect benchmark's 8 runs): the baseline absorbs it with
    A = 0.0236 ± 0.0035 (truth 0.015) at reduced χ² 0.9887; the damping refit sits at
    c_extra = 0 ± 0.9e-6 N s/m with R² 0.009 against the model's parameters (so, locally,
    "not confounded" and 23 standard errors from the truth); yet a fit with c_extra held
    at the truth reaches reduced χ² 0.9889 with A 0.018: the slips of a damped block
    barely depend on c, and A's slip shortening takes its place.

    Held at 2e-5 from the baseline's point the χ² does not even change (Δnll −1.1):
    simulated, slips shorten with c up to ~2e-5 N s/m at A = 0.015 and not beyond, and
    not at all at A = 0.0236 — past that much damping (from A or c) a slip ends without
    overshoot. So it is the standard errors that tell: with c held there the baseline's
    A, μmax and μmin are confounded (A ± 0.0117 against ± 0.0035; at 2eb2dc5 ± 0.0268
    against ± 0.0033). The reference is the baseline's own standard error, c held at the
    refit's value, not the refit's with c free: on that set the refit's c_extra is
    0 ± 5.3e-5 and its A ± 0.019, which made the ± 0.0268 look only 1.4× wider.

    So the candidate is solved again with its parameter held at the realistic magnitude
    (from the refit, same mode sequence), and its χ² compared with the refit's: within
    the χ²₁ quantile at ``screen_p`` (6.6 at 0.01) the magnitude is not excluded, and
    the parameters it moves or unpins (:data:`MAGNITUDE_WIDER`) are its partners (none:
    the data do not see it there). The solve stops as soon as it is within that
    quantile, or once even :data:`GIVE_UP_MARGIN` times what its step still promises
    cannot bring it there (then its Δnll is a lower bound); away from continuity, where
    that promise says less, only with :data:`MAGNITUDE_DECISIVE` times the quantile to
    spare."""
    from scipy import stats

    name, value = task.magnitude
    names = prob.theta.names
    i = names.index(name)
    vals = dict(zip(names, (float(v) for v in prob.theta.from_scaled(w[: prob.n_theta]))))
    target = float(prob.theta.to_scaled({**vals, name: float(value)})[i])
    if not prob.theta.lo[i] <= target <= prob.theta.hi[i]:
        return dict(parameter=name, value=float(value), absorbed=None,
                    error="the realistic magnitude lies outside the candidate's bounds")
    ref = min(chi2, task.null_chi2) if task.null_chi2 is not None else chi2
    need = float(stats.chi2.isf(task.screen_p, 1))
    const = prob.chi2_constant()

    def stopper(beyond: float, within: bool):
        def stop(it: int, half_chi2: float, promised: float) -> bool:
            d = 2.0 * half_chi2 + const - ref
            if within and d <= need:
                return True
            return it > GIVE_UP_AFTER and d - 2.0 * GIVE_UP_MARGIN * max(promised, 0.0) > beyond
        return stop

    # near continuity: within the quantile, or past it; away from continuity only past
    # MAGNITUDE_DECISIVE times it (a point there that looks absorbed is no evidence)
    stop, decisive = stopper(need, within=True), stopper(MAGNITUDE_DECISIVE * need, within=False)

    w0 = np.array(w, float)
    w0[i] = target
    give_up0, far0, opts0 = prob.give_up, getattr(prob, "give_up_far", None), prob.opts
    horizons = np.array(prob.ev_M, copy=True)
    try:
        # (the arcs may be resized: the refit's record has taken its own horizons already)
        if prob.E:
            w0 = prob.settle_arcs(w0)
        prob.give_up, prob.give_up_far = stop, decisive
        prob.opts = replace(opts0, max_iter=min(opts0.max_iter, MAGNITUDE_MAX_ITER))
        sol = prob.solve(w0, fixed={i: target})
        if (task.regime_runs and not sol.get("success") and sol["status"] != GAVE_UP
                and np.isfinite(sol["f"]) and 2.0 * float(sol["f"]) + const - ref <= need):
            # the runs left out are read at this point (below), which fits as well so far:
            # finished towards continuity, where its χ² is the model's. Measured
            # (rejuvenation held at 1 µm): 10 iterations left it 2.9 nm off continuity
            more = prob.solve(sol["w"], fixed={i: target})
            if np.isfinite(more["f"]):
                sol = dict(more, iterations=int(sol["iterations"]) + int(more["iterations"]))
    finally:
        prob.give_up, prob.give_up_far, prob.opts = give_up0, far0, opts0
    chi2_m = 2.0 * float(sol["f"]) + const
    dnll = 0.5 * (chi2_m - ref)
    # judged only at a point the solver vouches for: converged, or stopped by the rules
    # above (``stop`` within GIVE_UP_FEAS of continuity, ``decisive`` anywhere, its point
    # then perhaps far off continuity: the Δnll a lower bound by a wide margin); else not settled
    settled = (bool(sol.get("success")) or sol["status"] == GAVE_UP) and np.isfinite(dnll)
    # held at the magnitude and fitting *better* than its own refit by more than the
    # quantile: no parameter of the model stands in for it there; the refit ended in a
    # local solution near its null (a start the solve never saw), which the report says
    better = bool(settled and 2 * dnll < -need)
    absorbed = bool(-need <= 2 * dnll <= need) if settled else None
    got = dict(zip(names, (float(v) for v in prob.theta.from_scaled(sol["w"][: prob.n_theta]))))
    se_m, stated = {}, {}
    if absorbed:
        # with the effect held at its magnitude, and, as the reference, held where the
        # refit has it (at its null: the current model's own standard errors)
        se_m = _held_stderrs(prob, sol["w"], i)
        # (the refit's own evaluation at w, the solve since having moved the arcs' last
        # point; not when settling the arcs resized them: the reference and se_m must
        # come from one problem)
        same = evaluated is not None and np.array_equal(horizons, prob.ev_M)
        stated = _held_stderrs(prob, w, i, evaluated if same else None) if se_m else {}
    moved = []
    for n in names:
        se_refit = (est.get(n) or {}).get("stderr")
        se = stated.get(n) or se_refit
        if n == name or not se or not np.isfinite(se) or se <= 0:
            continue
        m = dict(parameter=n, value=vals[n], at_magnitude=got[n], z=float((got[n] - vals[n]) / se), stderr=float(se),
                 stderr_refit=float(se_refit) if se_refit and np.isfinite(se_refit) else None,
                 # "held": the current model's (the effect held at the refit's value); "refit":
                 # that covariance failed or left this parameter undetermined
                 stderr_reference="held" if stated.get(n) else "refit")
        if se_m:
            s2 = se_m.get(n)
            ok = s2 is not None and np.isfinite(s2)
            m.update(stderr_at_magnitude=float(s2) if ok else None, wider=float(s2 / se) if ok else None,
                     undetermined=not ok)
        m["partner"] = bool(absorbed and (abs(m["z"]) >= MAGNITUDE_MOVED_Z or m.get("undetermined")
                                          or (m.get("wider") or 0.0) >= MAGNITUDE_WIDER))
        moved.append(m)

    def weight(m):  # each criterion in units of its own threshold
        return math.inf if m.get("undetermined") else max(abs(m["z"]) / MAGNITUDE_MOVED_Z,
                                                          (m.get("wider") or 0.0) / MAGNITUDE_WIDER)

    moved.sort(key=lambda m: (not m["partner"], -weight(m), m["parameter"]))
    partners = [m["parameter"] for m in moved if m["partner"]]
    out = dict(parameter=name, value=float(value), chi2=float(chi2_m), delta_nll=float(dnll),
               needed_delta_nll=0.5 * need, absorbed=absorbed, better=better, partners=partners,
               moved=moved[:max(4, len(partners))], stderr_checked=bool(se_m), status=sol["status"],
               iterations=int(sol["iterations"]), lower_bound=bool(sol["status"] == GAVE_UP and absorbed is False))
    if task.regime_runs:
        # The runs left out for their regime, at the held values: with its parameter at
        # the magnitude and the model's own refitted to the runs fitted, does the effect
        # make them? (identify.diagnosis.regime_notes.held_evidence). Measured (withheld rejuvenation,
        # dc = 1 µm; 2 runs fitted, 6 left out): held at 1 µm the runs fitted give χ²
        # 2744.73 against the current model's 2744.97, and all 6 come out as the data's
        # (χ² 0, against 54.3 at the current values); on top of the current values without
        # the refit, 1 µm had shrunk the fitted runs' largest slips (z 5.5, 7.8).
        _, g = prob.evaluate(sol["w"])
        out["continuity_um"] = float(np.abs(g).max()) if g.size else 0.0
        out["regime"] = regime_of_left_out(task, {**task.values, **got})
        # (where a profile over the parameter starts: identify.diagnosis.regime_profile; not JSON)
        out["_start"] = dict(w=np.array(sol["w"], float), ev_M=np.array(prob.ev_M))
    return out


def _held_stderrs(prob, w: np.ndarray, i: int, evaluated=None) -> dict:
    """Each parameter's robust standard error at w with parameter i held (known); {} when
    the covariance fails as a whole (it then says nothing of any one parameter).
    ``evaluated``: the central-difference evaluation at w, when there is one."""
    from identify.fitting.result import standard_errors

    try:
        C = prob.covariance(w, fixed_idx=[i], robust=True, evaluated=evaluated)
    except Exception:
        return {}
    errors = standard_errors(prob.theta, w[: prob.n_theta], C, 1.0)
    se = {n: x[0] for j, (n, x) in enumerate(zip(prob.theta.names, errors)) if j != i}
    return se if any(v is not None and np.isfinite(v) for v in se.values()) else {}


def _could_be_named(task: CandidateTask, chi2: float, n_eff: int, n_obs: int) -> bool:
    """Whether the diagnosis's tests could name this refit (generously: see SCREEN_P);
    the current model itself always counts (its held-out gap decides the verdict)."""
    if task.effect is None or task.null_chi2 is None or task.null_n_eff is None:
        return True
    dnll, dk = 0.5 * (task.null_chi2 - chi2), n_eff - task.null_n_eff
    if not np.isfinite(dnll):
        return False  # the refit is not scored at all
    return bool(2 * dnll > _needed(task, dk, n_obs))


def _estimates(prob, w, ev) -> dict:
    """value, stderr, 95 % interval of every free parameter (robust covariance)."""
    from identify.fitting.result import standard_errors

    tm = prob.theta
    th = w[: prob.n_theta]
    try:
        C = prob.covariance(w, robust=True, evaluated=ev)
    except Exception:
        C = np.full((prob.n_theta, prob.n_theta), np.nan)
    lo, hi = tm.from_scaled(tm.lo), tm.from_scaled(tm.hi)

    def bound(i):
        """'lower'/'upper' where the estimate sits on a bound (its value is the bound's,
        not the data's: a damping at −3e-7 N s/m is the least the model allows)."""
        tol = 1e-6 * max(1.0, abs(tm.lo[i]), abs(tm.hi[i]))
        return "lower" if th[i] - tm.lo[i] <= tol else "upper" if tm.hi[i] - th[i] <= tol else None

    return {n: dict(value=float(v), stderr=se, ci95=list(ci) if ci is not None else None, at_bound=bound(i),
                    bound=float(lo[i] if bound(i) == "lower" else hi[i]) if bound(i) else None)
            for i, (n, v, (se, _, ci)) in enumerate(zip(tm.names, tm.from_scaled(th), standard_errors(tm, th, C, 1.0)))}


def _confounding(prob, w, ev, extra: Sequence[str]) -> dict:
    """How much of each candidate parameter the other free parameters can mimic.

    In the information metric (nuisances eliminated), R² of the candidate's direction
    regressed on the others' (1: exactly absorbed), and the others it leans on most."""
    names = prob.theta.names
    if not extra:
        return {}
    try:
        I = prob.information(w, evaluated=ev)
    except Exception as err:
        return {n: dict(r2=float("nan"), partners=[], note=str(err)) for n in extra}
    if not np.all(np.isfinite(I)):
        # (LAPACK would print "DLASCL parameter number 4 had an illegal value" and return NaN)
        return {n: dict(r2=float("nan"), partners=[], note="the information matrix is not finite at this solution")
                for n in extra}
    out = {}
    for n in extra:
        if n not in names:
            continue
        c = names.index(n)
        others = [i for i in range(len(names)) if names[i] not in extra]
        Icc = I[c, c]
        if not others or Icc <= 0:
            # no information at all on it: as confounded as it gets (nothing to name)
            out[n] = dict(r2=0.0 if Icc > 0 else 1.0, partners=[], confounded=Icc <= 0)
            continue
        Ibb = I[np.ix_(others, others)]
        Ibc = I[others, c]
        coef = np.linalg.lstsq(Ibb, Ibc, rcond=1e-12)[0]
        r2 = float(np.clip(Ibc @ coef / Icc, 0.0, 1.0))
        corr = [(names[i], float(I[i, c] / math.sqrt(max(I[i, i] * Icc, 1e-300)))) for i in others]
        corr.sort(key=lambda t: -abs(t[1]))
        # the top partners always (R² can come from several weak ones)
        out[n] = dict(r2=r2, partners=[dict(parameter=a, score_correlation=b) for a, b in corr[:3]],
                      confounded=bool(r2 > 0.99))
    return out
