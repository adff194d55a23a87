"""The trials of a changed mode sequence: one run solved alone with the parameters held
(:func:`run_alone`, :func:`try_sequence`, :func:`continue_trial`), a trial's χ² judged
against what its frames expect (:func:`excess_chi2`, :func:`excess_parts`), a kept
change taken into the whole problem (:func:`keep_trial`), and the whole problem solved
again with the parameters free once a pass has made its changes (:func:`solve_joint`).
"""

from __future__ import annotations

import copy
import logging
import time
from dataclasses import replace

import numpy as np

from identify.fitting.mode_sequence.carry import with_triggers
from identify.fitting.problem import Problem

__all__ = ["held_options", "run_alone", "run_alone_or_none", "keep_trial", "excess_chi2", "excess_parts",
           "try_sequence", "continue_trial", "solve_joint"]

log = logging.getLogger(__name__)


def held_options(opts):
    """``opts`` with no parameter free: a trial's NLP holds them (FitOptions, rightly,
    refuses that for a fit, so the copy bypasses its checks)."""
    o = copy.copy(opts)
    object.__setattr__(o, "free", ())
    object.__setattr__(o, "bounds", {})
    return o


def _run_index(prob, i: int) -> np.ndarray:
    """Indices in ``prob``'s w of run i's own variables (offset, plateaus, phase, arc
    starts), in the order a problem of run i alone lays them out."""
    parts = [[prob.i_off + i]] if prob.n_off else []
    parts.append(prob.i_x + np.nonzero(prob.pl_run == i)[0])
    parts.append([prob.i_phi + prob.phase_of_run[i]])
    if prob.n_s:
        parts.append(prob.i_s + np.nonzero(prob.ev_run == i)[0])
    return np.concatenate(parts).astype(int)


def run_alone(prob, w, i: int, model, opts, say):
    """(problem, w) of run i of ``prob`` alone, the parameters held at ``w``'s and the
    arcs sized as in ``prob``: at that w its residuals are ``prob``'s rows of run i.
    A trial on it costs one run's arcs, without their parameter derivatives, instead of
    every run's. Measured on the 8-run model-made set of :mod:`identify.simulation.withheld` (both
    fits side by side on the two cores): the same 44 trials and kept changes, the same
    estimates; the ambiguous pass 21 -> 13 s, the misfit pass 88 -> 41 s (its trials at
    a 10 Hz slip where nothing helps 19 -> 4 s: the rest is the joint solves of kept
    changes), the whole fit 153 -> 97 s."""
    sub = Problem([prob.runs[i]], model, prob.params(w[: prob.n_theta]), held_options(opts))
    sub.ev_M = prob.ev_M[prob.ev_run == i].copy()
    sub.counter = prob.counter
    sub.progress = say
    sub.build()
    return sub, np.asarray(w, float)[_run_index(prob, i)]


def _adopt(prob, w, i: int, trial, w_trial, model, values, opts, say):
    """(problem, w) of ``prob`` with run i's sequence and variables from a local trial's
    solution, the other runs and the parameters as in ``w``."""
    full, w0 = with_triggers(prob, w, {i: trial.runs[0].trigger_steps}, model, values, opts, say)
    w0[_run_index(full, i)] = w_trial
    # the trial's solution may slip past an arc's horizon (the trial does not resize);
    # a longer arc changes the next rest, so the starts are synced to the arcs again
    return full, full.settle_arcs(w0)


def keep_trial(prob, best, i, trial, sol, model, values, opts, say):
    """A local trial kept: the run alone converged (the parameters still held), then its
    sequence and solution taken into the whole problem. Returns (problem, solution,
    iterations, wall s); problem and solution are None if the whole problem cannot be
    rebuilt for it (the change is then not made; the iterations were spent). The whole
    problem is solved with the parameters free once the pass has no more changes to try
    (:func:`solve_joint`), not after each: a trial is judged at held parameters anyway, and
    converging its run first means the next trial on that run does not count the run's
    unfinished iterations as its own gain.
    Measured on the 8-run model-made set of :mod:`identify.simulation.withheld` (the machine to
    itself, by the profiler): the five joint solves after its five kept changes took
    5.3 s of a 52 s fit; the one joint solve now takes 1.8 s, and the fit 48.5 s (42.7 s
    with the one arc evaluation less per sizing of :meth:`Problem.size_arcs`)."""
    its, wall = 0, 0.0
    try:
        more = _solve_again(trial, sol["w"], held_options(opts))
        its, wall = more["iterations"], more["wall_s"]
        if np.isfinite(more["f"]):
            sol = more
    except Exception as err:  # the trial's short solution stands
        log.info("converging a kept mode-sequence change alone failed: %s", err)
    try:
        full, w0 = _adopt(prob, best["w"], i, trial, sol["w"], model, values, opts, say)
        r = full.residuals(w0)
    except Exception as err:
        log.info("taking a kept mode-sequence change into the whole problem failed: %s", err)
        return None, None, its, wall
    # (not a loose solution any more: the pass's joint solve, or its failure, decides)
    adopted = {k: v for k, v in best.items() if k != "loose"}
    return full, dict(adopted, w=w0, f=0.5 * float(r @ r), success=False, status=sol["status"]), its, wall


