"""The mode sequence, tried against the model: a slip trigger moved, a slip
inserted or removed, the problem rebuilt for the new sequence, the solution carried
over to it, a short re-solve, and the move kept when χ² falls beyond what the frames it
uses expect.

The detector fixes the sequence from the frames alone; at a few σ of slip length it
places some triggers a step off, merges two slips or splits one. The fitted model says
where it disagrees: a slip whose capacity crossing lies far from where the run's other
slips put theirs, its trigger residual √12·(s − φ) beyond :data:`TRIGGER_GATE`, sits
in another step interval than the sequence gives it. The passes here try moves only
there, so data whose triggers fit pay nothing.

A trial changes one run's sequence, and given the parameters the runs are independent
(each has its own plateaus, offset, phase and arc starts), so a trial solves that run
alone with the parameters held (:func:`_alone`): its χ² change is the whole problem's
at those parameters. Kept changes are solved jointly, the parameters free, once per
pass (:func:`_joint`).

A run with many slips off by whole steps (a phase-locked run of 3σ slips: 16 of its
323 on the 10-run speed benchmark) is first given one trial that moves each of them by
what its residual says (:func:`batch_triggers`), instead of a trial, a re-solve and a
rebuild of the whole problem per slip.
"""

from __future__ import annotations

import copy
import logging
import time
from dataclasses import replace

import numpy as np

from identify.fitting.problem import Problem
from identify.fitting.rundata import make_run_data
from identify.model.symbolic import LENGTH_UNIT

log = logging.getLogger(__name__)


def _carry(old_steps, values, new_steps):
    """Per-slip values (e.g. moving times) carried to a new trigger list: a slip keeps
    its value by position when only triggers moved, an inserted one takes the preceding
    old slip's (the following one is the merged slip, its value inflated)."""
    if values is None:
        return None
    old_steps, values = np.asarray(old_steps), np.asarray(values)
    if len(new_steps) == len(old_steps):
        return values
    prev = np.clip(np.searchsorted(old_steps, new_steps, side="right") - 1, 0, len(old_steps) - 1)
    return values[prev]


def _carry_horizons(old, new) -> np.ndarray:
    """Arc horizons (steps) of the previous problem carried to the new one, never past
    the next trigger."""
    M = np.ones(new.E, int)
    for ri in np.unique(new.ev_run):
        sel_new, sel_old = new.ev_run == ri, old.ev_run == ri
        M[sel_new] = _carry(old.ev_step[sel_old], old.ev_M[sel_old], new.ev_step[sel_new])
    return np.maximum(np.minimum(M, new.ev_gap), 1)


def _carry_solution(old, new, w: np.ndarray) -> np.ndarray:
    """The previous solution as a start for the new mode sequence: parameters, offsets
    and phases as they were; each plateau the position of the old plateau it lies in,
    an inserted plateau its position in the frames; each run's first slip its start
    position, the other starts mid-interval until :meth:`Problem.settle_arcs` sets them
    from the arcs."""
    if new.n_w == old.n_w:
        return w.copy()
    v = np.zeros(new.n_w)  # every entry is set below
    v[: old.i_x] = w[: old.i_x]
    v[new.i_phi : new.i_s] = w[old.i_phi : old.i_s]
    v[new.i_s : new.n_w] = 0.5
    if new.n_s and old.n_s:  # the same runs, each with its first slip, in the same order
        v[new.i_s + new.ev_firsts] = w[old.i_s + old.ev_firsts]
        # a slip whose trigger and predecessor's trigger are where they were keeps its
        # start (Problem.settle_arcs moves it only if its target moved: CARRY_START_TOL)
        same = _unchanged_slips(old, new)
        v[new.i_s + same[:, 1]] = w[old.i_s + same[:, 0]]
    x_old = w[old.i_x : old.i_x + old.P]
    p_new = p_old = 0
    for ri, r in enumerate(new.runs):
        if r.kind != "events":
            continue
        t_old, t_new = old.runs[ri].trigger_steps, r.trigger_steps
        # plateau j of the new run starts after trigger j − 1 (the first at the start)
        for j in range(len(t_new) + 1):
            if j == 0:
                v[new.i_x + p_new + j] = x_old[p_old]
                continue
            k = int(np.searchsorted(t_old, t_new[j - 1], side="right"))
            if k >= 1 and t_old[k - 1] == t_new[j - 1]:
                v[new.i_x + p_new + j] = x_old[p_old + k]
            else:  # inserted: its frames' level, shifted as the solution shifts the old plateau it was in
                q = p_old + k
                v[new.i_x + p_new + j] = (new.pl_x0[p_new + j] - old.pl_x0[q]) / LENGTH_UNIT + x_old[q]
        p_new += len(t_new) + 1
        p_old += len(t_old) + 1
    return v


