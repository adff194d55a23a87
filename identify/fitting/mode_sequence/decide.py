"""The mode sequence decided by the data: slip triggers moved where their residuals put
them, missed slips inserted, and the sequence as detected kept where a change does not pay."""

from __future__ import annotations

import logging

import numpy as np

from identify.fitting.mode_sequence.missed import missed_slips
from identify.fitting.mode_sequence.passes import (
    ambiguous_triggers,
    batch_triggers,
    excess_chi2,
    misfit_triggers,
    with_triggers,
)
from identify.fitting.suspect import NOISE_P, suspect_reason

log = logging.getLogger(__name__)


def _missed(prob, w, passes) -> tuple[dict, int]:
    """The missed slips to insert at ``w``, when the ``missed`` pass is on."""
    return missed_slips(prob, w) if "missed" in passes else ({}, 0)


def decide_sequence(prob, best: dict, model, values: dict, opts, say, fresh_start: dict | None = None):
    """The mode sequence decided against the model from a solution ``best`` of ``prob``:
    triggers the model places a step or two off moved (the frames taken while the block
    moved left out), missed slips inserted, runs with many triggers a step off by their
    residuals given one trial each, then the detector's ambiguous triggers and whatever
    still misfits tried (:mod:`identify.fitting.mode_sequence.passes`), each change re-solved.
    Returns (problem, solution) with the counts in ``triggers_moved``, ``slips_inserted``
    and ``slips_removed``, and in ``restarts`` each solve after inserted slips
    (:func:`after_insertion`). ``fresh_start`` (parameter values): after inserting slips,
    solve afresh from the staged start of those values (:func:`fit` passes its start).
    The diagnosis calls it again for a model with a named effect, whose sequence the
    baseline had bent to absorb the effect. Should the decided sequence end worse than
    ``best`` (:data:`SEQUENCE_SLACK`), ``prob`` and ``best`` are returned instead, with
    what was not kept in ``sequence_not_kept``."""
    # the mode sequence: move triggers the model places a step or two off, and leave
    # out the frames taken while the block moved; re-solve until nothing moves
    # (a slip the detection missed is inserted where the model predicts it and the
    # frames show it, once no trigger moves any more; in the first round, together
    # with the moves, when they do not touch the plateaus it splits: with_insertions)
    refined = inserted = 0
    restarts: list[dict] = []  # the solves after inserted slips (after_insertion)
    prob0, best0 = prob, best
    passes = opts.sequence_passes
    for round_ in range(6 if {"triggers", "missed"} & set(passes) else 0):
        changes, n_moved = prob.refine_triggers(best["w"]) if "triggers" in passes else ({}, 0)
        n_added = 0
        if n_moved == 0:
            changes, n_added = _missed(prob, best["w"], passes)
        elif round_ == 0:
            changes, n_moved, n_added = with_insertions(prob, changes, n_moved, *_missed(prob, best["w"], passes))
        if round_ > 0 and n_moved + n_added == 0:
            break
        refined += n_moved
        inserted += n_added
        say(f"mode sequence: {n_moved} slip trigger(s) moved, {n_added} missed slip(s) inserted; re-solving")
        prob, w_next = with_triggers(prob, best["w"], changes, model, values, opts, say)
        if n_added and opts.staged_start and fresh_start is not None:
            sol = after_insertion(prob, w_next, fresh_start, int(n_added), opts, restarts)
        else:
            sol = prob.solve(w_next, loose=True)  # (the next round decides on it: LOOSE_STAT_TOL)
        sol["iterations"] += best["iterations"]
        sol["wall_s"] += best["wall_s"]
        best = sol
    # then the detector's ambiguous triggers, against the repaired sequence (tried before
    # it, on merged slips, they moved correct triggers: calibration seeds 1 and 4)
    # (its kept changes are solved at held parameters; the misfit pass solves them jointly)
    # (first, the runs with many triggers a step off by their residuals, each in one trial)
    prob, best, n_batch = batch_triggers(prob, best, model, values, opts, say)
    prob, best, n_alt = ambiguous_triggers(prob, best, model, values, opts, say)
    # last, whatever the local scores and the detector left where the model's triggers misfit
    prob, best, n_seq = misfit_triggers(prob, best, model, values, opts, say, unsolved=n_alt + n_batch > 0)
    if best.get("loose"):  # no pass re-solved it: the sequence is settled, solved fully now
        say("the mode sequence settled: solving to the full tolerance")
        best = full_tolerance(prob, best)
    moved, ins, rem = refined + n_batch + n_alt + n_seq["moved"], inserted + n_seq["inserted"], n_seq["removed"]
    worse = worse_sequence(prob0, best0, prob, best)
    if worse is not None:
        say(f"the mode sequence as detected kept: the changes ({moved} trigger(s) moved, {ins} slip(s) inserted, "
            f"{rem} removed) ended with excess χ² {worse['excess_after']:.6g} against {worse['excess_before']:.6g}")
        spent = dict(iterations=best["iterations"], wall_s=best["wall_s"])  # (cumulative: every round's solves)
        prob, best = prob0, (full_tolerance(prob0, best0) if best0.get("loose") else dict(best0))
        if best0.get("loose"):
            spent = {k: spent[k] + best[k] - best0[k] for k in spent}
        best.update(spent)
        best["sequence_not_kept"] = dict(worse, triggers_moved=moved, slips_inserted=ins, slips_removed=rem)
        moved = ins = rem = 0
        restarts = []
    best["triggers_moved"], best["slips_inserted"], best["slips_removed"] = moved, ins, rem
    best["restarts"] = restarts
    return prob, best