def run_alone_or_none(prob, w, i, model, opts, say):
    """:func:`run_alone`, or None (logged) if run i cannot be set up alone."""
    try:
        sub, w_sub = run_alone(prob, w, i, model, opts, say)
        return sub, w_sub, excess_chi2(sub, sub.residuals(w_sub))
    except Exception as err:
        log.info("run %d alone could not be set up for mode-sequence trials: %s", i, err)
        return None


def excess_chi2(p, r) -> float:
    """χ² above its expectation (χ² − number of observations): comparable across mode
    sequences, which can leave a frame more or less out as moving."""
    return float(np.sum(r ** 2)) + p.chi2_constant() - p.n_observations()


def _split(p, r) -> tuple[float, float]:
    """(frames, triggers) parts of :func:`excess_chi2` for a problem of one run: the plateau
    frames' χ² above their number, the trigger rows' above theirs."""
    g = p.residual_groups()
    n_frames = int(sum(run.plateau_n.sum() for run in p.runs if run.kind == "events"))
    frames = float(np.sum(r[: g["slopes"][1]] ** 2)) + p.chi2_constant() - n_frames
    t0, t1 = g["triggers"]
    return frames, float(np.sum(r[t0:t1] ** 2)) - (p.n_observations() - n_frames)


def excess_parts(before, w_before, after, w_after) -> str:
    """How a trial's excess χ² changed, frames and triggers apart: a change the frames
    pay for is one only the model's triggers ask for."""
    (f0, t0), (f1, t1) = _split(before, before.residuals(w_before)), _split(after, after.residuals(w_after))
    return f"frames {f1 - f0:+.1f}, triggers {t1 - t0:+.1f}"


def try_sequence(prob, w, changes: dict, model, values, short, say):
    """(problem, short solution, excess χ²) of a changed mode sequence; the excess is
    inf when the trial cannot be evaluated (it is then not taken)."""
    try:
        t0 = time.perf_counter()
        trial, w0 = with_triggers(prob, w, changes, model, values, short, say)
        t_build = time.perf_counter() - t0
        sol = trial.solve(w0)
        f = excess_chi2(trial, trial.residuals(sol["w"])) if np.isfinite(sol["f"]) else np.inf
    except Exception as err:
        log.info("mode-sequence trial %s failed: %s", {i: list(map(int, s)) for i, s in changes.items()}, err)
        return None, dict(iterations=0, wall_s=0.0), np.inf
    log.info("mode-sequence trial: build %.2f s, %d iteration(s) %.2f s, excess %.1f",
             t_build, sol["iterations"], sol["wall_s"], f)
    return trial, sol, f


def _solve_again(trial, w, opts) -> dict:
    """The trial's problem solved from ``w`` under ``opts`` (its own were a trial's)."""
    trial.opts = opts
    return trial.solve(w)


def continue_trial(trial, sol, opts, iters: int):
    """A screened (local) trial solved ``iters`` more iterations from where it stopped:
    (that solve, excess χ²), or (None, inf) if it fails."""
    try:
        more = _solve_again(trial, sol["w"], held_options(replace(opts, max_iter=iters)))
        f = excess_chi2(trial, trial.residuals(more["w"])) if np.isfinite(more["f"]) else np.inf
    except Exception as err:
        log.info("continuing a mode-sequence trial failed: %s", err)
        return None, np.inf
    return more, f


def _keep(trial, sol, opts):
    """The whole problem solved to convergence, the parameters free, from the point
    where a pass's kept changes left it (:func:`keep_trial`). Returns (problem, solution,
    iterations, wall s) of that solve."""
    # (if that solve fails, the adopted point stands, its parameters never freed: say so)
    failed = f"{sol.get('status')}; the joint solve after the kept mode-sequence changes failed"
    prob, best = trial, dict(sol, success=False)
    try:
        full = _solve_again(prob, best["w"], opts)
    except Exception as err:  # the adopted point stands
        log.info("solve after a kept mode-sequence move failed: %s", err)
        return prob, dict(best, status=failed), 0, 0.0
    # the joint solve wins even at a higher ½χ²: it starts from the point the kept changes
    # were adopted at and descends a merit that counts the constraints, which that point
    # can still violate (a kept 4-iteration trial point, kept instead, ended calibration
    # seed 1 as not converged)
    if np.isfinite(full["f"]):
        if full["f"] > best["f"]:
            log.info("kept changes solved to %s at ½χ² %.6g, above the adopted point's %.6g",
                     full["status"], full["f"], best["f"])
        best = full
    else:
        best["status"] = failed
    return prob, best, full["iterations"], full["wall_s"]


def solve_joint(prob, best, opts, say):
    """:func:`_keep` for a caller that keeps no iteration count of its own: (problem,
    solution) with the solve's iterations and time added to ``best``'s."""
    say("  the whole problem re-solved with the kept changes, the parameters free")
    its0, wall0 = best["iterations"], best["wall_s"]
    prob, sol, its, wall = _keep(prob, best, opts)
    sol = dict(sol, iterations=its0 + its, wall_s=wall0 + wall)
    return prob, sol