# A carried start within this distance (units of its trigger interval) of where the
# previous arc's end now puts it is not synced: its arc, integrated at the solution the
# start comes from, is then not integrated again (1e-3 of the interval is 1e-6 µm of slip
# length, START_SCALE_UM; the solutions carried are feasible to 1e-4 µm or better).
CARRY_START_TOL = 1e-3


def _unchanged_slips(old, new) -> np.ndarray:
    """(old index, new index) of the slips with a predecessor whose trigger step and
    predecessor's trigger step are the same in both problems (same run)."""
    def key(p):
        prev = np.r_[-1, p.ev_step[:-1]] if p.E else np.zeros(0)
        return {(int(p.ev_run[e]), int(p.ev_step[e]), int(prev[e])): e for e in p.ev_next}

    ko, kn = key(old), key(new)
    pairs = [(ko[k], e) for k, e in kn.items() if k in ko]
    return np.array(pairs, int).reshape(-1, 2)


# ----------------------------------------------------------------------------- driver
def with_triggers(prob, w, changes: dict, model, values, opts, say):
    """The NLP with the trigger steps of ``changes`` ({run index: steps}) and ``w``
    carried over to it (the frames taken while a block moved carried with their slips)."""
    moving = prob.moving_times(w)
    new_runs = []
    for i, r in enumerate(prob.runs):
        if r.kind != "events":
            new_runs.append(r)
            continue
        steps = changes.get(i, r.trigger_steps)
        new_runs.append(make_run_data(r.events, triggers=steps, moving_s=_carry(r.trigger_steps, moving.get(i), steps)))
    new = Problem(new_runs, model, values, opts)
    new.ev_M = _carry_horizons(prob, new)
    new.counter = prob.counter  # the timing report covers every solve, not just the last
    new.progress = say
    new.build()
    return new, new.settle_arcs(_carry_solution(prob, new, w), keep=CARRY_START_TOL)


def _other_step(steps, detected, j, alt, reach: int = 2):
    """The run's trigger steps with detected slip j at ``alt``; neighbours within
    ``reach`` slips that the mode sequence moved go back to their detected steps (a
    late trigger bends the solution, and the local scores then move its neighbours).
    None when slip j is not where it was detected or two slips would share a step."""
    n = int(detected[j])
    if n not in steps or alt in steps:
        return None
    new = np.where(steps == n, alt, steps)
    det = set(int(d) for d in detected)
    for k in range(max(j - reach, 0), min(j + reach + 1, len(detected))):
        d = int(detected[k])
        if k == j or d in new:
            continue
        moved = [c for c in new if abs(int(c) - d) <= 2 and int(c) not in det and int(c) != alt]
        if len(moved) == 1:
            new = np.where(new == moved[0], d, new)
    new = np.sort(new)
    return new if np.all(np.diff(new) > 0) else None


