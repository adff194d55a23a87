"""Slips that stop at a creep tail's onset: a kink of the model in its parameters.

Under the stick option a slip ends when its speed falls below the stick threshold. After
the inertial deceleration the speed dips; where the dip reaches below the threshold the
block stops within a fraction of a millisecond, where it stays just above it the block
creeps on for milliseconds first (its friction, velocity-strengthened, balancing the
spring). Between the two the dip grazes the threshold: the stop time, and with it the
slip's length and its contact's age, bend there. A solution with a slip near that point
is where the solvers stall: their steps cross the bend, which no linearisation
predicts, while the derivatives on either side of it are right.

Found by moving each slip's threshold by :data:`CREEP_MARGIN` either way: a slip whose
stop time then changes by more than :data:`BRANCH_RATIO` times changes how it stops.
Measured on the 8-run withheld-conditions set (noise seed 0), at the fit's end: of 278
slips, one changes at a 10 % margin (slip 93, run 5, 20.3 N/m, 30 µN, 100 Hz: 0.060 ms, 0.192 ms
with the threshold 10 % lower), none at 5 % or below; it is the constraint the fit's
solve left violated (1.7e-4 µm), and a scan along the solver's last step bends at it.
On seeds 1-7, whose fits converged, none at 10 %; at 20 % the same slip on three of them
(it creeps for 0.4 ms there, farther from the bend).
"""

from __future__ import annotations

import numpy as np

__all__ = ["BRANCH_RATIO", "CREEP_MARGIN", "creep_onset_mask", "creep_onsets", "onset_text",
           "threshold_stop_times"]

CREEP_MARGIN = 0.1
BRANCH_RATIO = 3.0
_LISTED = 3  # slips a report names; the rest are counted


def threshold_stop_times(arcs, A: np.ndarray, Y: np.ndarray | None = None,
                         margin: float = CREEP_MARGIN) -> np.ndarray:
    """Per arc (columns of ``A``, :class:`identify.fitting.arcs.ArcFunctions` inputs), its
    stop time (ms) at its stick threshold, ``margin`` lower and ``margin`` higher (3 × n;
    NaN for arcs without the stick option, threshold 0, which stop at a reversal).
    ``Y``: the arcs' outputs at ``A`` if known."""
    n = A.shape[1]
    T = np.full((3, n), np.nan)
    iv = arcs.index.get("v_stick")
    if not n or iv is None:
        return T
    vs = A[iv]
    cols = np.nonzero(np.isfinite(vs) & (vs > 0))[0]
    if not cols.size:
        return T
    base = A[:, cols]
    T[0, cols] = (arcs.evaluate(base) if Y is None else Y[:, cols])[2]
    for row, sign in ((1, -1.0), (2, 1.0)):
        moved = base.copy()
        moved[iv] = vs[cols] * (1.0 + sign * margin)
        T[row, cols] = arcs.evaluate(moved)[2]
    return T


def _changes_branch(T: np.ndarray) -> np.ndarray:
    """Per arc: its stop time changes by more than BRANCH_RATIO times over the three thresholds."""
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.max(T, axis=0) / np.min(T, axis=0)
        return np.all(np.isfinite(T), axis=0) & (np.min(T, axis=0) > 0) & (ratio > BRANCH_RATIO)


def creep_onset_mask(arcs, A: np.ndarray, Y: np.ndarray | None = None, margin: float = CREEP_MARGIN) -> np.ndarray:
    """Per arc: whether a stick threshold ``margin`` lower or higher changes its stop time
    by more than :data:`BRANCH_RATIO` times (its speed's dip near the threshold;
    :func:`threshold_stop_times`). Arcs without the stick option and arcs that cannot be
    integrated are False."""
    return _changes_branch(threshold_stop_times(arcs, A, Y, margin))


def creep_onsets(prob, w: np.ndarray, margin: float = CREEP_MARGIN) -> list[dict]:
    """The slips of a solved :class:`identify.fitting.problem.Problem` at ``w`` that stop
    at a creep tail's onset (:func:`creep_onset_mask`), each as a dict a report and JSON
    can carry: its run's name, its number among the run's slips (from 1), its trigger
    step, its run's conditions and its stop time (ms) at the threshold and at the
    threshold ``margin`` lower and higher."""
    if not prob.E:
        return []
    T = threshold_stop_times(prob.arcs, prob.arc_inputs(w), margin=margin)
    out = []
    for e in np.nonzero(_changes_branch(T))[0]:
        ri = int(prob.ev_run[e])
        out.append(dict(run=prob.runs[ri].name, slip=int(np.sum(prob.ev_run[:e] == ri)) + 1,
                        trigger_step=int(prob.ev_step[e]), spring_constant_N_per_m=float(prob.ev_k[e]),
                        normal_load_uN=float(prob.ev_Nb[e]) * 1e6, step_frequency_Hz=float(prob.ev_fp[e]),
                        stop_ms=float(T[0, e]), stop_ms_threshold_lower=float(T[1, e]),
                        stop_ms_threshold_higher=float(T[2, e]), margin=float(margin)))
    return out


def onset_text(onsets: list[dict]) -> str:
    """The report's words for :func:`creep_onsets` ("" when there are none)."""
    if not onsets:
        return ""
    named = "; ".join(
        f"slip {o['slip']} of {o['run']} (step {o['trigger_step']}: stops in {o['stop_ms']:.3g} ms, "
        f"{o['stop_ms_threshold_lower']:.3g} ms with the stick threshold {100 * o['margin']:.0f} % lower, "
        f"{o['stop_ms_threshold_higher']:.3g} ms {100 * o['margin']:.0f} % higher)" for o in onsets[:_LISTED])
    more = f" and {len(onsets) - _LISTED} more" if len(onsets) > _LISTED else ""
    return f"at a creep tail's onset, a kink of the model the solvers cannot step across: {named}{more}"