SEQUENCE_SLACK = 2.0
"""The mode-sequence changes a fit decides (:func:`decide_sequence`) are each meant to
lower χ²; all of them together ending with an excess χ² (χ² − observations, comparable
across sequences) more than this above the solution they started from are undone, that
solution kept. Why: on data the model cannot follow, each round's trigger moves chase
the misfit. Measured (rejuvenation withheld at dc = 0.3 µm, the exponential baseline, 7
runs): the first solve ended at χ² 21 208, continuous to 1e-7 µm; 57 trigger moves and 5
insertions later the fit ended `Line_Search_Failed` at χ² 56 498, 0.15 µm off
continuity, ½χ² 3e5 from its Gauss–Newton solution (887 iterations, 557 s)."""


SEQUENCE_FEAS_UM = 1e-3
"""... and only when the solution it started from is continuous to this (1 nm, 1/90 of the
camera noise) or at least as continuous as the end: a point off continuity can have a
lower χ² than the model's own, which is no reason to go back to it."""


def worse_sequence(prob0, best0, prob, best, slack: float = SEQUENCE_SLACK) -> dict | None:
    """The excess χ² (and continuity, µm) before and after when the decided sequence's
    solution is worse than the one it started from (by more than ``slack``, with
    :data:`SEQUENCE_FEAS_UM`), or not finite; else None. The one rule for both places a
    sequence is decided: a fit (:func:`decide_sequence`, :data:`SEQUENCE_SLACK`), and the
    diagnosis deciding it again for a model with a named effect (slack 0: a change must
    lower χ² to be adopted, since the named effect's scores were measured without it)."""
    try:
        r0, g0 = prob0.evaluate(best0["w"])
        r1, g1 = prob.evaluate(best["w"])
    except Exception:  # (either cannot be evaluated: no comparison, the sequence stands)
        return None
    e0, e1 = excess_chi2(prob0, r0), excess_chi2(prob, r1)
    f0 = float(np.abs(g0).max()) if g0.size else 0.0
    f1 = float(np.abs(g1).max()) if g1.size else 0.0
    if not (np.isfinite(e0) and np.isfinite(f0)):
        return None
    if np.isfinite(e1) and np.isfinite(f1):  # (an end not finite is worse, whatever the start)
        if e1 <= e0 + slack:
            return None
        if f0 > max(f1, SEQUENCE_FEAS_UM):
            return None  # the start was further off continuity: its lower χ² is not the model's
    return dict(excess_before=float(e0), excess_after=float(e1), continuity_before_um=f0, continuity_after_um=f1)


def full_tolerance(prob, best: dict) -> dict:
    """A loose solution (``Problem.solve(loose=True)``) solved on to the full tolerances;
    if that fails, the loose point stands, reported as not converged."""
    failed = {k: v for k, v in best.items() if k != "loose"}
    failed.update(success=False, status=f"{best.get('status')} (loose); the full-tolerance solve failed")
    try:
        sol = prob.solve(best["w"])
    except Exception as err:
        log.info("the full-tolerance solve after the mode sequence failed: %s", err)
        return failed
    spent = dict(iterations=best["iterations"] + sol["iterations"], wall_s=best["wall_s"] + sol["wall_s"])
    return dict(sol, **spent) if np.isfinite(sol["f"]) else dict(failed, **spent)