MAX_TRIGGER_TRIALS = 8
TRIAL_ITER = 4
# The misfit-trigger pass screens each change with SCREEN_ITER iterations and gives only
# the SCREEN_KEEP best the rest of TRIAL_ITER: a location has up to 10 changes, and most
# lose by tens of χ² units at once (measured on seed 28: wrong-way moves lost 57-106)
SCREEN_ITER = 1
SCREEN_KEEP = 3
# A trigger residual √12·(s − φ) beyond this puts the slip's capacity crossing 0.58 of an
# interval from the run's phase φ (½ unless FitOptions.free_phase), where its other
# slips cross: a cycle locks them at one phase (in calibration seed 28's 2.5-σ run the
# triggers away from its errors read −1.0 … +0.6, most −0.3), so a slip far from it is
# the outlier sought. (With a free phase near an interval's edge, a well-placed trigger
# passes 2 only if it strays across the interval from the others.) Measured on the
# bundled FOTAS set: the two moves the ambiguous pass kept had −3.2 and +4.4 at their own
# slip and the next, the six it rejected −0.17 on every neighbour; the late OTS trigger
# (identify.traces.events) left 9.6 two slips after it.
TRIGGER_GATE = 2.0
GATE_REACH = 2  # the slip's own trigger and the next two (where a late one rings)
BATCH_MIN = 3  # slips a run needs a step off, by their residuals, for a batch trial (batch_triggers)
BATCH_REACH = 2  # steps a batch trial moves a slip at most
# A batch trial is kept when none of its moved slips still misfits in its solution and
# it lowers the run's χ² − n_obs by BATCH_GAIN per slip moved (a 3σ gain each on average,
# as identify.fitting.missed asks of an insertion); a moved slip that still misfits has its move
# dropped and the rest is tried again, BATCH_ROUNDS trials at most. Why: on calibration
# seed 14 a batch of 12 moves gained 56 (4.7 a move) and, kept at 1 a move, left the
# passes after it 18 misfit triggers and reduced χ² 1.117 where they alone had reached
# 1.067; on the 10-run speed benchmark's 3σ run, 16 moves gained 1027.
BATCH_GAIN = 9.0
BATCH_ROUNDS = 3


def _trigger_misfit(prob, r: np.ndarray, i: int, n: int, reach: int = GATE_REACH) -> float:
    """Largest |trigger residual| of run i's slip nearest step n and the ``reach`` slips
    after it (a run's first slip has none), in the residual vector ``r``."""
    evs = np.nonzero(prob.ev_run == i)[0]
    if not len(evs):
        return 0.0
    k = int(np.argmin(np.abs(prob.ev_step[evs] - n)))
    t0 = prob.residual_groups()["triggers"][0]
    row = {int(e): t0 + q for q, e in enumerate(prob.ev_next)}
    vals = np.array([r[row[int(e)]] for e in evs[k:k + reach + 1] if int(e) in row], float)
    # a trigger the model cannot evaluate is as misfit as it gets
    return float(np.max(np.where(np.isfinite(vals), np.abs(vals), np.inf))) if vals.size else 0.0


def _held(opts):
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


def _alone(prob, w, i: int, model, opts, say):
    """(problem, w) of run i of ``prob`` alone, the parameters held at ``w``'s and the
    arcs sized as in ``prob``: at that w its residuals are ``prob``'s rows of run i.
    A trial on it costs one run's arcs, without their parameter derivatives, instead of
    every run's. Measured on the 8-run model-made set of :mod:`identify.simulation.withheld` (both
    fits side by side on the two cores): the same 44 trials and kept changes, the same
    estimates; the ambiguous pass 21 -> 13 s, the misfit pass 88 -> 41 s (its trials at
    a 10 Hz slip where nothing helps 19 -> 4 s: the rest is the joint solves of kept
    changes), the whole fit 153 -> 97 s."""
    sub = Problem([prob.runs[i]], model, prob.params(w[: prob.n_theta]), _held(opts))
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


def _kept(prob, best, i, trial, sol, model, values, opts, say):
    """A local trial kept: the run alone converged (the parameters still held), then its
    sequence and solution taken into the whole problem. Returns (problem, solution,
    iterations, wall s); problem and solution are None if the whole problem cannot be
    rebuilt for it (the change is then not made; the iterations were spent). The whole
    problem is solved with the parameters free once the pass has no more changes to try
    (:func:`_joint`), not after each: a trial is judged at held parameters anyway, and
    converging its run first means the next trial on that run does not count the run's
    unfinished iterations as its own gain.
    Measured on the 8-run model-made set of :mod:`identify.simulation.withheld` (the machine to
    itself, by the profiler): the five joint solves after its five kept changes took
    5.3 s of a 52 s fit; the one joint solve now takes 1.8 s, and the fit 48.5 s (42.7 s
    with the one arc evaluation less per sizing of :meth:`Problem.size_arcs`)."""
    its, wall = 0, 0.0
    try:
        more = _solve_again(trial, sol["w"], _held(opts))
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


