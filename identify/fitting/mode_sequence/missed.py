"""Slips the event detection missed, found with the fitted model.

A slip of a few noise σ between two short plateaus is sometimes merged away by the
segmentation (measured: 1.4 % of the 3σ slips of a k = 20.3 N/m, 30 µN, 100 Hz run with
12-frame plateaus). The fit then has one plateau twice as long as the model's rest and
one "slip" twice as long as the model's arc, and bends the friction parameters to
explain both: on the calibration set the runs with a missed slip put τ, μmin and A
about 2 standard errors off, the others did not.

The detector had to scan every frame for a change of any size in either direction. The
fitted model knows where to look and what to expect: aging the contact from the end of
the previous slip, it predicts the step at which the spring force first exceeds the
capacity. Where that step lies well inside a detected plateau, the frames after it are
tested against the frames before it for a forward jump of the block, at the steps up
to that one only: a short scan, so a test little above 3σ is enough.
"""

from __future__ import annotations

import numpy as np

from identify.model.symbolic import LENGTH_UNIT

__all__ = ["best_split", "missed_slips"]

MIN_FRAMES = 3  # frames on each side of an inserted slip (the detector's shortest plateau)


def _predicted_triggers(prob, w, Y0, P) -> np.ndarray:
    """Per slip, the first step after it at which the model slips again (inf: none
    before the next detected trigger, or the run's end)."""
    model, law = prob.model, prob.law
    step = float(model.step(P))
    x = w[prob.i_x : prob.i_x + prob.P] * LENGTH_UNIT
    out = np.full(prob.E, np.inf)
    for e in range(prob.E):
        run = prob.runs[prob.ev_run[e]]
        last = prob.ev_step[e + 1] if e + 1 < prob.E and not prob.ev_first[e + 1] else run.events.steps.max() + 1
        start = prob.ev_step[e] + prob.ev_M[e]
        n = np.arange(start + 1, last, dtype=float)
        if n.size == 0:
            continue
        xp = x[prob.ev_prev[e] + 1]
        Pe = prob.run_params(P, int(prob.ev_run[e]))
        z = law.rest(np.full(n.size, Y0[1, e]), (n - start) / run.fp, Pe)
        cap = model.hold_coefficient(z, xp, Pe) * model.normal_load(Pe)
        force = model.spring_force(step * n - xp, Pe)
        over = np.nonzero(force > cap)[0]
        if over.size:
            out[e] = n[over[0]]
    return out


def best_split(prob, w: np.ndarray, e: int, upto: float = np.inf, accept=None):
    """The best place for a slip among the frames after slip e and before the next
    trigger: the two-level χ² gain n₁n₂/(n₁+n₂)·(d/σ)² of splitting them at each step
    up to ``upto`` (at least ``MIN_FRAMES`` frames each side; d > 0 the forward jump of
    the block position), among the splits ``accept(gain, d, positions tried)`` passes.
    Returns (gain, step, jump in m), or None."""
    P = prob.params(w[: prob.n_theta])
    step = float(prob.model.step(P))
    ri = int(prob.ev_run[e])
    run = prob.runs[ri]
    ev = run.events
    off = w[prob.i_off + ri] * LENGTH_UNIT if prob.n_off else 0.0
    last = prob.ev_step[e + 1] if e + 1 < prob.E and not prob.ev_first[e + 1] else np.inf
    sel = (ev.steps >= prob.ev_step[e] + prob.ev_M[e]) & (ev.steps < last)
    steps = ev.steps[sel]
    if steps.size < 2 * MIN_FRAMES:
        return None
    block = step * steps - (ev.trace.elongation[sel] - off)  # block position per frame
    cands = np.unique(steps[(steps > steps.min()) & (steps <= upto)])
    ok = accept or (lambda gain, d, tried: True)
    best = None
    for n in cands:
        after = steps >= n
        n2 = int(after.sum())
        n1 = steps.size - n2
        if n1 < MIN_FRAMES or n2 < MIN_FRAMES:
            continue
        d = block[after].mean() - block[~after].mean()
        gain = n1 * n2 / (n1 + n2) * (d / run.sigma) ** 2
        if d > 0 and ok(gain, d, cands.size) and (best is None or gain > best[0]):
            best = (float(gain), int(n), float(d))
    return best


def missed_slips(prob, w: np.ndarray, min_gain: float = 9.0):
    """Slips to insert where the fitted model predicts one inside a detected plateau and
    the frames show it.

    Per slip e, with n* the model's next trigger after it, inside the plateau that
    follows e: the best split of that plateau (:func:`best_split`) at the steps up to
    n* + 2 is kept when its jump is at least half the run's median slip and its gain ≥
    ``min_gain`` + 2·ln(positions tried) (3σ, plus the price of the scan). The model's
    step is approximate (the merged plateau's fitted position is a compromise of its
    two levels): hence the scan up to it.

    Returns ({run index: trigger steps with the insertions}, number inserted).
    """
    if not prob.E:
        return {}, 0
    P = prob.params(w[: prob.n_theta])
    Y0 = prob.arc_outputs(w)
    n_pred = _predicted_triggers(prob, w, Y0, P)
    median_slip = {}
    for ri in np.unique(prob.ev_run):
        median_slip[int(ri)] = float(np.median(Y0[0, prob.ev_run == ri])) * LENGTH_UNIT
    inserted: dict[int, list] = {}
    for e in np.nonzero(np.isfinite(n_pred))[0]:
        ri = int(prob.ev_run[e])
        split = best_split(prob, w, e, upto=n_pred[e] + 2, accept=lambda gain, d, tried, half=0.5 * median_slip[ri]: (
            d >= half and gain >= min_gain + 2.0 * np.log(max(tried, 1))))
        if split is not None:
            inserted.setdefault(ri, []).append(split[1])
    changes = {}
    for ri, new in inserted.items():
        steps = prob.runs[ri].trigger_steps
        changes[ri] = np.unique(np.concatenate([steps, np.array(new, int)])).astype(int)
    return changes, int(sum(len(v) for v in inserted.values()))
