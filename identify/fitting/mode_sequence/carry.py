"""A mode sequence changed: the problem rebuilt for the new trigger steps, with the
previous solution carried over to it (:func:`with_triggers`) so that a short re-solve
starts where the old sequence's solution stood, and the arcs it did not change are not
integrated again.
"""

from __future__ import annotations

import numpy as np

from identify.fitting.problem import Problem
from identify.fitting.rundata import make_run_data
from identify.model.symbolic import LENGTH_UNIT

__all__ = ["CARRY_START_TOL", "with_triggers"]


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


def with_triggers(prob, w, changes: dict, model, values, opts, say):
    """The NLP with the trigger steps of ``changes`` ({run index: steps}) and ``w``
    carried over to it (the frames taken while a block moved carried with their slips)."""
    moving = prob.moving_times(w)
    ramps = prob.slip_ramps(w) if prob.D else {}
    new_runs = []
    for i, r in enumerate(prob.runs):
        if r.kind != "events":
            new_runs.append(r)
            continue
        steps = changes.get(i, r.trigger_steps)
        new_runs.append(make_run_data(r.events, triggers=steps, moving_s=_carry(r.trigger_steps, moving.get(i), steps),
                                      drops=r.drops, ramp_s=_carry(r.trigger_steps, ramps.get(i), steps)))
    new = Problem(new_runs, model, values, opts)
    new.ev_M = _carry_horizons(prob, new)
    new.counter = prob.counter  # the timing report covers every solve, not just the last
    new.progress = say
    new.build()
    return new, new.settle_arcs(_carry_solution(prob, new, w), keep=CARRY_START_TOL)