def with_insertions(prob, moved: dict, n_moved: int, inserted: dict, n_inserted: int) -> tuple[dict, int, int]:
    """The trigger moves ``moved`` ({run: steps}) with the slips of ``inserted`` (found
    at the same solution, :func:`identify.fitting.mode_sequence.missed.missed_slips`) added: (changes, number
    moved, number inserted). A move that meets or crosses an inserted slip is not made
    (the two disagree about one slip; the insertion has the frames' 3σ jump for it, the
    move only a local score on plateaus the missed slip bent); the next round's scores,
    on the repaired sequence, decide again whether it moves.

    Why: an insertion is followed by a solve from a fresh start, which makes the solve
    after the moves redundant. Measured on the 10-run speed benchmark (2026-11-25): the
    first round had moved 3 triggers and re-solved (18 s), the second inserted 6 slips
    and solved afresh (64 s). Now the first round moves 2 and inserts 7, one move left
    to the next round; the seventh slip, found on plateaus a misplaced trigger bent, is
    removed again by the misfit pass (identify.fitting.mode_sequence.passes), which ends with every trigger
    fitting: 163 -> 135 s, the same profiler."""
    if not n_inserted:
        return moved, n_moved, 0
    out, n_kept = dict(moved), n_moved
    for ri, steps in inserted.items():
        old = np.asarray(prob.runs[ri].trigger_steps, int)
        added = np.setdiff1d(steps, old)
        base = np.asarray(moved.get(ri, old), int).copy()
        if len(base) == len(old):
            lo, hi = np.minimum(old, base), np.maximum(old, base)
            meets = ((added[None, :] >= lo[:, None]) & (added[None, :] <= hi[:, None])).any(axis=1) & (base != old)
            if meets.any():
                log.info("run %d: %d trigger move(s) meeting the missed slips inserted left to the next round",
                         ri, int(meets.sum()))
                n_kept -= int(meets.sum())
                base[meets] = old[meets]
        new = np.union1d(base, added).astype(int)
        if len(new) != len(base) + len(added) or np.any(np.diff(base) <= 0):
            log.info("missed slips in run %d left to the next round: the moves collide with them", ri)
            return moved, n_moved, 0
        out[ri] = new
    return out, n_kept, int(n_inserted)


def after_insertion(prob, w_warm, fresh_start: dict, n_added: int, opts, restarts: list) -> dict:
    """The solve after inserting missed slips: from a fresh staged start of ``fresh_start``
    on the repaired sequence, and from the warm point ``w_warm`` (the solution before,
    carried over) only when that looks wrong (:func:`suspect_reason`; a solve that did not
    converge but fits within the noise is taken, :data:`NOISE_P`); the better is kept,
    and the comparison appended to ``restarts``.

    Why fresh first: a missed slip bends the solution before it (and the staged start
    made from the merged plateaus) far off. On the 10-run speed benchmark the warm solve
    ended in another basin, ½χ² 1238.74 against the fresh solve's 1237.28; over 14
    calibration repeats with both solves (9 insertions) the two ended within 0.003 of
    each other. Why the warm one when the fresh looks wrong: in the 50-repeat
    calibration it was kept 3 times of 5, once by 881 of ½χ² (seed 30, the fresh solve
    Stalled at reduced χ² 1.55). Solving both always cost a second solve of the whole
    problem: ~100 s of the 10-run fit (docs/engineering-notes.md, Speed)."""
    from identify.fitting.start import staged_start

    try:
        fresh, _ = staged_start(prob, fresh_start, seed=opts.seed or 0)
        sol = prob.solve(prob.initial_w(fresh), loose=True)
    except Exception as err:  # the warm solve decides
        log.info("fresh start after inserting slips failed: %s", err)
        sol = dict(w=w_warm, f=np.inf, status=f"failed: {err}", success=False, iterations=0, wall_s=0.0)
    rec = dict(slips_inserted=n_added, fresh_half_chi2=float(sol["f"]),
               fresh_suspect=suspect_reason(prob, sol, noise_p=NOISE_P),
               fresh_status=str(sol.get("status")), fresh_s=float(sol["wall_s"]), warm_half_chi2=None, kept="fresh")
    if rec["fresh_suspect"]:
        warm = prob.solve(w_warm, loose=True)
        rec["warm_half_chi2"] = float(warm["f"])
        its, wall = sol["iterations"] + warm["iterations"], sol["wall_s"] + warm["wall_s"]
        if np.isfinite(warm["f"]) and not warm["f"] >= sol["f"]:
            sol, rec["kept"] = warm, "warm"
        sol = dict(sol, iterations=its, wall_s=wall)
    log.info("after inserting %d slip(s): fresh solve ½χ² %.6g%s", n_added, rec["fresh_half_chi2"],
             f" ({rec['fresh_suspect']}; warm {rec['warm_half_chi2']:.6g}, {rec['kept']} kept)"
             if rec["fresh_suspect"] else "")
    restarts.append(rec)
    return sol
