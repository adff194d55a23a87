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
alone with the parameters held (:func:`identify.fitting.mode_sequence.trials.run_alone`): its
χ² change is the whole problem's at those parameters. Kept changes are solved jointly,
the parameters free, once per pass (:func:`identify.fitting.mode_sequence.trials.solve_joint`).

A run with many slips off by whole steps (a phase-locked run of 3σ slips: 16 of its
323 on the 10-run speed benchmark) is first given one trial that moves each of them by
what its residual says (:func:`batch_triggers`), instead of a trial, a re-solve and a
rebuild of the whole problem per slip.

The passes are here; the problem rebuilt for a new sequence is in
:mod:`identify.fitting.mode_sequence.carry`, the trials' machinery in
:mod:`identify.fitting.mode_sequence.trials`.
"""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np

from identify.fitting.mode_sequence.carry import CARRY_START_TOL as CARRY_START_TOL
from identify.fitting.mode_sequence.carry import with_triggers as with_triggers
from identify.fitting.mode_sequence.trials import (
    continue_trial,
    excess_parts,
    held_options,
    keep_trial,
    run_alone_or_none,
    solve_joint,
    try_sequence,
)
from identify.fitting.mode_sequence.trials import excess_chi2 as excess_chi2

log = logging.getLogger(__name__)


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
# as identify.fitting.mode_sequence.missed asks of an insertion); a moved slip that still misfits has its move
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
    trial (:func:`keep_trial`). The whole problem is not solved again here: the misfit pass
    that follows does that once it has made its own changes (its ``unsolved``).
    Returns (problem, solution, slips moved)."""
    from identify.traces.events import AMBIGUOUS_RSS

    if "ambiguous" not in opts.sequence_passes:
        return prob, best, 0
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
    short = held_options(replace(opts, max_iter=TRIAL_ITER))
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
        alone = run_alone_or_none(prob, best["w"], i, model, opts, say)
        if alone is None:
            continue
        sub, w_sub, now = alone
        trial, sol, f = try_sequence(sub, w_sub, {0: new_steps}, model, sub.values, short, say)
        if trial is None:
            continue
        its, wall = its + sol["iterations"], wall + sol["wall_s"]
        kept = f < now - 1.0
        say(f"  {prob.runs[i].name}: slip at step {n} tried at {alt}: the run's chi2 - n_obs {now:.1f} -> {f:.1f} "
            f"({excess_parts(sub, w_sub, trial, sol['w'])}), " + ("kept" if kept else "not kept"))
        if not kept:
            continue
        full, adopted, it_full, s_full = keep_trial(prob, best, i, trial, sol, model, values, opts, say)
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
    if int(opts.sequence_trials) <= 0 or "batch" not in opts.sequence_passes or not prob.E:
        return prob, best, 0
    shifts = _predicted_shifts(prob, prob.residuals(best["w"]))
    short = held_options(replace(opts, max_iter=TRIAL_ITER))
    moved, its, wall = 0, 0, 0.0
    for i in sorted(shifts, key=lambda i: -len(shifts[i])):
        if len(shifts[i]) < BATCH_MIN:
            continue
        run = prob.runs[i]
        steps = np.array(run.trigger_steps, int)
        alone = run_alone_or_none(prob, best["w"], i, model, opts, say)
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
            trial, sol, f = try_sequence(sub, w_sub, {0: new}, model, sub.values, short, say)
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
        full, adopted, it_full, s_full = keep_trial(prob, best, i, trial, sol, model, values, opts, say)
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
    :func:`identify.fitting.mode_sequence.missed.missed_slips` and the ambiguous-trigger pass, can still be
    wrong where slips are a few σ of a frame: on calibration seed 28 a state with 230 nm
    slips every 5 steps (2.5 σ) kept one missed slip, two slips a step late, a pair a step
    early and one spurious slip. The fit then bent μmin 6 % low and A 20 % high (−9.8 σ)
    at reduced χ² 1.10; with the true sequence χ² fell by 575 and every estimate came
    within 3 %. Each of those errors left trigger residuals of 3 to 12.5 at or after it,
    where the run's other triggers read −1.0 … +0.6.

    So, worst first, at each slip whose trigger residual exceeds :data:`TRIGGER_GATE`,
    the local changes of :func:`_moves` are each solved for :data:`SCREEN_ITER`
    iteration and the :data:`SCREEN_KEEP` best on to :data:`TRIAL_ITER`; the best is
    kept when it lowers χ² − n_obs by more than 1, its state solved to convergence, and
    the residuals read again. Measured on seed 28 from the fitted
    sequence: the insertion gained 473, moving either late slip 33-34, the early pair 30;
    single moves in the wrong direction lost 57 to 106. At most ``opts.sequence_trials``
    trials (0: the pass is off). Errors that leave the slip's own trigger and the next
    within the gate are out of its reach, as is a run's first slip (it has no trigger
    residual).

    A kept change is solved on its state alone, the parameters held (:func:`keep_trial`); once
    no flagged slip has a change left to try, the whole problem is solved with the
    parameters free (:func:`solve_joint`) and the triggers read again, and the pass goes
    on if that flags new ones. ``unsolved``: ``best`` already carries changes kept at held
    parameters (the ambiguous pass's), so the whole problem is solved at the end even
    if this pass keeps nothing. Returns (problem, solution, counts by kind)."""
    counts = dict(moved=0, inserted=0, removed=0)
    budget = int(opts.sequence_trials) if "misfit" in opts.sequence_passes else 0
    r_now = prob.residuals(best["w"])
    flagged = _flagged(prob, r_now) if budget > 0 else []
    if not flagged:
        if unsolved:
            prob, best = solve_joint(prob, best, opts, say)
        return prob, best, counts
    log.info("triggers that misfit (|r|, run, slip): %s", flagged)
    state = _MisfitPass(prob, best, r_now, counts, model, values, opts, say, budget, pending=unsolved)
    say(f"mode sequence: trying local changes where slip triggers misfit (|residual| > {TRIGGER_GATE:g})")
    while state.trials < budget:
        target = state.next_target()
        if target is None:
            if not state.pending:
                break
            # the parameters free: the triggers move a little everywhere, and may flag others
            state.solve_joint()
            continue
        state.try_at(*target)
    if state.pending:  # (the trial budget spent)
        state.solve_joint()
    prob, best, trials = state.prob, state.best, state.trials
    left = len(_flagged(prob, state.r_now))
    say(f"  {trials} trial(s); " + (f"{left} slip trigger(s) still misfit" if left else "every trigger fits")
        + (" (trial budget spent)" if left and trials >= budget else ""))
    # (best carries the iterations before the pass and of its joint solves: add the trials')
    best["iterations"], best["wall_s"] = best["iterations"] + state.its, best["wall_s"] + state.wall
    return prob, best, counts


class _MisfitPass:
    """The state of :func:`misfit_triggers` as it goes: the problem and solution now, their
    trigger residuals, the changes tried, the trials and the iterations and time they took."""

    def __init__(self, prob, best, r_now, counts, model, values, opts, say, budget: int, pending: bool):
        self.prob, self.best, self.r_now, self.counts = prob, best, r_now, counts
        self.model, self.values, self.opts, self.say, self.budget = model, values, opts, say, budget
        self.screen = held_options(replace(opts, max_iter=SCREEN_ITER))
        self.its, self.wall, self.trials = 0, 0.0, 0
        self.tried: set = set()  # (run, local key) of the changes tried, and the undoing of those kept
        self.pending = pending  # changes kept at held parameters, the whole problem not solved since

    def next_target(self):
        """(run, slip, local changes not tried yet) at the worst flagged slip that has any,
        or None."""
        from identify.fitting.mode_sequence.missed import best_split

        prob = self.prob
        for _, i, k in _flagged(prob, self.r_now):
            run = prob.runs[i]
            e_prev = int(np.nonzero(prob.ev_run == i)[0][k - 1])
            split = best_split(prob, self.best["w"], e_prev)
            moves = [m for m in _moves(run.trigger_steps, k, split and split[1], int(run.events.steps.max()))
                     if (i, _local(run.trigger_steps, m[1])) not in self.tried]
            if moves:
                return i, k, moves
        return None

    def solve_joint(self) -> None:
        """The whole problem solved with the parameters free and its residuals read again."""
        self.prob, self.best = solve_joint(self.prob, self.best, self.opts, self.say)
        self.pending = False
        self.r_now = self.prob.residuals(self.best["w"])

    def try_at(self, i: int, k: int, moves: list) -> None:
        """The changes ``moves`` at run i's slip k screened on the run alone, the best few
        solved on, and the best of them kept if it lowers the run's χ² − n_obs by more than 1."""
        before = self.prob.runs[i].trigger_steps
        name, at = self.prob.runs[i].name, int(before[k])
        alone = run_alone_or_none(self.prob, self.best["w"], i, self.model, self.opts, self.say)
        if alone is None:
            self.tried.update((i, _local(before, m[1])) for m in moves)  # (not tried again)
            return
        sub, w_sub, now = alone
        results = self._screen(i, before, sub, w_sub, moves)
        if not results:
            return
        f, label, kind, n, trial, sol = self._finish(results)
        if not f < now - 1.0:
            self.say(f"  {name}: no change at step {at} lowers chi2 (best: {label}, "
                     f"the run's chi2 - n_obs {now:.1f} -> {f:.1f})")
            return
        self.say(f"  {name}: {label}: the run's chi2 - n_obs {now:.1f} -> {f:.1f} "
                 f"({excess_parts(sub, w_sub, trial, sol['w'])}), kept")
        self._keep(i, before, trial, sol, kind, n)

    def _screen(self, i: int, before, sub, w_sub, moves: list) -> list:
        """[excess χ², label, kind, slips, trial, solution] of each change the trial budget
        allows, solved for SCREEN_ITER iterations on the run alone."""
        results = []
        for label, steps, kind, n in moves[: self.budget - self.trials]:
            self.trials += 1
            self.tried.add((i, _local(before, steps)))
            trial, sol, f = try_sequence(sub, w_sub, {0: np.array(steps, int)}, self.model, sub.values,
                                         self.screen, self.say)
            self.its, self.wall = self.its + sol["iterations"], self.wall + sol["wall_s"]
            if trial is not None:
                results.append([f, label, kind, n, trial, sol])
        return results

    def _finish(self, results: list) -> list:
        """The SCREEN_KEEP best screened changes solved on to TRIAL_ITER iterations; the
        best of all then."""
        rank = lambda c: c[0] if np.isfinite(c[0]) else np.inf  # noqa: E731
        for c in sorted(results, key=rank)[:SCREEN_KEEP]:
            if np.isfinite(c[0]):
                more, c[0] = continue_trial(c[4], c[5], self.opts, TRIAL_ITER - SCREEN_ITER)
                if more is not None:  # (its χ², even if higher: one iteration's may not be feasible)
                    self.its, self.wall, c[5] = self.its + more["iterations"], self.wall + more["wall_s"], more
        return min(results, key=rank)

    def _keep(self, i: int, before, trial, sol, kind: str, n: int) -> None:
        """A change kept: its run converged alone and taken into the whole problem (unless
        that cannot be rebuilt), the change's undoing marked as tried."""
        full, adopted, it_full, s_full = keep_trial(self.prob, self.best, i, trial, sol, self.model, self.values,
                                                    self.opts, self.say)
        self.its, self.wall = self.its + it_full, self.wall + s_full
        if full is None:
            return
        self.counts[kind] += n
        self.prob, self.best, self.pending = full, adopted, True
        self.tried.add((i, _local(self.prob.runs[i].trigger_steps, before)))  # (its undoing)
        self.r_now = self.prob.residuals(self.best["w"])