def _alone_or_none(prob, w, i, model, opts, say):
    """:func:`_alone`, or None (logged) if run i cannot be set up alone."""
    try:
        sub, w_sub = _alone(prob, w, i, model, opts, say)
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


def _parts(before, w_before, after, w_after) -> str:
    """How a trial's excess χ² changed, frames and triggers apart: a change the frames
    pay for is one only the model's triggers ask for."""
    (f0, t0), (f1, t1) = _split(before, before.residuals(w_before)), _split(after, after.residuals(w_after))
    return f"frames {f1 - f0:+.1f}, triggers {t1 - t0:+.1f}"


def _trial(prob, w, changes: dict, model, values, short, say):
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
    if opts.solver == "ipopt":
        trial.build()  # (Ipopt's iteration limit is built into its solver object)
    return trial.solve(w)


def _continue(trial, sol, opts, iters: int):
    """A screened (local) trial solved ``iters`` more iterations from where it stopped:
    (that solve, excess χ²), or (None, inf) if it fails."""
    try:
        more = _solve_again(trial, sol["w"], _held(replace(opts, max_iter=iters)))
        f = excess_chi2(trial, trial.residuals(more["w"])) if np.isfinite(more["f"]) else np.inf
    except Exception as err:
        log.info("continuing a mode-sequence trial failed: %s", err)
        return None, np.inf
    return more, f


def _keep(trial, sol, opts):
    """The whole problem solved to convergence, the parameters free, from the point
    where a pass's kept changes left it (:func:`_kept`). Returns (problem, solution,
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


def _joint(prob, best, opts, say):
    """:func:`_keep` for a caller that keeps no iteration count of its own: (problem,
    solution) with the solve's iterations and time added to ``best``'s."""
    say("  the whole problem re-solved with the kept changes, the parameters free")
    its0, wall0 = best["iterations"], best["wall_s"]
    prob, sol, its, wall = _keep(prob, best, opts)
    sol = dict(sol, iterations=its0 + its, wall_s=wall0 + wall)
    return prob, sol


def ambiguous_triggers(prob, best, model, values, opts, say):
    """Try the other step of each slip whose detected trigger the frames leave ambiguous
    (:data:`identify.traces.events.AMBIGUOUS_RSS`), most ambiguous first, against the model.

    A slip put a step late by the noise on its neighbouring frames loads the model's
    arc with one step too many; the chain of slips after it rings (each plateau is the
    last plus a slip) and the parameters bend to absorb it. The local scores of
    :meth:`Problem.refine_triggers` hold the plateaus at their fitted, already bent,
    levels and miss it (measured: they moved the next slip two steps late instead); a
    short re-solve (:data:`TRIAL_ITER` iterations) does not. Only slips whose own or
    next triggers misfit (:data:`TRIGGER_GATE`) are tried: on data whose triggers fit, a
    trial costs a rebuild and a re-solve and gains nothing (measured on the bundled FOTAS
    set: 8 trials, 2 kept, 42 iterations against 8 without the pass). Each trial also puts the
    neighbours the mode sequence moved back where they were detected (:func:`_other_step`).
    A move is kept when it lowers χ² beyond what the frames it uses expect (χ² − number
    of observations: a trial can leave a frame more or less out as moving), and the
    kept change's run is solved to convergence, the parameters held, before the next
    trial (:func:`_kept`). The whole problem is not solved again here: the misfit pass
    that follows does that once it has made its own changes (its ``unsolved``).
    Returns (problem, solution, slips moved)."""
    from identify.traces.events import AMBIGUOUS_RSS

    cands = []
    for i, r in enumerate(prob.runs):
        if r.kind != "events":
            continue
        sl = r.events.slips
        for j, (alt, m) in enumerate(zip(sl.get("alt_trigger_step", ()), sl.get("alt_margin", ()))):
            if alt >= 0 and m < AMBIGUOUS_RSS:
                cands.append((float(m), i, j, int(alt)))
    if not cands:
        return prob, best, 0
    cands = sorted(cands)
    r_now = prob.residuals(best["w"])
    short = _held(replace(opts, max_iter=TRIAL_ITER))
    moved, tried, fit_there, its, wall = 0, 0, 0, 0, 0.0
    say(f"{len(cands)} ambiguous slip trigger(s): trying the other step of those whose triggers misfit "
        f"(|residual| > {TRIGGER_GATE:g} at the slip or the next {GATE_REACH})")
    for _, i, j, alt in cands:
        n = int(prob.runs[i].events.slips["trigger_step"][j])
        misfit = _trigger_misfit(prob, r_now, i, n)
        if misfit <= TRIGGER_GATE:
            fit_there += 1
            log.info("ambiguous trigger (run %d, step %d) not tried: its triggers fit (|r| <= %.2f)", i, n, misfit)
            continue
        steps = np.asarray(prob.runs[i].trigger_steps, int)
        new_steps = _other_step(steps, np.asarray(prob.runs[i].events.slips["trigger_step"], int), j, alt)
        if new_steps is None:
            continue
        if tried == MAX_TRIGGER_TRIALS:
            log.info("ambiguous triggers: stopped after %d trials", tried)
            break
        tried += 1
        alone = _alone_or_none(prob, best["w"], i, model, opts, say)
        if alone is None:
            continue
        sub, w_sub, now = alone
        trial, sol, f = _trial(sub, w_sub, {0: new_steps}, model, sub.values, short, say)
        if trial is None:
            continue
        its, wall = its + sol["iterations"], wall + sol["wall_s"]
        kept = f < now - 1.0
        say(f"  {prob.runs[i].name}: slip at step {n} tried at {alt}: the run's chi2 - n_obs {now:.1f} -> {f:.1f} "
            f"({_parts(sub, w_sub, trial, sol['w'])}), " + ("kept" if kept else "not kept"))
        if not kept:
            continue
        full, adopted, it_full, s_full = _kept(prob, best, i, trial, sol, model, values, opts, say)
        its, wall = its + it_full, wall + s_full
        if full is None:
            continue
        prob, best, moved = full, adopted, moved + 1
        r_now = prob.residuals(best["w"])
    if fit_there:
        say(f"  {fit_there} other ambiguous trigger(s) not tried: the model's triggers fit there")
    best["iterations"], best["wall_s"] = best["iterations"] + its, best["wall_s"] + wall
    return prob, best, moved




def _trigger_residuals(prob, r: np.ndarray):
    """(trigger residual, run, slip index in its run) of every slip with a trigger row
    in ``r``; a residual the model cannot evaluate is inf."""
    t0 = prob.residual_groups()["triggers"][0]
    for q, e in enumerate(prob.ev_next):
        v = float(r[t0 + q])
        i = int(prob.ev_run[e])
        yield (v if np.isfinite(v) else np.inf), i, int(np.searchsorted(prob.runs[i].trigger_steps, prob.ev_step[e]))


def _predicted_shifts(prob, r: np.ndarray) -> dict:
    """{run index: {slip index in its run: shift in steps}} for the slips whose own
    trigger residual exceeds :data:`TRIGGER_GATE` while the slip before theirs fits:
    the shift round(r/√12) that brings the capacity crossing into the run's phase
    (r = √12·(s − φ), s in units of the step interval). A slip after a misfit one is
    left out: its residual is the ringing of its predecessor, not its own."""
    res: dict = {}
    for v, i, k in _trigger_residuals(prob, r):
        res.setdefault(i, {})[k] = v
    out: dict = {}
    for i, by_k in res.items():
        for k, v in by_k.items():
            before = by_k.get(k - 1, 0.0)  # (a run's second slip: its first has no residual)
            if not (np.isfinite(v) and abs(v) > TRIGGER_GATE and abs(before) <= TRIGGER_GATE):
                continue
            d = int(np.clip(np.rint(v / np.sqrt(12.0)), -BATCH_REACH, BATCH_REACH))
            if d:
                out.setdefault(i, {})[k] = d
    return out


def batch_triggers(prob, best, model, values, opts, say):
    """Move, in one trial per run, every slip whose trigger residual says how many
    steps off it is (:func:`_predicted_shifts`), before the passes that try one change
    at a time.

    Why: a run of slips a few σ of a frame long can have many triggers a step off, each
    one kept by the passes after a trial, a re-solve of its run and a rebuild of the
    whole problem (~4 s each on the 10-run speed benchmark, whose 3σ run at 100 Hz had
    15 such changes kept and 12 triggers still misfit when the trial budget was spent).
    Runs with fewer than :data:`BATCH_MIN` such slips are left to those passes. A
    moved slip that still misfits in the trial's solution has its move dropped and the
    rest is tried again; a trial is kept when none does and the run's χ² − n_obs falls
    by :data:`BATCH_GAIN` per slip moved. The passes after it still try whatever
    misfits. Returns (problem, solution, slips moved); the whole problem is left to
    be solved by the misfit pass (its ``unsolved``)."""
    if int(opts.sequence_trials) <= 0 or not prob.E:
        return prob, best, 0
    shifts = _predicted_shifts(prob, prob.residuals(best["w"]))
    short = _held(replace(opts, max_iter=TRIAL_ITER))
    moved, its, wall = 0, 0, 0.0
    for i in sorted(shifts, key=lambda i: -len(shifts[i])):
        if len(shifts[i]) < BATCH_MIN:
            continue
        run = prob.runs[i]
        steps = np.array(run.trigger_steps, int)
        alone = _alone_or_none(prob, best["w"], i, model, opts, say)
        if alone is None:
            continue
        sub, w_sub, now = alone
        moves, kept = dict(shifts[i]), False
        for _ in range(BATCH_ROUNDS):
            new = steps.copy()
            for k, d in moves.items():
                new[k] += d
            if not (np.all(np.diff(new) > 0) and new[0] >= 0 and new[-1] <= int(run.events.steps.max())):
                log.info("batch of trigger moves on run %d not tried: two slips would share a step", i)
                break
            trial, sol, f = _trial(sub, w_sub, {0: new}, model, sub.values, short, say)
            its, wall = its + sol["iterations"], wall + sol["wall_s"]
            if trial is None:
                break
            # a moved slip whose trigger still misfits in the trial's solution was moved
            # wrong, or not far enough: its move is dropped and the rest tried again
            wrong = {k for _, _, k in _flagged(trial, trial.residuals(sol["w"]))} & set(moves)
            n = len(moves)
            kept = not wrong and f < now - BATCH_GAIN * n
            say(f"  {run.name}: {n} slip trigger(s) moved where their residuals put them "
                f"(" + ", ".join(f"{int(steps[k])}{d:+d}" for k, d in sorted(moves.items())) + "): "
                f"the run's chi2 - n_obs {now:.1f} -> {f:.1f}"
                + (f", {len(wrong)} of them still misfit" if wrong else "") + (", kept" if kept else ", not kept"))
            if kept or not wrong or n - len(wrong) < BATCH_MIN:
                break
            moves = {k: d for k, d in moves.items() if k not in wrong}
        if not kept:
            continue
        full, adopted, it_full, s_full = _kept(prob, best, i, trial, sol, model, values, opts, say)
        its, wall = its + it_full, wall + s_full
        if full is None:
            continue
        prob, best, moved = full, adopted, moved + len(moves)
    best["iterations"], best["wall_s"] = best["iterations"] + its, best["wall_s"] + wall
    return prob, best, moved


def _flagged(prob, r: np.ndarray) -> list:
    """(|trigger residual|, run, slip index in its run) of the slips whose trigger
    residual exceeds :data:`TRIGGER_GATE` (one the model cannot evaluate counts as
    infinite), worst first."""
    out = [(abs(v), i, k) for v, i, k in _trigger_residuals(prob, r) if abs(v) > TRIGGER_GATE]
    return sorted(out, key=lambda c: -c[0])


def _moves(steps: np.ndarray, k: int, split: int | None, last_step: int) -> list:
    """(label, trigger steps, kind, slips changed) of the local changes tried for a run
    whose slip k (k ≥ 1: it has a trigger residual) misfits: the slip a step either
    way; the slip before it (a misplaced slip spoils the next one's trigger); either
    pair the slip is in, together (two slips a step early in a row move only together:
    each alone loses); a slip inserted at ``split`` between the slip and the one before
    (a merged pair); the slip removed (a spurious one). Changes that would put two slips
    at one step, or a slip outside the run, are left out."""
    T = [int(t) for t in steps]
    out = []

    def shifted(idx, d):
        new = list(T)
        for j in idx:
            new[j] += d
        return new

    for d in (-1, 1):
        out.append((f"slip at step {T[k]} to {T[k] + d}", shifted([k], d), "moved", 1))
        out.append((f"slip at step {T[k - 1]} to {T[k - 1] + d}", shifted([k - 1], d), "moved", 1))
        for a in (k - 1, k):
            if a + 1 < len(T):
                out.append((f"slips at steps {T[a]}, {T[a + 1]} to {T[a] + d}, {T[a + 1] + d}",
                            shifted([a, a + 1], d), "moved", 2))
    if split is not None and T[k - 1] < split < T[k]:
        out.append((f"slip inserted at step {split}", sorted(T + [split]), "inserted", 1))
    out.append((f"slip at step {T[k]} removed", T[:k] + T[k + 1:], "removed", 1))
    # (not past the run's last step: the detector puts a run's last slip at it, at times)
    ok = lambda s: all(b > a for a, b in zip(s, s[1:])) and s[0] >= 0 and s[-1] <= last_step  # noqa: E731
    return [m for m in out if ok(m[1])]


LOCAL_SLIPS = 3  # a change's reach along the run, in slips: a plateau chains to the next few


def _local(before, after) -> tuple:
    """Key of the change from trigger steps ``before`` to ``after``: the triggers it
    changed and ``LOCAL_SLIPS`` unchanged ones either side (the run's ends where there
    are fewer). The same change reached from another flagged slip has the same key, and
    so has a change tried before a change kept further along the run."""
    before = [int(t) for t in before]
    changed = sorted(set(before) ^ {int(t) for t in after})
    if not changed:
        return ()
    lo_i = int(np.searchsorted(before, changed[0])) - LOCAL_SLIPS
    hi_i = int(np.searchsorted(before, changed[-1], side="right")) + LOCAL_SLIPS - 1
    lo = before[lo_i] if lo_i >= 0 else -np.inf
    hi = before[hi_i] if hi_i < len(before) else np.inf
    return (lo, hi) + tuple(int(t) for t in after if lo <= t <= hi)


def misfit_triggers(prob, best, model, values, opts, say, unsolved: bool = False):
    """Repair the mode sequence where the fitted model's triggers misfit.

    The detector's sequence, after the local refinements of :meth:`Problem.refine_triggers`,
    :func:`identify.fitting.missed.missed_slips` and the ambiguous-trigger pass, can still be
    wrong where slips are a few σ of a frame: on calibration seed 28 a run with 230 nm
    slips every 5 steps (2.5 σ) kept one missed slip, two slips a step late, a pair a step
    early and one spurious slip. The fit then bent μmin 6 % low and A 20 % high (−9.8 σ)
    at reduced χ² 1.10; with the true sequence χ² fell by 575 and every estimate came
    within 3 %. Each of those errors left trigger residuals of 3 to 12.5 at or after it,
    where the run's other triggers read −1.0 … +0.6.

    So, worst first, at each slip whose trigger residual exceeds :data:`TRIGGER_GATE`,
    the local changes of :func:`_moves` are each solved for :data:`SCREEN_ITER`
    iteration and the :data:`SCREEN_KEEP` best on to :data:`TRIAL_ITER`; the best is
    kept when it lowers χ² − n_obs by more than 1, its run solved to convergence, and
    the residuals read again. Measured on seed 28 from the fitted
    sequence: the insertion gained 473, moving either late slip 33-34, the early pair 30;
    single moves in the wrong direction lost 57 to 106. At most ``opts.sequence_trials``
    trials (0: the pass is off). Errors that leave the slip's own trigger and the next
    within the gate are out of its reach, as is a run's first slip (it has no trigger
    residual).

    A kept change is solved on its run alone, the parameters held (:func:`_kept`); once
    no flagged slip has a change left to try, the whole problem is solved with the
    parameters free (:func:`_keep`) and the triggers read again, and the pass goes on
    if that flags new ones. ``unsolved``: ``best`` already carries changes kept at held
    parameters (the ambiguous pass's), so the whole problem is solved at the end even
    if this pass keeps nothing. Returns (problem, solution, counts by kind)."""
    from identify.fitting.missed import best_split

    counts = dict(moved=0, inserted=0, removed=0)
    budget = int(opts.sequence_trials)
    r_now = prob.residuals(best["w"])
    flagged = _flagged(prob, r_now) if budget > 0 else []
    if not flagged:
        if unsolved:
            prob, best = _joint(prob, best, opts, say)
        return prob, best, counts
    log.info("triggers that misfit (|r|, run, slip): %s", flagged)
    screen = _held(replace(opts, max_iter=SCREEN_ITER))
    its, wall, trials = 0, 0.0, 0
    tried: set = set()  # (run, local key) of the changes tried, and the undoing of those kept
    say(f"mode sequence: trying local changes where slip triggers misfit (|residual| > {TRIGGER_GATE:g})")
    pending = unsolved  # changes kept at held parameters, the whole problem not solved since
    while trials < budget:
        target = None
        for _, i, k in _flagged(prob, r_now):
            run = prob.runs[i]
            e_prev = int(np.nonzero(prob.ev_run == i)[0][k - 1])
            split = best_split(prob, best["w"], e_prev)
            moves = [m for m in _moves(run.trigger_steps, k, split and split[1], int(run.events.steps.max()))
                     if (i, _local(run.trigger_steps, m[1])) not in tried]
            if moves:
                target = (i, k, moves)
                break
        if target is None:
            if not pending:
                break
            # the parameters free: the triggers move a little everywhere, and may flag others
            prob, best = _joint(prob, best, opts, say)
            pending = False
            r_now = prob.residuals(best["w"])
            continue
        i, k, moves = target
        before = prob.runs[i].trigger_steps
        name, at = prob.runs[i].name, int(before[k])
        alone = _alone_or_none(prob, best["w"], i, model, opts, say)
        if alone is None:
            tried.update((i, _local(before, m[1])) for m in moves)  # (not tried again)
            continue
        sub, w_sub, now = alone
        results = []
        for label, steps, kind, n in moves[: budget - trials]:
            trials += 1
            tried.add((i, _local(before, steps)))
            trial, sol, f = _trial(sub, w_sub, {0: np.array(steps, int)}, model, sub.values, screen, say)
            its, wall = its + sol["iterations"], wall + sol["wall_s"]
            if trial is not None:
                results.append([f, label, kind, n, trial, sol])
        if not results:
            continue
        rank = lambda c: c[0] if np.isfinite(c[0]) else np.inf  # noqa: E731
        for c in sorted(results, key=rank)[:SCREEN_KEEP]:
            if np.isfinite(c[0]):
                more, c[0] = _continue(c[4], c[5], opts, TRIAL_ITER - SCREEN_ITER)
                if more is not None:  # (its χ², even if higher: one iteration's may not be feasible)
                    its, wall, c[5] = its + more["iterations"], wall + more["wall_s"], more
        f, label, kind, n, trial, sol = min(results, key=rank)
        if not f < now - 1.0:
            say(f"  {name}: no change at step {at} lowers chi2 (best: {label}, "
                f"the run's chi2 - n_obs {now:.1f} -> {f:.1f})")
            continue
        say(f"  {name}: {label}: the run's chi2 - n_obs {now:.1f} -> {f:.1f} "
            f"({_parts(sub, w_sub, trial, sol['w'])}), kept")
        full, adopted, it_full, s_full = _kept(prob, best, i, trial, sol, model, values, opts, say)
        its, wall = its + it_full, wall + s_full
        if full is None:
            continue
        counts[kind] += n
        prob, best, pending = full, adopted, True
        tried.add((i, _local(prob.runs[i].trigger_steps, before)))  # (its undoing)
        r_now = prob.residuals(best["w"])
    if pending:  # (the trial budget spent)
        prob, best = _joint(prob, best, opts, say)
        r_now = prob.residuals(best["w"])
    left = len(_flagged(prob, r_now))
    say(f"  {trials} trial(s); " + (f"{left} slip trigger(s) still misfit" if left else "every trigger fits")
        + (" (trial budget spent)" if left and trials >= budget else ""))
    # (best carries the iterations before the pass and of its joint solves: add the trials')
    best["iterations"], best["wall_s"] = best["iterations"] + its, best["wall_s"] + wall
    return prob, best, counts
